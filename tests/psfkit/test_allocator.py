"""The allocator setting of the image-heavy commands (psfkit.cli.allocator)."""

import platform
import resource
import subprocess
import sys

import pytest

from psfkit.cli.allocator import reuse_freed_memory


def test_reuse_freed_memory_takes_effect_on_glibc_and_is_a_no_op_elsewhere():
    # in a child process: the setting is process-wide
    code = "from psfkit.cli.allocator import reuse_freed_memory; print(reuse_freed_memory())"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True)
    glibc = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    assert result.stdout.strip() == str(glibc)


# Allocate and free arrays of growing size (2..30 MiB), as a full-resolution PSF pass does,
# and count the page faults. With the setting each freed block is reused and only the heap's
# growth is faulted in: the pages of the largest array, 30 MiB (measured: 7678 faults of 4 KiB
# pages, every run). glibc's default serves every new size with fresh pages: all of them
# (measured 118813, every run). Transparent huge pages are off in the child: numpy asks for
# them on large arrays, and where the kernel grants them a fault maps 2 MiB, so the default's
# count then depends on how much free memory the machine has (12014, 18657, and 4860 under
# load, on one machine) instead of on the allocator.
_FAULTS = """
import ctypes, resource, sys, numpy as np
PR_SET_THP_DISABLE = 41
if ctypes.CDLL(None, use_errno=True).prctl(PR_SET_THP_DISABLE, 1, 0, 0, 0) != 0:
    print("no-prctl")
    raise SystemExit(0)
if sys.argv[1] == "on":
    from psfkit.cli.allocator import reuse_freed_memory
    assert reuse_freed_memory()
before = resource.getrusage(resource.RUSAGE_SELF).ru_minflt
for mb in range(2, 31):
    a = np.ones(mb * 2**20 // 8)
    del a
print(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before)
"""


def _page_faults(setting: str) -> int:
    done = subprocess.run([sys.executable, "-c", _FAULTS, setting], capture_output=True,
                          text=True, check=True)
    if done.stdout.strip() == "no-prctl":
        pytest.skip("prctl(PR_SET_THP_DISABLE) refused: huge pages make fault counts vary")
    return int(done.stdout.strip())


def test_freed_blocks_are_reused_instead_of_faulted_in_again():
    if not (sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"):
        pytest.skip("the setting applies to glibc only (a no-op elsewhere, tested above)")
    page = resource.getpagesize()
    largest = 30 * 2**20 // page
    every = sum(mb * 2**20 for mb in range(2, 31)) // page
    off, on = _page_faults("off"), _page_faults("on")
    assert on <= 1.1 * largest, (on, largest)           # only the heap's growth
    assert off >= 0.9 * every, (off, every)             # the default: every array anew
    assert reuse_freed_memory() and reuse_freed_memory()     # calling it again is harmless
