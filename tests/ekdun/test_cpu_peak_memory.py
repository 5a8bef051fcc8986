"""The CPU peak-memory estimate of ``ekdun eval``: the largest live set of one forward pass,
and nothing from the profiler on stderr."""

from __future__ import annotations

import subprocess
import sys

CHILD = r"""
import torch
from ekdun.evaluation.evaluate import cpu_peak_memory

class TwoBuffers(torch.nn.Module):
    # holds 1 MiB, then 2 MiB beside it (3 MiB live), frees both, then 2.5 MiB alone
    def forward(self, y):
        a = torch.ones(2**18)           # 1 MiB of float32
        b = torch.ones(2**19)           # 2 MiB
        s = float(a.sum() + b.sum())
        del a, b
        c = torch.ones(5 * 2**17)       # 2.5 MiB
        return c.sum() + s

print(cpu_peak_memory(TwoBuffers(), torch.zeros(1)))
"""


def test_peak_is_the_largest_live_set_and_stderr_stays_quiet():
    done = subprocess.run([sys.executable, "-c", CHILD], capture_output=True, text=True,
                          check=True)
    peak = int(done.stdout.strip())
    mib = 2**20
    # 3 MiB live at once (not the 5.5 MiB allocated in all, not the 2.5 MiB at the end)
    assert 3 * mib <= peak < 3 * mib + 64 * 1024, peak
    assert "USDT" not in done.stderr and "profiler_start" not in done.stderr, done.stderr
