"""simulate_grid: a grid a lab could have measured, plus its ground truth."""

import filecmp
import json

import numpy as np
import pytest

from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.io import read_grid
from psfkit.simulate import BenchConfig, VirtualCamera, read_ground_truth, simulate_grid


def test_grid_loads_back_through_the_reader_with_its_manifest(grid_3x3, small_config):
    grid = read_grid(grid_3x3)
    assert grid.grid_shape == (3, 3)
    assert grid.image_shape == (3, 135, 180)
    assert grid.dtype == np.uint16
    assert grid.center_index == (1, 1)
    assert grid.dark_file == "dark.tiff"
    assert grid.bit_depth == 12
    truth = read_ground_truth(grid_3x3)
    np.testing.assert_allclose(grid.field_deg(), truth.field_deg)
    # corners of a full-FoV grid: tan θ = (FoV/2 · pitch) / z
    fov_h, fov_w = small_config.fov_monitor_px
    z, pitch = small_config.monitor_distance_mm, small_config.monitor_pixel_pitch_mm
    expected = np.rad2deg(np.arctan([fov_w / 2 * pitch / z, fov_h / 2 * pitch / z]))
    np.testing.assert_allclose(grid.field_deg()[2, 2], expected, rtol=1e-9)
    np.testing.assert_allclose(grid.monitor_px()[0, 0], [-fov_w / 2, -fov_h / 2])


def test_ground_truth_matches_the_noisy_captures(grid_3x3):
    """Dark-subtracted captures scatter around the clean PSFs with Poisson–Gaussian noise,
    and the recorded shifts/gains are the geometry's."""
    grid = read_grid(grid_3x3)
    truth = read_ground_truth(grid_3x3)
    for r, c in [(1, 1), (0, 2)]:
        signal = grid.load(r, c) - grid.black_level
        clean = np.asarray(truth.clean_psfs[r, c])
        bright = clean > 0.2 * clean.max()
        assert np.mean(signal[bright]) == pytest.approx(np.mean(clean[bright]), rel=0.02)
        assert np.corrcoef(signal.ravel(), clean.ravel())[0, 1] > 0.97
    cam = VirtualCamera(truth.config)
    np.testing.assert_allclose(truth.shift_px[0, 0], cam.true_shift_px(truth.field_deg[0, 0]))
    assert truth.gain[1, 1] == 1.0
    assert truth.gain[0, 0] < truth.gain[0, 1] < 1.0
    dark = grid.load_dark()
    assert abs(dark.mean() - grid.black_level) < 0.5 * 16


def test_fixed_seed_gives_identical_files(tmp_path):
    config = BenchConfig(downsample=8, seed=11)
    a = simulate_grid(tmp_path / "a", config, grid_shape=(2, 3), progress=False)
    b = simulate_grid(tmp_path / "b", config, grid_shape=(2, 3), progress=False)
    c = simulate_grid(tmp_path / "c", BenchConfig(downsample=8, seed=12), grid_shape=(2, 3),
                      progress=False)
    names = sorted(p.name for p in a.iterdir() if p.is_file())
    _match, mismatch, errors = filecmp.cmpfiles(a, b, names, shallow=False)
    assert not mismatch and not errors
    assert filecmp.cmp(a / "ground_truth" / "psfs_clean.npy",
                       b / "ground_truth" / "psfs_clean.npy", shallow=False)
    assert not filecmp.cmp(a / "psf_r00_c00.tiff", c / "psf_r00_c00.tiff", shallow=False)


def test_even_grid_has_no_centre_and_says_so(tmp_path):
    grid = read_grid(simulate_grid(tmp_path / "g", BenchConfig(downsample=8), grid_shape=(2, 2),
                                   progress=False))
    assert grid.center_index is None
    with pytest.raises(InvalidInputError, match="no centre position"):
        grid.require_center()


def test_saturation_on_purpose_is_recorded(tmp_path):
    out = simulate_grid(tmp_path / "sat", BenchConfig(downsample=8, peak_fraction=3.0),
                        grid_shape=(1, 1), progress=False)
    truth = json.loads((out / "ground_truth" / "truth.json").read_text())
    assert truth["positions"][0]["saturated_pixels"] > 0
    assert read_grid(out).load(0, 0).max() == 65520


