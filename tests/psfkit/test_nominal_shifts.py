"""Where the eigen-kernel fit places each PSF (``fit-eigen --shifts``, issue 23 item 5).

The forward model ``y = crop(K * pad(x))`` puts the PSF of a scene point at a position linear
in its field position; the fit must place the measured PSFs there, not at their own registered
shifts (which remove the distortion the kernels must carry, and are biased where a PSF is
mostly off the sensor). Checked against the virtual bench's true chief-ray shifts.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from psfkit.calibration.alignment import RELIABLE_OVERLAP, GridAligner
from psfkit.calibration.nominal_shifts import nominal_shifts
from psfkit.fitting.grid.eigen import DEFAULT_RIDGE, NormalEquations
from psfkit.fitting.grid.fit import fit_eigen_grid
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.forward.weights import get_basis
from psfkit.io import read_grid
from psfkit.io.grid import GridPosition
from psfkit.simulate import BenchConfig, simulate_grid


def _lattice(n: int, m: int, step: float = 100.0) -> list[GridPosition]:
    return [GridPosition(file=f"p{r}{c}.npy", row=r, col=c,
                         monitor_px=((c - m // 2) * step, (r - n // 2) * step))
            for r in range(n) for c in range(m)]


def test_affine_map_of_the_reliable_positions_is_recovered_exactly():
    """Registered shifts = an exact affine map + large errors at the unreliable positions:
    the nominal shifts are the map's (re-based to 0 at the centre), the errors ignored."""
    positions = _lattice(9, 9)
    xy = np.array([p.monitor_px for p in positions])
    matrix = np.array([[-0.31, 0.004], [-0.003, -0.305]])
    exact = xy @ matrix.T + np.array([0.2, -0.1])            # an offset the centre removes
    radius = np.abs(xy).max(axis=1) / 400
    overlap = np.clip(1.05 - 0.6 * radius, 0, 1)              # outer ring below 0.5
    rng = np.random.default_rng(0)
    error = np.where((overlap < RELIABLE_OVERLAP)[:, None], rng.normal(0, 5, exact.shape), 0)
    result = nominal_shifts(positions, exact + error, overlap, (4, 4))
    assert result.source == "affine"
    assert result.positions_used == int(np.count_nonzero(overlap >= RELIABLE_OVERLAP)) == 49
    nominal = np.array([result.shifts[(p.row, p.col)] for p in positions])
    np.testing.assert_allclose(nominal, exact - exact[40], atol=1e-9)
    assert result.shifts[(4, 4)] == (0.0, 0.0)
    assert result.deviation_px == pytest.approx(np.hypot(*(error + exact[40]).T).max())
    np.testing.assert_allclose(result.fit.matrix, matrix, atol=1e-12)
    doc = result.to_dict()
    assert doc["source"] == "affine" and doc["positions_used"] == 49
    json.dumps(doc)


def test_fallbacks_every_position_then_the_registered_shifts():
    """A 3 × 3 grid over the full field has only its centre reliable: the map is fitted to
    every position; a single row has no two-dimensional map: each PSF keeps its own shift."""
    positions = _lattice(3, 3, step=400)
    xy = np.array([p.monitor_px for p in positions])
    registered = -0.3 * xy
    overlap = np.where(np.abs(xy).max(axis=1) > 0, 0.3, 1.0)
    result = nominal_shifts(positions, registered, overlap, (1, 1))
    assert result.source == "affine (all positions)" and result.positions_used == 9
    np.testing.assert_allclose([result.shifts[(p.row, p.col)] for p in positions], registered,
                               atol=1e-9)
    row = _lattice(1, 5)
    shifts = np.array([[-60.0, 0.1], [-30.2, 0.0], [0.0, 0.0], [29.9, -0.1], [61.0, 0.0]])
    result = nominal_shifts(row, shifts, np.ones(5), (0, 2))
    assert result.source == "registered" and result.fit is None
    np.testing.assert_array_equal([result.shifts[(0, c)] for c in range(5)], shifts)
    with pytest.raises(ValueError, match="centre"):
        nominal_shifts(row[:2], shifts[:2], np.ones(2), (0, 2))


