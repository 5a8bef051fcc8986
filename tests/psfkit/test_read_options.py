"""The data contract at the I/O boundary: units of integer files, the white level, the read
options recorded in kernel files, and the one PSF loader."""

from __future__ import annotations

import json

import numpy as np
import pytest

from psfkit.calibration.psf_image import load_psf_image, subtract_background
from psfkit.errors import InvalidInputError, ModelFileError
from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels
from psfkit.io import read_pairs, write_image
from psfkit.io.images import read_image_float, unit_range
from psfkit.io.read_options import ReadOptions, choose

RNG = np.random.default_rng(0)
LEVELS = RNG.integers(0, 256, size=(3, 12, 17)).astype(np.uint8)


def test_every_8_bit_level_reads_the_same_from_8_and_16_bit_files(tmp_path):
    q = np.arange(256, dtype=np.uint8).reshape(1, 16, 16).repeat(3, axis=0)
    write_image(tmp_path / "a.png", q)
    write_image(tmp_path / "b.tif", q.astype(np.uint16) * np.uint16(257))
    write_image(tmp_path / "c.png", q.astype(np.uint16) * np.uint16(257))
    a = read_image_float(tmp_path / "a.png")
    assert a.dtype == np.float32 and a.min() == 0 and a.max() == 1
    np.testing.assert_array_equal(a, q.astype(np.float32) / np.float32(255))
    np.testing.assert_array_equal(read_image_float(tmp_path / "b.tif"), a)
    np.testing.assert_array_equal(read_image_float(tmp_path / "c.png"), a)


def test_float_files_are_kept_and_white_level_scales_integers(tmp_path):
    values = RNG.normal(size=(3, 5, 7)).astype(np.float32)        # negative values too
    write_image(tmp_path / "f.npy", values)
    np.testing.assert_array_equal(read_image_float(tmp_path / "f.npy", white_level=7.0), values)
    twelve_bit = (LEVELS.astype(np.uint16) * 16)                  # 0..4080 of 4095
    np.testing.assert_array_equal(unit_range(twelve_bit, "x", white_level=4080),
                                  LEVELS.astype(np.float32) / np.float32(255))
    with pytest.raises(InvalidInputError, match="x: white level"):
        unit_range(twelve_bit, "x", white_level=0)
    bad = values.copy()
    bad[0, 0, 0] = np.inf
    with pytest.raises(InvalidInputError, match="y: contains NaN/Inf"):
        unit_range(bad, "y")


def _pairs(root, scene, measurement, suffix, manifest=None):
    for sub, image in (("scene", scene), ("measurement", measurement)):
        (root / sub).mkdir(parents=True)
        write_image(root / sub / f"a{suffix}", image)
    if manifest is not None:
        (root / "pairs.json").write_text(json.dumps(manifest))
    return root


def test_pairs_white_level_from_pairs_json(tmp_path):
    eight = _pairs(tmp_path / "eight", LEVELS, LEVELS[::-1].copy(), ".png")
    twelve = _pairs(tmp_path / "twelve", LEVELS.astype(np.uint16) * 16,
                    LEVELS[::-1].astype(np.uint16) * 16, ".png", {"white_level": 4080})
    a, b = read_pairs(eight).load(0), read_pairs(twelve).load(0)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert read_pairs(twelve).read_options(2) == ReadOptions("RGB", "none", 2, 4080.0)
    # without the declared white level the same 12-bit files would be 16x too dark
    assert read_pairs(twelve, recorded=ReadOptions(white_level=65535)).white_level == 4080
    (tmp_path / "bad").mkdir()
    bad = _pairs(tmp_path / "bad" / "p", LEVELS, LEVELS, ".png", {"white_level": -1})
    with pytest.raises(InvalidInputError, match=r"pairs\.json: 'white_level' must be positive"):
        read_pairs(bad)


