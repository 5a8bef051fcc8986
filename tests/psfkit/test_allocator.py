"""The allocator setting of the image-heavy commands (psfkit.allocator)."""

import platform
import subprocess
import sys

from psfkit.allocator import reuse_freed_memory


def test_reuse_freed_memory_takes_effect_on_glibc_and_is_a_no_op_elsewhere():
    # in a child process: the setting is process-wide
    code = "from psfkit.allocator import reuse_freed_memory; print(reuse_freed_memory())"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                            check=True)
    glibc = sys.platform.startswith("linux") and platform.libc_ver()[0] == "glibc"
    assert result.stdout.strip() == str(glibc)


def test_reuse_freed_memory_can_be_called_again():
    assert reuse_freed_memory() == reuse_freed_memory()
