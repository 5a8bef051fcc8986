"""Atomic output files and folders, and the one output policy (``docs/inputs-and-errors.md``).

All or nothing: a command declares its outputs in one :class:`OutputTransaction` before any
work; each is written to a temporary twin in its own folder and all are renamed into place
together, or removed on failure. An existing file or non-empty folder is replaced only with
``--overwrite``, checked up front and again at commit by renames that cannot clobber.
Temporary names and the cleaning of stale ones: :mod:`psfkit.io.temps`.
"""

from __future__ import annotations

import contextlib
import ctypes
import errno
import os
import tempfile
from collections.abc import Iterable, Iterator
from contextvars import ContextVar
from pathlib import Path

from psfkit.errors import InvalidInputError
from psfkit.io.temps import TEMP_TAG, clean_once, owner, remove_path, remove_stale_temps

__all__ = ["TEMP_TAG", "OutputExistsError", "OutputTransaction", "atomic_directory",
           "atomic_file", "check_output", "protected_inputs", "remove_stale_temps",
           "rename_noreplace"]

_RENAME_NOREPLACE = 1
_AT_FDCWD = -100


class OutputExistsError(InvalidInputError):
    """An output exists and would be replaced without ``--overwrite``."""


#: The inputs of the running command, as ``(given, resolved)`` paths (see
#: :func:`protected_inputs`).
_INPUTS: ContextVar[tuple[tuple[str, Path], ...]] = ContextVar("psfkit_inputs", default=())


@contextlib.contextmanager
def protected_inputs(paths: Iterable[str | os.PathLike]) -> Iterator[None]:
    """Within the block no output may be one of the existing ``paths``, a folder holding one,
    or an existing path inside one, even with ``overwrite`` (``report GRID --out GRID``)."""
    given = [os.fspath(p) for p in paths]
    token = _INPUTS.set(tuple((p, Path(p).resolve()) for p in given if p and os.path.lexists(p)))
    try:
        yield
    finally:
        _INPUTS.reset(token)


def _check_not_an_input(path: Path, overwrite: bool) -> None:
    """Refuse an output that is an input, holds one, or (with ``overwrite``) is an existing
    path inside an input folder; a new name inside is allowed."""
    if any(TEMP_TAG in part for part in path.parts):   # inside an output being written
        return
    target = path.resolve()
    for given, source in _INPUTS.get():
        if source == target or target in source.parents:
            relation = "is" if source == target else "holds"
        elif overwrite and source in target.parents and os.path.lexists(target):
            relation = "is part of"
        else:
            continue
        raise InvalidInputError(f"{path}: {relation} the input {given}; an output never "
                                "replaces an input, even with --overwrite (choose another "
                                "path)")


_UMASK = os.umask(0)   # the only way to read it; done once, at import, before any threads
os.umask(_UMASK)


# ------------------------------------------------------------------------ no-clobber rename

def _load_renameat2():
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        fn = libc.renameat2
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p,
                   ctypes.c_uint]
    fn.restype = ctypes.c_int
    return fn


_renameat2 = _load_renameat2()


def rename_noreplace(src: Path, dst: Path) -> None:
    """Rename the file ``src`` to ``dst``; :class:`FileExistsError` if ``dst`` exists.

    ``renameat2(RENAME_NOREPLACE)``, else link + unlink, else (no hard links) check + rename.
    """
    if _renameat2 is not None:
        if _renameat2(_AT_FDCWD, os.fsencode(src), _AT_FDCWD, os.fsencode(dst),
                      _RENAME_NOREPLACE) == 0:
            return
        err = ctypes.get_errno()
        if err not in (errno.ENOSYS, errno.EINVAL, errno.ENOTSUP, errno.EPERM):
            raise OSError(err, os.strerror(err), str(dst))
    try:
        os.link(src, dst)
    except FileExistsError:
        raise
    except OSError:
        if os.path.lexists(dst):
            raise FileExistsError(errno.EEXIST, os.strerror(errno.EEXIST), str(dst)) from None
        os.rename(src, dst)
        return
    os.unlink(src)


# ------------------------------------------------------------------------------ the policy

def _exists_error(path: Path, what: str) -> OutputExistsError:
    return OutputExistsError(f"{path}: {what} (use --overwrite to replace it)")