@pytest.fixture(scope="module")
def wide_grid(tmp_path_factory):
    """A 9 × 9 virtual-bench grid of 128 × 128 px whose edge points land on the sensor edges
    (±30°, ``ekdun make-dataset --sensor 128 128``'s camera): the outer PSFs are half off the
    sensor, and their registration is biased by their deformation."""
    half_mm = 128 * 16 * 3.45e-3 / 2
    gap_mm = half_mm / math.tan(math.radians(30.0))
    fov = round(2 * 200.0 * half_mm / gap_mm / 0.2768)
    config = BenchConfig(sensor_shape=(2048, 2048), downsample=16, gap_mm=gap_mm,
                         monitor_distance_mm=200.0, aperture_mm=(1.3, 1.3),
                         fov_monitor_px=(fov, fov), seed=0)
    out = simulate_grid(tmp_path_factory.mktemp("wide") / "grid", config, grid_shape=(9, 9),
                        suffix=".npy", progress=False)
    truth = json.loads((out / "ground_truth" / "truth.json").read_text())
    true_shifts = {(p["row"], p["col"]): tuple(p["shift_px"]) for p in truth["positions"]}
    return read_grid(out), true_shifts


def test_nominal_shifts_are_the_true_chief_rays_where_registration_is_biased(wide_grid):
    grid, truth = wide_grid
    aligner = GridAligner(grid)
    aligned = [aligner.align(p) for p in grid.positions]
    registered = np.array([a.shift for a in aligned])
    overlap = np.array([a.overlap for a in aligned])
    true = np.array([truth[(p.row, p.col)] for p in grid.positions])
    result = nominal_shifts(grid.positions, registered, overlap, grid.require_center())
    nominal = np.array([result.shifts[(p.row, p.col)] for p in grid.positions])
    registration_error = np.hypot(*(registered - true).T)
    # the bias being fixed (measured 1.23 px at a corner) ...
    assert registration_error[overlap < RELIABLE_OVERLAP].max() > 0.5
    assert registration_error[overlap >= RELIABLE_OVERLAP].max() < 0.1
    # ... and the map's shifts (measured within 0.006 px of the chief rays)
    assert np.hypot(*(nominal - true).T).max() < 0.03
    assert result.deviation_px == pytest.approx(np.hypot(*(registered - nominal).T).max())


def _fit_at(grid, shifts: dict, convention: str) -> np.ndarray:
    """The per-pixel least squares of fit-eigen with every PSF at the given shift."""
    aligner = GridAligner(grid, min_quality=0)
    c, h, w = grid.image_shape
    equations = NormalEquations(get_basis("paper"), convention, (c, h, w))
    for pos in grid.positions:
        a = aligner.align(pos, shift=shifts[(pos.row, pos.col)], check_quality=False)
        equations.add(a.image, a.valid, a.shift)
    return equations.solve(DEFAULT_RIDGE, conditioning=False)[0]


@pytest.mark.parametrize("convention", ["source", "sensor"])
def test_affine_placement_fits_the_kernels_of_the_true_shifts(wide_grid, convention):
    """The default fit is the fit at the true chief-ray shifts (measured 0.12 % of its norm);
    at the registered shifts it is far from it (measured 6.3 % / 5.7 %)."""
    grid, truth = wide_grid
    reference = _fit_at(grid, truth, convention)
    fits = {mode: fit_eigen_grid(grid, EigenFitOptions(convention=convention, shifts=mode,
                                                       cv_bases=()), workers=1)
            for mode in ("affine", "registered")}
    distance = {mode: np.linalg.norm(fit.full_kernels[convention] - reference)
                / np.linalg.norm(reference) for mode, fit in fits.items()}
    assert distance["affine"] < 0.005
    assert distance["registered"] > 10 * distance["affine"]
    assert fits["affine"].summary()["shifts"]["source"] == "affine"
    assert fits["registered"].summary()["shifts"] == {"source": "registered"}
