"""Pairs folders: layouts, channel order, flips, and every refusal."""

import json

import numpy as np
import pytest

from psfkit.errors import InvalidInputError
from psfkit.io import read_pairs, write_image


def _pairs(root, names=("a", "b"), shape=(3, 8, 10), scene_dir="scene",
           measurement_dir="measurement", suffix=".npy"):
    rng = np.random.default_rng(0)
    for name in names:
        write_image(root / scene_dir / f"{name}{suffix}", rng.random(shape).astype(np.float32))
        write_image(root / measurement_dir / f"{name}{suffix}",
                    rng.random(shape).astype(np.float32))
    return root


def test_generic_layout(tmp_path):
    pairs = read_pairs(_pairs(tmp_path / "p"))
    assert pairs.names == ("a", "b") and pairs.shape == (3, 8, 10)
    scenes, measurements = pairs.load_all()
    assert scenes.shape == (2, 3, 8, 10) and measurements.dtype == np.float32


def test_dlmd_layout_is_read_as_rgb(real_data):
    pairs = read_pairs(real_data("dlmd_mirflickr"))
    assert pairs.channel_order == "BGR" and len(pairs) == 7
    scene, _ = pairs.load(0)
    raw = np.load(real_data("dlmd_mirflickr", "lensed", pairs.scene_files[0]))
    np.testing.assert_array_equal(scene[0], raw[..., 2])          # R came from the last axis


def test_manifest_flip_and_names(tmp_path):
    root = _pairs(tmp_path / "p", scene_dir="targets", measurement_dir="captures")
    (root / "pairs.json").write_text(json.dumps({"scene_dir": "targets",
                                                 "measurement_dir": "captures", "flip": "ud"}))
    pairs = read_pairs(root)
    scene, _ = pairs.load(0)
    np.testing.assert_array_equal(scene, np.moveaxis(np.load(root / "targets" / "a.npy"), -1,
                                                     0)[:, ::-1])


@pytest.mark.parametrize("case,message", [
    ("missing", "no such pairs folder"),
    ("empty", "empty pairs folder"),
    ("unpaired", "unpaired file(s) measurement/c.npy"),
    ("no scene dir", "no scene folder"),
    ("size", "scene 8×10×3 differs from its measurement 8×11×3"),
    ("nan", "contains NaN/Inf"),
])
def test_refusals(tmp_path, case, message):
    root = tmp_path / "p"
    if case == "empty":
        (root / "scene").mkdir(parents=True)
        (root / "measurement").mkdir()
    elif case != "missing":
        _pairs(root)
    if case == "unpaired":
        write_image(root / "measurement" / "c.npy", np.zeros((3, 8, 10), np.float32))
    if case == "no scene dir":
        (root / "scene").rename(root / "elsewhere")
    if case == "size":
        write_image(root / "measurement" / "a.npy", np.ones((3, 8, 11), np.float32))
    if case == "nan":
        bad = np.ones((3, 8, 10), np.float32)
        bad[0, 1, 1] = np.nan
        np.save(root / "scene" / "b.npy", np.moveaxis(bad, 0, -1))  # write_image refuses NaN
    with pytest.raises(InvalidInputError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_pairs(root)
