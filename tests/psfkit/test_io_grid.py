"""The PSF-grid format: round trips and every refusal the reader promises."""

import json
import re
import shutil

import numpy as np
import pytest
import tifffile

from psfkit.errors import GridFormatError
from psfkit.io import GridWriter, read_grid, read_image, write_image


def _psf(seed, shape=(3, 12, 16), dtype=np.uint16):
    rng = np.random.default_rng(seed)
    return (rng.integers(1, 4000, size=shape)).astype(dtype)


@pytest.fixture()
def grid_dir(tmp_path):
    """A valid 3×3 RGB grid of small random images, written with GridWriter."""
    out = tmp_path / "grid"
    with GridWriter(out, (3, 3), bit_depth=12, black_level=64) as w:
        for r in range(3):
            for c in range(3):
                w.add(r, c, _psf(r * 3 + c), field_deg=(c - 1.0, r - 1.0),
                      monitor_px=(100.0 * (c - 1), 100.0 * (r - 1)), exposure_s=0.01)
        w.add_dark(np.full((3, 12, 16), 64, np.uint16))
    return out


def _manifest(grid_dir):
    return json.loads((grid_dir / "manifest.json").read_text())


def _write_manifest(grid_dir, doc):
    (grid_dir / "manifest.json").write_text(json.dumps(doc))


def test_round_trip(grid_dir):
    grid = read_grid(grid_dir)
    assert grid.grid_shape == (3, 3)
    assert grid.image_shape == (3, 12, 16)
    assert grid.channels == ("R", "G", "B")
    assert grid.center_index == (1, 1)
    assert grid.black_level == 64
    np.testing.assert_array_equal(grid.load(2, 1), _psf(7).astype(np.float32))
    assert grid.field_deg()[2, 0].tolist() == [-1.0, 1.0]
    assert grid.exposures().shape == (3, 3)
    assert grid.load_dark().mean() == 64


def test_csv_manifest_with_dark_row(grid_dir):
    doc = _manifest(grid_dir)
    (grid_dir / "manifest.json").unlink()
    lines = ["# lab grid, field angles in degrees", "file,row,col,field_x_deg,field_y_deg,role"]
    lines += [f"{p['file']},{p['row']},{p['col']},{p['field_deg'][0]},{p['field_deg'][1]},psf"
              for p in doc["positions"]]
    lines.append("dark.tiff,,,,,dark")
    (grid_dir / "manifest.csv").write_text("\n".join(lines) + "\n")
    grid = read_grid(grid_dir)
    assert grid.grid_shape == (3, 3)
    assert grid.dark_file == "dark.tiff"
    assert grid.center_index == (1, 1)
    assert grid.exposures() is None


@pytest.mark.parametrize("fmt", [".png", ".npy", ".tiff"])
@pytest.mark.parametrize("channels", [1, 3])
def test_image_formats_round_trip(tmp_path, fmt, channels):
    image = _psf(0, shape=(channels, 9, 7))
    path = write_image(tmp_path / f"x{fmt}", image)
    back = read_image(path)
    assert back.dtype == np.uint16
    np.testing.assert_array_equal(back, image)


def test_bgr_and_planar_tiff(tmp_path):
    rgb = _psf(1, shape=(3, 5, 6))
    np.save(tmp_path / "bgr.npy", np.moveaxis(rgb[::-1], 0, -1))
    np.testing.assert_array_equal(read_image(tmp_path / "bgr.npy", channel_order="BGR"), rgb)
    tifffile.imwrite(tmp_path / "planar.tif", rgb, photometric="rgb", planarconfig="separate")
    np.testing.assert_array_equal(read_image(tmp_path / "planar.tif"), rgb)


