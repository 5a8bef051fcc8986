"""`ekdun train --kernel-lr-scale`: 0 freezes the physics kernels at --kernels (the U-Net
absorption runs of issue 24 train EK-DUN on an oracle's kernels, frozen)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ekdun.cli import main as ekdun_main
from ekdun.training import load_checkpoint
from psfkit.forward.kernelfile import load_kernels


def _train(pairs, kernel_file, run, *extra: str) -> int:
    return ekdun_main(["train", str(pairs), str(run), "--kernels", str(kernel_file),
                       "--epochs", "2", "--iterations", "2", "--batch-size", "2",
                       "--device", "cpu", "--threads", "1", "--seed", "1", "--quiet", *extra])


def test_scale_zero_freezes_the_kernels_and_is_recorded(tiny_data, tmp_path):
    pairs, kernel_file = tiny_data
    assert _train(pairs, kernel_file, tmp_path / "frozen", "--kernel-lr-scale", "0") == 0
    assert _train(pairs, kernel_file, tmp_path / "free", "--kernel-lr-scale", "1") == 0
    frozen = load_kernels(tmp_path / "frozen" / "kernels_learned.npz").kernels
    start = load_kernels(tmp_path / "frozen" / "kernels_initial.npz").kernels
    np.testing.assert_array_equal(frozen, start)
    # the same training with the kernels' learning rate on moves them
    moved = load_kernels(tmp_path / "free" / "kernels_learned.npz").kernels
    assert np.abs(moved - start).max() > 1e-6 * np.abs(start).max()
    meta = load_checkpoint(tmp_path / "frozen" / "checkpoint.pt")["metadata"]
    assert meta["training"]["kernel_lr_scale"] == 0.0
    assert meta["epoch"] == 2
    # Table 2 does not pool a frozen-kernel run with the learned ones
    assert ekdun_main(["eval", str(tmp_path / "frozen"), str(tmp_path / "free"), "--data",
                       str(pairs), "--include-training", "--out", str(tmp_path / "tables"),
                       "--quiet"]) == 0
    rows = json.loads((tmp_path / "tables" / "table2.json").read_text())["rows"]
    labels = {Path(r["checkpoint"]).parent.name: r["label"] for r in rows}
    assert labels["frozen"] == labels["free"] + " (frozen kernels)"


def test_scale_is_refused_where_it_cannot_apply(tiny_data, tmp_path, capsys):
    pairs, kernel_file = tiny_data
    code = ekdun_main(["train", str(pairs), str(tmp_path / "u"), "--kernels", str(kernel_file),
                       "--network", "updn", "--kernel-lr-scale", "0", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--kernel-lr-scale" in err[0]
    assert _train(pairs, kernel_file, tmp_path / "n", "--kernel-lr-scale", "-1") == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--kernel-lr-scale" in err[0]
    assert not (tmp_path / "u").exists() and not (tmp_path / "n").exists()
