"""The virtual bench: a physics-based simulated diffuser camera with known ground truth."""

from psfkit.simulate.bench_config import BenchConfig
from psfkit.simulate.camera import VirtualCamera
from psfkit.simulate.compact import (
    CompactTruth,
    cutout_scan,
    read_compact_truth,
    simulate_compact_scan,
)
from psfkit.simulate.compact_camera import CompactCamera
from psfkit.simulate.psf_grid import (
    GroundTruth,
    grid_monitor_positions,
    read_ground_truth,
    simulate_grid,
    simulate_scan,
)
from psfkit.simulate.psf_patch import PsfPatch, place_patch
from psfkit.simulate.sensor import SensorModel

__all__ = ["BenchConfig", "CompactCamera", "CompactTruth", "GroundTruth", "PsfPatch",
           "SensorModel", "VirtualCamera", "cutout_scan", "grid_monitor_positions",
           "place_patch", "read_compact_truth", "read_ground_truth", "simulate_compact_scan",
           "simulate_grid", "simulate_scan"]