def _corrupt(grid_dir, case):
    doc = _manifest(grid_dir)
    if case == "missing file":
        (grid_dir / "psf_r01_c02.tiff").unlink()
        return "psf_r01_c02.tiff: listed in manifest.json but missing"
    if case == "duplicate index":
        doc["positions"][4]["row"], doc["positions"][4]["col"] = 0, 0
        _write_manifest(grid_dir, doc)
        return r"grid index \(0, 0\) appears twice"
    if case == "missing index":
        doc["positions"] = [p for p in doc["positions"] if (p["row"], p["col"]) != (2, 1)]
        (grid_dir / "psf_r02_c01.tiff").unlink()
        _write_manifest(grid_dir, doc)
        return r"grid index \(2, 1\) missing"
    if case == "mixed shapes":
        write_image(grid_dir / "psf_r00_c01.tiff", _psf(1, shape=(3, 12, 15)))
        return r"psf_r00_c01.tiff: shape 12×15×3 uint16 differs from psf_r00_c00.tiff"
    if case == "mixed bit depths":
        write_image(grid_dir / "psf_r00_c01.tiff", _psf(1, dtype=np.uint8))
        return "psf_r00_c01.tiff: pixel type .* uint8 differs"
    if case == "not an image":
        (grid_dir / "psf_r02_c02.tiff").write_text("this is not a TIFF")
        return "psf_r02_c02.tiff: not a readable image"
    if case == "nan":
        for p in doc["positions"]:
            p["file"] = p["file"].replace(".tiff", ".npy")
            image = read_image(grid_dir / p["file"].replace(".npy", ".tiff")).astype(np.float32)
            (grid_dir / p["file"].replace(".npy", ".tiff")).unlink()
            if p["file"] == "psf_r01_c01.npy":
                image[0, 3, 3] = np.nan   # write_image refuses NaN: save the bad file directly
            np.save(grid_dir / p["file"], np.moveaxis(image, 0, -1))
        doc.pop("dark_frame")
        (grid_dir / "dark.tiff").unlink()
        _write_manifest(grid_dir, doc)
        return "psf_r01_c01.npy: contains 1 NaN/Inf pixel"
    if case == "all zero":
        write_image(grid_dir / "psf_r00_c00.tiff", np.zeros((3, 12, 16), np.uint16))
        return "psf_r00_c00.tiff: all-zero frame"
    if case == "unlisted file":
        shutil.copy(grid_dir / "psf_r00_c00.tiff", grid_dir / "extra_psf.tiff")
        return "does not match the folder: image file.* extra_psf.tiff not listed"
    if case == "no manifest":
        (grid_dir / "manifest.json").unlink()
        return "no manifest.json or manifest.csv"
    if case == "two manifests":
        (grid_dir / "manifest.csv").write_text("file,row,col\n")
        return "has both manifest.json and manifest.csv"
    if case == "bad json":
        (grid_dir / "manifest.json").write_text('{"positions": [}')
        return "manifest.json: invalid JSON at line 1"
    if case == "wrong version":
        doc["version"] = 99
        _write_manifest(grid_dir, doc)
        return "grid format version 99 is not supported"
    if case == "bad index type":
        doc["positions"][0]["row"] = "first"
        _write_manifest(grid_dir, doc)
        return "'row' must be a non-negative integer"
    if case == "file outside folder":
        doc["positions"][0]["file"] = "../elsewhere.tiff"
        _write_manifest(grid_dir, doc)
        return "must be a plain name inside the grid folder"
    if case == "bad dark frame":
        write_image(grid_dir / "dark.tiff", np.zeros((1, 12, 16), np.uint16))
        return "dark.tiff: shape 12×16×1"
    raise AssertionError(case)


BAD_CASES = ["missing file", "duplicate index", "missing index", "mixed shapes",
             "mixed bit depths", "not an image", "nan", "all zero", "unlisted file",
             "no manifest", "two manifests", "bad json", "wrong version", "bad index type",
             "file outside folder", "bad dark frame"]


