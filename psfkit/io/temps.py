"""The toolkit's temporary outputs, ``.<name>.psfkit-tmp.<pid>@<host>.<random>[<suffix>]``
(``<host>``: 6 hex digits of the machine's name), and removing those of killed runs."""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import socket
import sys
import time
from pathlib import Path

TEMP_TAG = ".psfkit-tmp."
"""Marks the toolkit's temporary outputs; followed by ``<pid>@<host>``."""
STALE_AGE_S = 24 * 3600.0
"""A temporary output older than this is stale even if its process id is alive (the id may
have been reused, or belong to another machine sharing the folder)."""
_TEMP_PID = re.compile(re.escape(TEMP_TAG) + r"(\d+)@([0-9a-f]{6})\.")
HOST = hashlib.sha1(socket.gethostname().encode()).hexdigest()[:6]
# ".<name>.psfkit-tmp.<pid>@<host>.<8 random>": group 1 is the output's name (its suffix
# follows the random part)
_TEMP_NAME = re.compile(r"\.([^/\s]*?)" + re.escape(TEMP_TAG) + r"\d+@[0-9a-f]{6}\.[a-z0-9_]{8}")


def public_name(text: str) -> str:
    """``text`` with every temporary output name replaced by the name of the output it
    becomes, so that a message never names a hidden file the user cannot see."""
    return _TEMP_NAME.sub(r"\1", text)


def owner(pid: int | None = None) -> str:
    """``<pid>@<host>`` of this process (or of ``pid``), as written into temporary names."""
    return f"{os.getpid() if pid is None else pid}@{HOST}"


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except PermissionError:  # alive, another user's
        return True
    except OSError:          # ProcessLookupError: gone
        return False
    return True


def remove_path(path: Path) -> None:
    """Delete a file, link or folder tree (what is already gone is fine)."""
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path, ignore_errors=True)
    else:
        path.unlink(missing_ok=True)


def remove_stale_temps(folder: str | os.PathLike, quiet: bool = False) -> list[Path]:
    """Remove the temporary outputs in ``folder`` whose process on this machine has ended or
    that are older than :data:`STALE_AGE_S`; says so on stderr unless ``quiet``. Returns the
    removed paths."""
    folder = Path(folder)
    removed = []
    try:
        entries = list(os.scandir(folder))
    except OSError:
        return removed
    now = time.time()
    for entry in entries:
        match = _TEMP_PID.search(entry.name)
        if match is None or not entry.name.startswith("."):
            continue
        try:
            age = now - entry.stat(follow_symlinks=False).st_mtime
        except OSError:
            continue
        here = match.group(2) == HOST
        if age < STALE_AGE_S and (not here or _pid_alive(int(match.group(1)))):
            continue
        path = Path(entry.path)
        remove_path(path)
        removed.append(path)
    if removed and not quiet:
        names = ", ".join(p.name for p in removed[:3]) + (" ..." if len(removed) > 3 else "")
        print(f"note: removed {len(removed)} stale temporary output(s) of interrupted runs "
              f"in {folder}: {names}", file=sys.stderr)
    return removed


_CLEANED: set[Path] = set()


def clean_once(folder: Path) -> None:
    """:func:`remove_stale_temps` once per folder and process (writers run often)."""
    key = folder.resolve()
    if key not in _CLEANED:
        _CLEANED.add(key)
        remove_stale_temps(folder)
