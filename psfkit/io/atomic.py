"""Atomic creation of output files and folders.

Outputs are first written under a temporary name in the destination's own directory and
renamed into place only once complete, so an interrupted or failed run never leaves a
half-written result behind (a rename within one file system is atomic).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from psfkit.errors import InvalidInputError


def _read_umask() -> int:
    mask = os.umask(0)  # the only way to read it; done once, at import, before any threads
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def _prepare_parent(path: Path) -> None:
    parent = path.parent
    if parent.exists() and not parent.is_dir():
        raise InvalidInputError(f"{parent}: exists and is not a directory")
    parent.mkdir(parents=True, exist_ok=True)


@contextlib.contextmanager
def atomic_file(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path; on success rename it to ``path``, on error delete it.

    The temporary file keeps the suffix of ``path`` so that writers choosing their
    format from the extension (numpy, matplotlib, tifffile) behave as for ``path``.
    """
    path = Path(path)
    if path.is_dir():
        raise InvalidInputError(f"{path}: is a directory, expected a file path")
    _prepare_parent(path)
    fd, tmp_name = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=f".tmp{path.suffix}",
                                    dir=path.parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        # mkstemp creates 0600 files; give the result the permissions of a normal new file
        os.chmod(tmp, 0o666 & ~_UMASK)
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


@contextlib.contextmanager
def atomic_directory(path: str | os.PathLike, overwrite: bool = False) -> Iterator[Path]:
    """Yield an empty temporary folder that becomes ``path`` when the block succeeds.

    Parameters
    ----------
    path : path-like
        Final folder.
    overwrite : bool
        Replace an existing ``path``. Without it an existing non-empty ``path`` is an error,
        raised before any work is done.
    """
    path = Path(path)
    if path.exists():
        if not path.is_dir():
            raise InvalidInputError(f"{path}: exists and is not a directory")
        if any(path.iterdir()) and not overwrite:
            raise InvalidInputError(
                f"{path}: output folder exists and is not empty (use --overwrite to replace it)")
    _prepare_parent(path)
    tmp = Path(tempfile.mkdtemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent))
    try:
        yield tmp
        os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp creates 0700 folders
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    old = None
    if path.exists():
        old = path.with_name(f".{path.name}.old-{os.getpid()}")
        os.replace(path, old)
    os.replace(tmp, path)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
