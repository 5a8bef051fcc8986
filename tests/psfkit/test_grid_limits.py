"""Irregular scans of any number of positions (issue 43): a grid is limited by the memory its
analyses hold, estimated from its headers, not by 64 positions per side."""

from __future__ import annotations

import json

import numpy as np
import pytest

import psfkit.io.grid_validation as grid_validation
from psfkit.characterization.characterize import THUMBNAIL_SIZE
from psfkit.errors import GridFormatError
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.io import read_grid
from psfkit.io.grid_validation import analysis_memory_bytes
from psfkit.io.validation import MAX_GRID_CELLS, format_bytes, machine_memory_bytes
from research.compact_bench import CompactCamera, simulate_compact_scan


@pytest.fixture(scope="module")
def scan_300(tmp_path_factory):
    return simulate_compact_scan(tmp_path_factory.mktemp("limits") / "scan", 300, (40, 40),
                                 CompactCamera(edge_margin_px=6))


def test_a_scan_of_300_positions_is_read(scan_300):
    grid = read_grid(scan_300)
    assert grid.layout == "irregular" and grid.grid_shape == (1, 300)
    assert len(grid.positions) == 300 and grid.center_index == (0, 0)


def test_the_estimate_follows_what_the_pipeline_keeps():
    assert grid_validation.THUMBNAIL_SIDE == THUMBNAIL_SIZE
    assert grid_validation.WORKING_SIDE == EigenFitOptions().working_size
    one = analysis_memory_bytes((1, 117), 117, (1, 1024, 1024))
    # per position: a 256² working copy (float32 + mask), its factors and records
    per_position = analysis_memory_bytes((1, 118), 118, (1, 1024, 1024)) - one
    assert 256**2 * 5 < per_position < 256**2 * 5 + 4 * 2**20
    assert one < 2**30                         # the real case: far below any machine's memory
    # the old limit's largest grid at full resolution: several GiB
    assert analysis_memory_bytes((64, 64), 4096, (3, 1080, 1440)) > 4 * 2**30
    assert machine_memory_bytes() > 2**28 and format_bytes(3 * 2**30) == "3 GiB"


def test_a_grid_that_cannot_fit_is_refused_in_one_line(scan_300, monkeypatch):
    monkeypatch.setattr(grid_validation, "machine_memory_bytes", lambda: 8 * 2**20)
    with pytest.raises(GridFormatError) as info:
        read_grid(scan_300)
    message = str(info.value)
    assert "\n" not in message and str(scan_300 / "manifest.json") in message
    assert "an irregular scan of 1 x 300 positions (300 captured) of 40 x 40 x 1 images" \
        in message
    assert "needs about" in message and "more than this machine's 8 MiB" in message


def test_declared_lattices_are_bounded(tmp_path, scan_300):
    grid = read_grid(scan_300)
    doc = json.loads((scan_300 / "manifest.json").read_text())
    folder = tmp_path / "lattice"
    folder.mkdir()
    image = np.zeros((12, 12), np.uint16)          # the smallest PSF frame
    image[5:7, 5:7] = 4000
    np.save(folder / "a.npy", image)
    manifest = {"format": "psfkit-grid", "version": 1, "grid_shape": [5000, 5000],
                "positions": [{"file": "a.npy", "row": 0, "col": 0}]}
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(GridFormatError, match=r"grid_shape \[5000, 5000\] declares 25000000 "
                                              f"positions, more than the {MAX_GRID_CELLS}"):
        read_grid(folder)
    manifest["grid_shape"] = [600, 600]           # allowed cells; the memory decides
    (folder / "manifest.json").write_text(json.dumps(manifest))
    assert read_grid(folder).grid_shape == (600, 600)
    manifest["positions"][0]["row"] = MAX_GRID_CELLS + 1
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(GridFormatError, match=r"'row' .* exceeds the limit"):
        read_grid(folder)
    assert grid.grid_shape == (1, 300) and len(doc["positions"]) == 300