def check_output(path: str | os.PathLike, kind: str = "file", overwrite: bool = False) -> Path:
    """Refuse an output path (``kind``: ``"file"`` or ``"folder"``) before any work:
    :class:`OutputExistsError` for an existing file or non-empty folder without ``overwrite``,
    :class:`~psfkit.errors.InvalidInputError` for a path of the other kind or a bad parent."""
    path = Path(path)
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise InvalidInputError(f"{path}: {parent} exists and is not a directory")
    if kind == "file":
        if path.is_dir():
            raise InvalidInputError(f"{path}: is a directory, expected a file path")
        if os.path.lexists(path) and not overwrite:
            raise _exists_error(path, "output file exists")
    else:
        if os.path.lexists(path) and not path.is_dir():
            raise InvalidInputError(f"{path}: exists and is not a directory")
        if path.is_dir() and any(path.iterdir()) and not overwrite:
            raise _exists_error(path, "output folder exists and is not empty")
    return path


def _prepare_parent(path: Path) -> list[Path]:
    """Create the missing folders above ``path``; returns them, outermost first."""
    missing = [p for p in reversed(path.parents) if not p.exists()]
    try:
        for folder in missing:
            folder.mkdir()
    except FileExistsError:
        pass   # created meanwhile by someone else
    except OSError as exc:
        _remove_empty(missing)
        raise InvalidInputError(f"{path}: cannot create its folder "
                                f"({exc.strerror or exc})") from None
    if not path.parent.is_dir():
        raise InvalidInputError(f"{path}: {path.parent} exists and is not a directory")
    return missing


def _remove_empty(folders: list[Path]) -> None:
    for folder in reversed(folders):
        with contextlib.suppress(OSError):
            folder.rmdir()


def _temp_for(path: Path, kind: str, created: list[Path]) -> Path:
    """Create the empty temporary twin of ``path`` next to it; new folders go to ``created``."""
    created += _prepare_parent(path)
    clean_once(path.parent)
    try:
        if kind == "file":
            fd, name = tempfile.mkstemp(prefix=f".{path.stem}{TEMP_TAG}{owner()}.",
                                        suffix=path.suffix, dir=path.parent)
            os.close(fd)
        else:
            name = tempfile.mkdtemp(prefix=f".{path.name}{TEMP_TAG}{owner()}.",
                                    dir=path.parent)
    except OSError as exc:
        _remove_empty(created)
        # name the user's path, not the hidden temporary one
        raise InvalidInputError(f"{path}: cannot write here ({exc.strerror or exc})") from None
    return Path(name)


class _Output:
    def __init__(self, path: Path, kind: str, overwrite: bool) -> None:
        self.path, self.kind, self.overwrite = path, kind, overwrite
        self.created: list[Path] = []   # parent folders made for it, removed on failure
        self.temp = _temp_for(path, kind, self.created)
        self.backup: Path | None = None   # the replaced output, kept until all are committed
        self.committed = False

    def commit(self) -> None:
        path, temp = self.path, self.temp
        os.chmod(temp, (0o666 if self.kind == "file" else 0o777) & ~_UMASK)  # mkstemp: 0600
        check_output(path, self.kind, self.overwrite)   # again: something may have appeared
        try:
            if self.kind == "file":
                self._commit_file()
            else:
                self._commit_folder()
        except OSError as exc:
            clobber = (FileExistsError, IsADirectoryError, NotADirectoryError)
            if isinstance(exc, clobber) or exc.errno in (errno.ENOTEMPTY, errno.EEXIST):
                raise _exists_error(path, "output was created meanwhile by another run") from exc
            raise InvalidInputError(f"{path}: cannot write here ({exc.strerror or exc})"
                                    ) from None
        self.committed = True

    def _commit_file(self) -> None:
        path, temp = self.path, self.temp
        if not self.overwrite or not os.path.lexists(path):
            rename_noreplace(temp, path)
            return
        with contextlib.suppress(OSError):   # a hard-linked backup allows a roll-back
            backup = path.with_name(f".{path.stem}{TEMP_TAG}{owner()}.old{path.suffix}")
            backup.unlink(missing_ok=True)
            os.link(path, backup)
            self.backup = backup
        os.replace(temp, path)   # atomic replacement: the path never disappears

    def _commit_folder(self) -> None:
        path, temp = self.path, self.temp
        if self.overwrite and path.is_dir() and any(path.iterdir()):   # move the old aside
            backup = path.with_name(f".{path.name}{TEMP_TAG}{owner()}.old")
            remove_path(backup)
            os.rename(path, backup)
            self.backup = backup
            try:
                os.rename(temp, path)
            except OSError:
                os.rename(backup, path)
                self.backup = None
                raise
            return
        # absent or empty: rename() replaces at most an empty folder and fails on a file or
        # a non-empty folder (ENOTDIR / ENOTEMPTY / EEXIST), so nothing can be clobbered
        os.rename(temp, path)

    def roll_back(self) -> None:
        if self.committed:
            if self.backup is not None and self.kind == "file":
                os.replace(self.backup, self.path)
            else:
                remove_path(self.path)
                if self.backup is not None:
                    os.rename(self.backup, self.path)
            self.backup = None
        remove_path(self.temp)

    def finish(self) -> None:
        if self.backup is not None:
            remove_path(self.backup)


