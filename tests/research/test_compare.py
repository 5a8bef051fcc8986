"""research.compare: learned vs measured eigen-kernels, against known ground truths."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy import ndimage

from psfkit.calibration.preprocess import luminance
from psfkit.errors import InvalidInputError, ModelFileError
from psfkit.forward.kernelfile import KernelModel
from psfkit.io import read_grid
from psfkit.simulate import BenchConfig, simulate_grid
from research.compare import (
    CompareOptions,
    DisplacementMap,
    compare_kernels,
    comparison_mask,
    displacement_map,
    map_agreement,
    measure_modes,
    pearson,
    resample,
)


@pytest.fixture(scope="module")
def grid_inner(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """3 × 3 grid over 80 % of the field: the edge PSFs overlap the centre one enough for a
    warp field (1 s)."""
    out = tmp_path_factory.mktemp("grids") / "grid_3x3_inner"
    return simulate_grid(out, BenchConfig(downsample=8), grid_shape=(3, 3), extent=0.8,
                         progress=False)


@pytest.fixture(scope="module")
def modes(grid_inner):
    grid = read_grid(grid_inner)
    return measure_modes(grid, "paper", "source", grid.image_shape[1:])


def _stretch(image: np.ndarray, du: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """``out(x) = image(x − D(x))``, so that ``out(x + D) ≈ image(x)`` for a smooth ``D``."""
    h, w = image.shape
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
    return cv2.remap(image, uu - du, vv - dv, cv2.INTER_CUBIC)


def _known_fields(shape: tuple[int, int], a: float = 0.005) -> dict[str, np.ndarray]:
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w].astype(np.float32)
    zero = np.zeros(shape, np.float32)
    return {"v": np.stack([zero, a * (vv - (h - 1) / 2)]),       # stretch along v
            "h": np.stack([a * (uu - (w - 1) / 2), zero])}       # stretch along u


def test_identical_learned_file_gives_perfect_agreement(modes):
    """(a) a learned file equal to the measured fit: correlations 1, angles 0."""
    result = compare_kernels(modes.model, modes)
    for name in ("v", "h"):
        m = result.learned.metrics[name]
        assert m["vs_measured_kernels"]["corr"] == pytest.approx(1.0, abs=1e-6)
        assert m["vs_measured_kernels"]["epe_px"] == pytest.approx(0.0, abs=1e-6)
        assert m["difference_ncc"] == pytest.approx(1.0, abs=1e-6)
        # the fit follows the grid's own warps (measured numbers in the notes)
        assert m["vs_measured_warp"]["corr"] > 0.5
    assert np.max(result.learned.angles_eigen_deg) < 1e-3
    assert result.learned.global_shift_px == (0.0, 0.0)
    doc = result.to_dict()
    assert doc["headline"]["learned"]["v_vs_kernels"] == pytest.approx(1.0, abs=1e-6)
    assert len(doc["learned"]["principal_angles_deg_vs_measured_pca"]) == 3
    # no change against the measured kernels: nothing to split
    change = doc["kernel_change"]["learned_vs_measured"]
    assert all(change[n]["change_rel"] < 1e-6 for n in ("base", "v", "h"))
    assert change["all"]["outside_mass_fraction"] < 0.05


def test_known_warp_is_recovered(grid_inner):
    """(b) Kv, Kh = Kbase displaced by a known smooth warp: the displacement maps match it."""
    grid = read_grid(grid_inner)
    base = luminance(grid.load(*grid.require_center()))
    base = np.clip(base - np.median(base), 0, None).astype(np.float32)
    mask = comparison_mask(base, CompareOptions())
    for name, truth in _known_fields(base.shape).items():
        moved = _stretch(base, truth[0], truth[1])
        found = displacement_map(base, moved, mask)
        agreement = map_agreement(found, DisplacementMap(truth, mask))
        assert agreement["corr"] >= 0.9, (name, agreement)
        assert agreement["epe_px"] < 0.1, (name, agreement)
        assert 0.7 < agreement["slope"] < 1.4, (name, agreement)


def test_known_warp_through_compare_kernels(modes):
    """(b) the same through the full comparison: learned kernels built from the measured Kbase
    with known warps; the learned displacement maps match the known fields."""
    base = modes.model.kernels[0]
    fields = _known_fields(base.shape[-2:])
    kernels = [base] + [np.stack([_stretch(ch, *fields[n]) for ch in base]) for n in ("v", "h")]
    learned = KernelModel(kernels=np.stack(kernels), basis="paper", convention="source",
                          sensor_shape=modes.sensor_shape)
    result = compare_kernels(learned, modes)
    for name in ("v", "h"):
        disp = result.learned.displacements[name]
        truth = DisplacementMap(fields[name], disp.mask)
        agreement = map_agreement(disp, truth)
        assert agreement["corr"] >= 0.9 and agreement["epe_px"] < 0.1, (name, agreement)


def test_unrelated_kernels_correlate_weakly(modes):
    """(c) correction kernels displaced by random smooth fields: low correlation (chance
    correlations of smooth fields over a small caustic reach about ±0.3; see the notes)."""
    base = modes.model.kernels[0]
    shape = base.shape[-2:]
    values = []
    for seed in range(3):
        rng = np.random.default_rng(seed)
        kernels = [base]
        for _ in range(2):
            field = np.stack([ndimage.gaussian_filter(rng.standard_normal(shape), 4)
                              for _ in range(2)]).astype(np.float32)
            field *= 0.4 / np.sqrt(np.mean(field**2))
            kernels.append(np.stack([_stretch(ch, *field) for ch in base]))
        learned = KernelModel(kernels=np.stack(kernels), basis="paper", convention="source",
                              sensor_shape=modes.sensor_shape)
        result = compare_kernels(learned, modes)
        for name in ("v", "h"):
            m = result.learned.metrics[name]
            values += [m["vs_measured_kernels"]["corr"], m["vs_measured_warp"]["corr"]]
            assert abs(m["difference_ncc"]) < 0.5, m
    values = np.abs(values)
    assert values.max() < 0.4 and values.mean() < 0.2, values


def test_shift_invariant_kernels_give_undefined_correlation(modes):
    """(d) Kv = Kh = Kbase: no displacement, correlations NaN with a note, no crash."""
    base = modes.model.kernels[0]
    learned = KernelModel(kernels=np.stack([base] * 3), basis="paper", convention="source",
                          sensor_shape=modes.sensor_shape)
    result = compare_kernels(learned, modes, initial=modes.model)
    for name in ("v", "h"):
        m = result.learned.metrics[name]
        assert result.learned.displacements[name].rms() < 0.02
        assert math.isnan(m["vs_measured_kernels"]["corr"])
        assert "no displacement" in m["vs_measured_kernels"]["note"]
        assert math.isnan(m["difference_ncc"])
        # the initial (here: the fit itself) is reported next to it
        assert result.initial.metrics[name]["vs_measured_kernels"]["corr"] == pytest.approx(1.0)
    doc = result.to_dict()                       # NaN → null, JSON-ready
    assert doc["headline"]["learned"]["v_vs_kernels"] is None


def test_sensor_convention_grid_fit_agrees_with_its_warps(grid_inner):
    """(d) with the paper's sensor-side weights the fit of the grid also follows the warps."""
    grid = read_grid(grid_inner)
    modes = measure_modes(grid, "paper", "sensor", grid.image_shape[1:])
    result = compare_kernels(modes.model, modes)
    assert result.measured_kernels_vs_warp["h"]["corr"] > 0.5
    assert result.measured_kernels_vs_warp["v"]["corr"] > 0.2