def test_existing_output_is_refused_before_any_work(tmp_path):
    out = tmp_path / "taken"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(InvalidInputError, match="not empty"):
        simulate_grid(out, BenchConfig(downsample=8), grid_shape=(1, 1), progress=False)
    assert [p.name for p in out.iterdir()] == ["keep.txt"]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]


def test_averaged_frames_divide_the_grid_noise_by_their_square_root(tmp_path):
    """``frames=9``: the same clean PSFs, float32 means whose noise about the ground truth is
    a third of one raw frame's (shot, read and quantisation noise all average down), recorded
    in the manifest and the ground truth; the dark frame is averaged too."""
    config = BenchConfig(downsample=16, seed=3)
    one = simulate_grid(tmp_path / "one", config, grid_shape=(1, 3), suffix=".npy",
                        progress=False)
    nine = simulate_grid(tmp_path / "nine", config, grid_shape=(1, 3), suffix=".npy",
                         progress=False, frames=9)
    np.testing.assert_array_equal(read_ground_truth(one).clean_psfs,
                                  read_ground_truth(nine).clean_psfs)
    grids = read_grid(one), read_grid(nine)
    assert grids[0].dtype == np.uint16 and grids[1].dtype == np.float32
    noise = []
    for grid, folder in zip(grids, (one, nine), strict=True):
        clean = read_ground_truth(folder).clean_psfs
        residual = np.stack([grid.load(0, c) - grid.black_level - clean[0, c]
                             for c in range(3)])
        noise.append((residual.std(), grid.load_dark().std()))
    assert 0.30 < noise[1][0] / noise[0][0] < 0.37
    assert 0.28 < noise[1][1] / noise[0][1] < 0.39
    manifest = json.loads((nine / "manifest.json").read_text())
    assert manifest["simulation"]["frames_averaged"] == 9
    assert "frames_averaged" not in json.loads((one / "manifest.json").read_text())["simulation"]
    assert json.loads((nine / "ground_truth" / "truth.json").read_text())["frames_averaged"] == 9


def test_averaged_frames_are_refused_as_png_or_a_non_positive_count(tmp_path):
    config = BenchConfig(downsample=16)
    with pytest.raises(ConfigurationError, match=r"TIFF or \.npy"):
        simulate_grid(tmp_path / "png", config, grid_shape=(1, 1), suffix=".png", frames=2,
                      progress=False)
    with pytest.raises(ConfigurationError, match="frames"):
        simulate_grid(tmp_path / "zero", config, grid_shape=(1, 1), frames=0, progress=False)
    assert not list(tmp_path.iterdir())


def test_ground_truth_without_its_clean_file_computes_the_same_psfs(tmp_path):
    """``clean_psfs=False`` (the demo's grid): the same captures, a ground truth of a few kB,
    and read_ground_truth computes the clean PSFs again, equal to the written file bit for
    bit, one position or the whole array."""
    config = BenchConfig(downsample=16, seed=5)
    full = simulate_grid(tmp_path / "full", config, grid_shape=(2, 3), progress=False)
    compact = simulate_grid(tmp_path / "compact", config, grid_shape=(2, 3), progress=False,
                            clean_psfs=False)
    names = sorted(p.name for p in full.iterdir() if p.is_file())
    _match, mismatch, errors = filecmp.cmpfiles(full, compact, names, shallow=False)
    assert not mismatch and not errors
    assert not (compact / "ground_truth" / "psfs_clean.npy").exists()
    assert sum(p.stat().st_size for p in (compact / "ground_truth").iterdir()) < 20_000
    written = read_ground_truth(full).clean_psfs
    computed = read_ground_truth(compact).clean_psfs
    assert computed.shape == written.shape and computed.dtype == written.dtype
    np.testing.assert_array_equal(computed[1, 2], written[1, 2])
    np.testing.assert_array_equal(computed[-1, 0], written[1, 0])
    np.testing.assert_array_equal(np.asarray(computed), written)
    np.testing.assert_array_equal(computed[:, 1], written[:, 1])
    assert written.max() > 0