class OutputTransaction:
    """The outputs of one command: declared first, written to temporaries, committed together.

    Examples
    --------
    >>> with OutputTransaction(overwrite=args.overwrite) as outputs:   # doctest: +SKIP
    ...     figures = outputs.folder(args.figures)      # checked now, before any work
    ...     kernels = outputs.file(args.out)
    ...     result = fit(...)                           # the long computation
    ...     write_figures(result, figures)              # into the temporaries
    ...     save_kernels(kernels, result.model)
    ... # here both appear, or (on any error, Ctrl-C or SIGTERM) neither does

    Parameters
    ----------
    overwrite : bool
        Replace existing outputs (``--overwrite``); default: refuse them.
    """

    def __init__(self, overwrite: bool = False) -> None:
        self.overwrite = overwrite
        self._outputs: list[_Output] = []

    def _declare(self, path: str | os.PathLike, kind: str) -> Path:
        if os.fspath(path) == "":   # Path("") is the current folder, never meant as an output
            raise InvalidInputError(f"an empty path was given for an output {kind}")
        path = Path(path)
        _check_not_an_input(path, self.overwrite)
        if any(o.path.resolve() == path.resolve() for o in self._outputs):
            raise InvalidInputError(f"{path}: given for two outputs of one command")
        check_output(path, kind, self.overwrite)
        output = _Output(path, kind, self.overwrite)
        self._outputs.append(output)
        return output.temp

    def file(self, path: str | os.PathLike) -> Path:
        """Declare an output file; returns the temporary path to write (same suffix)."""
        return self._declare(path, "file")

    def folder(self, path: str | os.PathLike) -> Path:
        """Declare an output folder; returns the (empty) temporary folder to fill."""
        return self._declare(path, "folder")

    def commit(self) -> None:
        """Rename every temporary into place; if one fails, undo those already done."""
        for output in self._outputs:
            check_output(output.path, output.kind, self.overwrite)   # all, before any rename
        done = []
        try:
            for output in self._outputs:
                output.commit()
                done.append(output)
        except BaseException:
            for output in reversed(done):
                with contextlib.suppress(OSError):
                    output.roll_back()
            raise
        for output in self._outputs:
            output.finish()
        self._outputs = []

    def discard(self) -> None:
        """Remove every temporary (on failure); nothing appears at the final paths."""
        for output in reversed(self._outputs):
            remove_path(output.temp)
            _remove_empty(output.created)
        self._outputs = []

    def _target_of(self, exc: BaseException | None) -> Path | None:
        """The output whose hidden temporary an :class:`OSError` names, if any."""
        name = getattr(exc, "filename", None) if isinstance(exc, OSError) else None
        if not name or TEMP_TAG not in str(name):
            return None
        failed = Path(os.fsdecode(name))
        for output in self._outputs:
            if (failed == output.temp or output.temp in failed.parents
                    or failed.name.startswith(f".{output.temp.stem}")):
                return output.path
        return None

    def __enter__(self) -> OutputTransaction:
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is not None:
            target = self._target_of(exc)
            self.discard()
            if target is not None:   # e.g. disk full while writing: name the user's path
                raise InvalidInputError(f"{target}: cannot write here "
                                        f"({exc.strerror or exc})") from None
            return
        try:
            self.commit()
        finally:
            self.discard()


# ------------------------------------------------------------------- single-output helpers

@contextlib.contextmanager
def atomic_file(path: str | os.PathLike, overwrite: bool = True) -> Iterator[Path]:
    """Yield a temporary path (``path``'s suffix) that becomes ``path`` on success.

    ``overwrite`` defaults to True: library code rewrites its own files (checkpoints).
    """
    with OutputTransaction(overwrite=overwrite) as outputs:
        yield outputs.file(path)


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield an empty temporary folder that becomes ``path`` when the block succeeds; an
    existing non-empty ``path`` is refused up front unless ``overwrite``."""
    with OutputTransaction(overwrite=overwrite) as outputs:
        yield outputs.folder(path)
