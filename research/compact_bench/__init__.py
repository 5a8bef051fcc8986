"""The compact-PSF bench (a lens-like camera imaging stars or beads at irregular known field
positions, with its ground truth): the truth the compact-PSF tests and
``benchmarks/bench_compact_psf.py`` check the analysis against. Not installed."""

from research.compact_bench.camera import CompactCamera
from research.compact_bench.scan import (
    CompactTruth,
    cutout_scan,
    read_compact_truth,
    simulate_compact_scan,
)

__all__ = ["CompactCamera", "CompactTruth", "cutout_scan", "read_compact_truth",
           "simulate_compact_scan"]
