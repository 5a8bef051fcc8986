"""The virtual bench: a physics-based simulated diffuser camera with known ground truth."""

from psfkit.simulate.bench_config import BenchConfig
from psfkit.simulate.camera import VirtualCamera
from psfkit.simulate.psf_grid import (
    GroundTruth,
    grid_monitor_positions,
    read_ground_truth,
    simulate_grid,
    simulate_scan,
)
from psfkit.simulate.psf_patch import PsfPatch, place_patch
from psfkit.simulate.sensor import SensorModel

__all__ = ["BenchConfig", "GroundTruth", "PsfPatch", "SensorModel", "VirtualCamera",
           "grid_monitor_positions", "place_patch", "read_ground_truth", "simulate_grid",
           "simulate_scan"]
