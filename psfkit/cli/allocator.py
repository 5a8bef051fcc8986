"""Process-wide memory-allocator settings for the image-heavy commands.

A full-resolution PSF pass allocates and frees a few dozen 5–20 MB arrays per grid position.
glibc's ``malloc`` serves blocks that large with fresh ``mmap`` pages and gives them back to
the system on ``free`` (until its adaptive threshold has grown), so each array is page-faulted
in anew: about 2 s of system time in a 9×9 ``fit-eigen`` (10–15 % of its CPU time). Keeping
freed blocks up to 32 MiB in the heap for reuse removes about half of it, for up to a few
hundred MB more resident memory at the peak. Other C libraries (macOS, Windows, musl) are left
as they are.
"""

from __future__ import annotations

import ctypes
import sys

M_TRIM_THRESHOLD = -1        # glibc mallopt parameters (malloc.h)
M_MMAP_THRESHOLD = -3
MMAP_THRESHOLD = 32 * 2**20  # glibc's largest accepted value on 64-bit systems
TRIM_THRESHOLD = 1024 * 2**20


def reuse_freed_memory() -> bool:
    """Ask glibc's ``malloc`` to keep freed blocks up to 32 MiB for reuse (module docstring).

    Returns whether the settings took effect (``False`` where the C library is not glibc:
    then nothing changes).
    """
    if not sys.platform.startswith("linux"):
        return False
    try:
        mallopt = ctypes.CDLL(None).mallopt       # the process's own C library
    except (OSError, AttributeError, TypeError):
        return False
    mallopt.argtypes = [ctypes.c_int, ctypes.c_int]
    mallopt.restype = ctypes.c_int
    return bool(mallopt(M_MMAP_THRESHOLD, MMAP_THRESHOLD)) and \
        bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