def test_joint_warps_from_all_positions(grid_inner):
    """warp_positions="all": every reliable position, all correction kernels at once."""
    grid = read_grid(grid_inner)
    options = CompareOptions(warp_positions="all")
    modes = measure_modes(grid, "paper", "source", grid.image_shape[1:], options)
    assert set(modes.warps) == {"v", "h"} and len(modes.warp_positions["all"]) >= 4
    result = compare_kernels(modes.model, modes, options=options)
    assert result.measured_kernels_vs_warp["h"]["corr"] > 0.5


def test_coarser_learned_file_and_smaller_kernels(grid_inner, modes):
    """A kernel file at 1/3 of the grid's resolution with kernels smaller than its sensor:
    the grid is resampled and the kernels padded (and the notes say so)."""
    coarse = resample(modes.model.kernels, (45, 60))[..., 2:-2, 3:-3]
    learned = KernelModel(kernels=coarse, basis="paper", convention="source",
                          sensor_shape=(45, 60))
    result = compare_kernels(learned, grid_inner,
                             options=CompareOptions(mask_border=2, smooth_px=1.0))
    assert result.measured.sensor_shape == (45, 60)
    assert any("resampled" in n for n in result.notes)
    assert any("zero-padded" in n for n in result.notes)
    assert result.learned.kernels.shape == (3, 3, 45, 60)