def test_recorded_options_fill_in_what_the_folder_does_not_declare(tmp_path):
    plain = _pairs(tmp_path / "plain", LEVELS.astype(np.float32), LEVELS.astype(np.float32),
                   ".npy")
    recorded = ReadOptions(channel_order="BGR", flip="lr", downsample=2, white_level=100.0)
    pairs = read_pairs(plain, recorded=recorded)
    assert (pairs.channel_order, pairs.flip, pairs.white_level) == ("BGR", "lr", 100.0)
    # a folder's own declaration wins over the record, and an explicit argument over both
    declared = _pairs(tmp_path / "declared", LEVELS.astype(np.float32),
                      LEVELS.astype(np.float32), ".npy", {"channel_order": "RGB"})
    assert read_pairs(declared, recorded=recorded).channel_order == "RGB"
    assert read_pairs(declared, "BGR", recorded=recorded).channel_order == "BGR"
    scene = read_pairs(plain, recorded=recorded).load(0)[0]
    np.testing.assert_array_equal(scene, LEVELS[::-1, :, ::-1].astype(np.float32))


def test_choose_flag_record_default():
    assert choose(None, "BGR", "RGB", "--channel-order", "m.npz") == ("BGR", None)
    assert choose(None, None, "RGB", "--channel-order", "m.npz") == ("RGB", None)
    assert choose("BGR", "BGR", "RGB", "--channel-order", "m.npz") == ("BGR", None)
    value, notice = choose("RGB", "BGR", "RGB", "--channel-order", "m.npz")
    assert value == "RGB" and notice.startswith("note: --channel-order RGB") and \
        "BGR recorded in m.npz" in notice and "\n" not in notice


def test_kernel_file_records_and_checks_read_options_and_origin(tmp_path):
    model = KernelModel(kernels=np.ones((1, 3, 5, 5), np.float32), basis="si",
                        sensor_shape=(8, 8), read_options=ReadOptions("BGR", "none", 4, None))
    path = save_kernels(tmp_path / "k.npz", model)
    assert load_kernels(path).read_options == model.read_options
    assert load_kernels(path).data_read_options().channel_order == "BGR"
    # files written before the options were recorded: the binning from the provenance only
    legacy = KernelModel(kernels=model.kernels, basis="si", sensor_shape=(8, 8),
                         provenance={"downsample": 3})
    assert legacy.data_read_options() == ReadOptions(downsample=3)

    def rewrite(path, **changes):
        with np.load(path) as f:
            kernels, meta = f["kernels"], json.loads(str(f["metadata"]))
        meta.update(changes)
        np.savez(path, kernels=kernels, metadata=json.dumps(meta))

    bad = save_kernels(tmp_path / "bad.npz", model)
    rewrite(bad, read_options={"channel_order": "GRB"})
    with pytest.raises(ModelFileError, match=r"bad\.npz.*channel order must be RGB or BGR"):
        load_kernels(bad)
    origin = save_kernels(tmp_path / "origin.npz", model)
    rewrite(origin, kernel_origin="top-left (0, 0)")
    with pytest.raises(ModelFileError, match=r"origin\.npz.*'kernel_origin'"):
        load_kernels(origin)


def test_the_one_psf_loader(tmp_path):
    psf = np.full((3, 40, 48), 0.05, np.float32)                  # background 0.05
    psf[:, 18:22, 20:26] += RNG.uniform(0.2, 0.9, size=(3, 4, 6)).astype(np.float32)
    psf[1, 30, 5] -= 0.2                                          # negative after background
    path = tmp_path / "psf.tif"
    write_image(path, (psf * 65535).astype(np.uint16))
    kernel = load_psf_image(str(path))
    assert kernel.dtype == np.float32 and kernel.min() == 0
    np.testing.assert_allclose(kernel.sum(axis=(1, 2)), 1, rtol=1e-6)
    expected = np.clip(subtract_background(read_image_float(path).astype(np.float64)), 0, None)
    np.testing.assert_allclose(kernel, expected / expected.sum(axis=(1, 2), keepdims=True),
                               rtol=1e-5, atol=1e-9)
    assert load_psf_image(str(path), downsample=2).shape == (3, 20, 24)
    write_image(tmp_path / "flat.npy", np.full((3, 20, 20), 0.5, np.float32))
    with pytest.raises(InvalidInputError, match=r"flat\.npy: a channel of the PSF has no signal"):
        load_psf_image(str(tmp_path / "flat.npy"))