@pytest.mark.parametrize("case", BAD_CASES)
def test_reader_refuses_bad_input_with_one_clear_line(grid_dir, case):
    expected = _corrupt(grid_dir, case)
    with pytest.raises(GridFormatError, match=expected) as info:
        read_grid(grid_dir, strict=True)
    assert "\n" not in str(info.value)
    if case in ("missing index", "nan", "all zero"):     # flagged, not refused (issue 26)
        grid = read_grid(grid_dir)
        if case == "missing index":
            assert grid.layout == "incomplete lattice"
            assert grid.missing() == [(2, 1)]
        else:
            assert grid.layout == "full lattice"
            assert len(grid.frame_problems) == 1
            assert re.search(expected, next(iter(grid.frame_problems.values())))


def test_not_a_folder(tmp_path):
    with pytest.raises(GridFormatError, match="no such grid folder"):
        read_grid(tmp_path / "nope")
    (tmp_path / "file.txt").write_text("x")
    with pytest.raises(GridFormatError, match="not a folder"):
        read_grid(tmp_path / "file.txt")


def test_explicit_centre_for_an_even_grid(tmp_path):
    out = tmp_path / "even"
    with GridWriter(out, (2, 2), center=[0, 1]) as w:
        for r in range(2):
            for c in range(2):
                w.add(r, c, _psf(r + c))
    assert read_grid(out).center_index == (0, 1)


def test_writer_is_atomic(tmp_path):
    out = tmp_path / "partial"
    with pytest.raises(RuntimeError), GridWriter(out, (2, 2)) as w:
        w.add(0, 0, _psf(0))
        raise RuntimeError("crash mid-way")
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(GridFormatError, match="never written"), GridWriter(out, (2, 2)) as w:
        w.add(0, 0, _psf(0))
    assert not out.exists()


def test_an_irregular_scan_in_json_and_csv(grid_dir):
    doc = _manifest(grid_dir)
    doc.pop("grid_shape")
    for p in doc["positions"]:
        del p["row"], p["col"]
    _write_manifest(grid_dir, doc)
    grid = read_grid(grid_dir)
    assert grid.layout == "irregular" and grid.grid_shape == (1, 9)
    assert [p.col for p in grid.positions] == list(range(9))
    assert grid.center_index == (0, 4)       # the position at field (0, 0)
    assert grid.find_reference("#2") == (0, 2) == grid.find_reference(doc["positions"][2]["file"])
    (grid_dir / "manifest.json").unlink()
    lines = ["file,monitor_x_px,monitor_y_px,role", *(
        f"{p['file']},{p['monitor_px'][0]},{p['monitor_px'][1]},psf" for p in doc["positions"]),
        "dark.tiff,,,dark"]
    (grid_dir / "manifest.csv").write_text("\n".join(lines) + "\n")
    assert read_grid(grid_dir).layout == "irregular"


@pytest.mark.parametrize("case", ["mixed", "no coordinates", "grid_shape", "half index"])
def test_irregular_manifests_that_are_refused(grid_dir, case):
    doc = _manifest(grid_dir)
    if case == "mixed":
        del doc["positions"][3]["row"], doc["positions"][3]["col"]
        expected = "psf_r01_c00.tiff has no row/col but other positions do"
    else:
        for p in doc["positions"]:
            del p["row"], p["col"]
        if case == "no coordinates":
            doc.pop("grid_shape")
            del doc["positions"][5]["monitor_px"], doc["positions"][5]["field_deg"]
            expected = "an irregular scan needs 'monitor_px' or 'field_deg' for every position"
        elif case == "grid_shape":
            expected = "'grid_shape' describes a lattice"
        else:
            doc.pop("grid_shape")
            doc["positions"][0]["row"] = 0
            expected = "give both 'row' and 'col'"
    _write_manifest(grid_dir, doc)
    with pytest.raises(GridFormatError, match=expected) as info:
        read_grid(grid_dir)
    assert "\n" not in str(info.value)