def test_refusals(grid_inner, modes, tmp_path):
    square = KernelModel(kernels=np.zeros((3, 3, 9, 9), np.float32) + 1, basis="paper",
                         sensor_shape=(135, 135))
    with pytest.raises(InvalidInputError, match="different aspect ratios"):
        compare_kernels(square, grid_inner)
    si = KernelModel.shift_invariant(modes.model.kernels[0], sensor_shape=modes.sensor_shape)
    with pytest.raises(ModelFileError, match="single kernel"):
        compare_kernels(si, modes)
    sensor_side = KernelModel(kernels=modes.model.kernels, basis="paper", convention="sensor",
                              sensor_shape=modes.sensor_shape)
    with pytest.raises(ModelFileError, match="basis/convention"):
        compare_kernels(sensor_side, modes)
    (tmp_path / "empty").mkdir()
    with pytest.raises(InvalidInputError):
        compare_kernels(modes.model, tmp_path / "empty")


def test_pearson_of_constant_map_is_nan():
    mask = np.ones((8, 8), bool)
    assert math.isnan(pearson(np.zeros((8, 8)), np.arange(64.0).reshape(8, 8), mask))
    assert pearson(np.arange(64.0).reshape(8, 8), np.arange(64.0).reshape(8, 8), mask) == \
        pytest.approx(1.0)


def test_numbers_are_the_metrics_flat(modes):
    """``KernelSetComparison.numbers()``: the quoted numbers, flat, equal to the metrics; the
    fit against itself gives NCC 1, correlation 1, EPE 0, angles 0; a one-PSF model NaN."""
    same = compare_kernels(modes.model, modes).learned.numbers()
    assert set(same) == {"v_diff_ncc", "v_disp_corr", "v_epe_px", "h_diff_ncc", "h_disp_corr",
                         "h_epe_px", "angles_deg"}
    assert same["v_diff_ncc"] == pytest.approx(1.0, abs=1e-6)
    assert same["h_disp_corr"] == pytest.approx(1.0, abs=1e-6)
    assert same["v_epe_px"] == pytest.approx(0.0, abs=1e-6)
    assert len(same["angles_deg"]) == 3 and max(same["angles_deg"]) < 1e-3
    base = modes.model.kernels[0]
    one = KernelModel(kernels=np.stack([base] * 3), basis="paper", convention="source",
                      sensor_shape=modes.sensor_shape)
    result = compare_kernels(one, modes).learned
    got = result.numbers()
    assert math.isnan(got["v_diff_ncc"]) and math.isnan(got["h_disp_corr"])
    assert got["v_epe_px"] == result.metrics["v"]["vs_measured_kernels"]["epe_px"] > 0


def test_written_comparison_holds_extra_files_and_rows(modes, tmp_path):
    """``write_comparison(extra_files=)`` writes them in the folder's transaction (a bad name
    leaves nothing behind); ``figure_learned_vs_measured(extra_rows=)`` adds rows."""
    from research.compare.figures import figure_learned_vs_measured
    from research.compare.report import write_comparison

    result = compare_kernels(modes.model, modes)
    out = write_comparison(result, tmp_path / "c", extra_files=[("note.md", "hello\n")])
    assert (out / "note.md").read_text() == "hello\n" and (out / "compare.json").is_file()
    with pytest.raises(ValueError, match="extra file name"):
        write_comparison(result, tmp_path / "d", extra_files=[("../x.md", "no")])
    assert not (tmp_path / "d").exists() and not (tmp_path / "x.md").exists()
    plain = figure_learned_vs_measured(result)
    more = figure_learned_vs_measured(result, extra_rows=[("oracle", modes.model.kernels)])
    assert len(more.axes) > len(plain.axes)
    assert more.get_size_inches()[1] == pytest.approx(plain.get_size_inches()[1] + 1.45)


def test_figure_names_a_kernel_file_reference_by_its_file(modes, tmp_path):
    """Fig. 7's last row is "measured (grid fit)" only when the measured side is a grid; a
    kernel file given as B (a pairs fit, an oracle) is named by its file."""
    from psfkit.forward.kernelfile import save_kernels
    from research.compare.figures import reference_label

    assert reference_label(compare_kernels(modes.model, modes)) == "measured (grid fit)"
    path = tmp_path / "pairs_fit.npz"
    save_kernels(path, modes.model)
    assert reference_label(compare_kernels(modes.model, path)) == "reference: pairs_fit.npz"
