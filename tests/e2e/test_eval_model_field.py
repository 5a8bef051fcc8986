"""``psfkit eval-model`` resolved over the field and over the pairs (issue 43, items 4 and 7):
errors by equal-area zone against a hand computation, the residual maps and their figure, and
``--holdout`` recorded by ``fit-pairs`` and honoured by ``eval-model``."""

from __future__ import annotations

import itertools
import json
from pathlib import Path

import numpy as np
import pytest

from psfkit.cli import main
from psfkit.fitting.pairs.fit import predict
from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels
from psfkit.forward.zones import ZONE_NAMES, field_zones

pytestmark = pytest.mark.e2e

SHAPE = (16, 24)


def _camera(seed: int = 3) -> KernelModel:
    rng = np.random.default_rng(seed)
    base = rng.random((1, 3, *SHAPE)) ** 6
    kernels = np.concatenate([base, base + 0.4 * rng.random((2, 3, *SHAPE)) ** 6])
    kernels /= kernels[0].sum(axis=(-2, -1), keepdims=True)
    return KernelModel(kernels=kernels.astype(np.float32), basis="paper", convention="sensor",
                       sensor_shape=SHAPE, channels=("R", "G", "B"))


def _scenes(n: int, seed: int = 4) -> np.ndarray:
    from scipy.ndimage import gaussian_filter

    rng = np.random.default_rng(seed)
    return np.stack([[gaussian_filter(c, 0.8) for c in im]
                     for im in rng.random((n, 3, *SHAPE))]).astype(np.float32)


@pytest.fixture(scope="module")
def edge_case(tmp_path_factory, write_pairs
              ) -> tuple[Path, Path, np.ndarray, np.ndarray, np.ndarray]:
    """A model, and pairs it predicts exactly except in the edge zone."""
    root = tmp_path_factory.mktemp("edge")
    model = _camera()
    model_file = save_kernels(root / "model.npz", model)
    x = _scenes(3)
    p = predict(model, x)
    y = p.copy()
    edge = field_zones(SHAPE).labels == 2
    rng = np.random.default_rng(5)
    y[..., edge] += 0.2 * np.abs(p[..., edge]).mean() * rng.standard_normal(y[..., edge].shape)
    y = y.astype(np.float32)
    return write_pairs(root / "pairs", x, y), model_file, p, y, edge


def test_by_zone_errors_match_a_hand_computation(edge_case, tmp_path, capsys):
    pairs, model_file, p, y, edge = edge_case
    out = tmp_path / "eval.json"
    assert main(["eval-model", str(model_file), str(pairs), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "centre" in printed and "held out" in printed
    doc = json.loads(out.read_text())
    assert doc["zones"]["pixels"] == [128, 128, 128]               # 16 x 24 in equal thirds
    for i in range(3):
        entry = doc["per_pair"][f"im{i}"]
        assert entry["role"] == "held out"          # a hand-made file: fitted on no pairs
        # no error off the edge (the same prediction, up to float32 FFT rounding)
        assert entry["by_zone"]["centre"]["raw"] < 1e-5
        assert entry["by_zone"]["middle"]["raw"] < 1e-5
        by_hand = np.linalg.norm((p[i] - y[i])[:, edge]) / np.linalg.norm(y[i][:, edge])
        assert entry["by_zone"]["edge"]["raw"] == pytest.approx(by_hand, rel=1e-4)
        assert entry["by_zone"]["edge"]["raw"] > 0.05
        # scaled: with the pair's whole-sensor best scale, which the edge error moves
        s = np.sum(p[i].astype(float) * y[i]) / np.sum(p[i].astype(float) ** 2)
        centre = field_zones(SHAPE).labels == 0
        by_hand = (np.linalg.norm((s * p[i] - y[i])[:, centre])
                   / np.linalg.norm(y[i][:, centre]))
        assert entry["by_zone"]["centre"]["scaled"] == pytest.approx(by_hand, rel=1e-3)
    assert doc["by_zone"]["edge"]["raw"] > 1e4 * doc["by_zone"]["centre"]["raw"]
    # the residual map: the edge alone, over the (held-out) pairs
    files = np.load(tmp_path / "eval_residual.npz")
    residual = files["maps"][0]
    assert residual.shape == SHAPE and np.array_equal(files["zones"], field_zones(SHAPE).labels)
    # by hand: the residual with each pair's best scale, RMS over pairs and channels, over the
    # measurements' RMS; off the edge only the scale's small mismatch remains
    p64, y64 = p.astype(float), y.astype(float)
    s = (np.sum(p64 * y64, axis=(1, 2, 3)) / np.sum(p64 ** 2, axis=(1, 2, 3)))[:, None, None,
                                                                                None]
    by_hand = np.sqrt(np.mean((s * p64 - y64) ** 2, axis=(0, 1))) / np.sqrt(np.mean(y64 ** 2))
    np.testing.assert_allclose(residual, by_hand, rtol=1e-3, atol=1e-6)
    assert residual[~edge].max() < 0.05 * residual[edge].mean()
    assert (tmp_path / "eval_residual.png").stat().st_size > 10_000


def _overlapping_texts(fig) -> list[tuple[str, str]]:
    """Pairs of visible, non-empty texts of a rendered figure whose boxes overlap."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.text import Text

    renderer = FigureCanvasAgg(fig).get_renderer()
    fig.draw(renderer)
    texts = [t for t in fig.findobj(Text) if t.get_visible() and t.get_text().strip()]
    boxes = [(t.get_text(), t.get_window_extent(renderer)) for t in texts]
    return [(a, b) for (a, ba), (b, bb) in itertools.combinations(boxes, 2)
            if ba.overlaps(bb)]


@pytest.mark.parametrize("shape", [SHAPE, (67, 120), (270, 480)])
def test_residual_figure_shares_one_labelled_scale_and_no_text_overlaps(shape):
    from psfkit.report.figures.field import RESIDUAL_LABEL, figure_residual_maps

    rng = np.random.default_rng(0)
    maps = [rng.random(shape).astype(np.float32), 0.5 * rng.random(shape).astype(np.float32)]
    fig = figure_residual_maps(maps, ["si.npz: si, source\n1 held-out pair(s)",
                                      "ek.npz: paper, source\n1 held-out pair(s)"],
                               field_zones(shape))
    images = [im for ax in fig.axes for im in ax.get_images()]
    assert len(images) == 2
    assert {im.get_clim() for im in images} == {images[0].get_clim()}   # one colour scale
    bars = [ax for ax in fig.axes if ax.get_ylabel() == RESIDUAL_LABEL]
    assert len(bars) == 1
    assert _overlapping_texts(fig) == []


def test_fit_pairs_holdout_is_recorded_and_eval_model_reports_it(tmp_path, capsys,
                                                                write_pairs):
    camera = _camera(7)
    x = _scenes(7, seed=8)
    pairs = write_pairs(tmp_path / "pairs", x, predict(camera, x))
    flags = ["--no-scale", "--no-nonneg", "--iterations", "100", "--quiet"]   # fast: CG only
    si, ek = tmp_path / "si.npz", tmp_path / "ek.npz"
    assert main(["fit-pairs", str(pairs), "--basis", "si", "--holdout", "im2,im5",
                 "--out", str(si), *flags]) == 0
    assert "held out (not fitted; recorded in si.npz): im2, im5" in capsys.readouterr().out
    assert main(["fit-pairs", str(pairs), "--basis", "ek", "--holdout", "im2",
                 "--holdout", "im5.npy", "--out", str(ek), *flags]) == 0
    for file in (si, ek):
        record = load_kernels(file).provenance
        assert record["holdout"] == ["im2", "im5"]
        assert record["names"] == ["im0", "im1", "im3", "im4", "im6"]   # fitted on the rest
        assert Path(record["pairs"]) == pairs.resolve()
    # honoured: the fit is that of the five pairs alone
    five = tmp_path / "five"
    keep = [0, 1, 3, 4, 6]
    write_pairs(five, x[keep], predict(camera, x[keep]))
    alone = tmp_path / "alone.npz"
    assert main(["fit-pairs", str(five), "--basis", "si", "--out", str(alone), *flags]) == 0
    np.testing.assert_allclose(load_kernels(si).kernels, load_kernels(alone).kernels,
                               rtol=0, atol=1e-6 * float(load_kernels(alone).kernels.max()))
    capsys.readouterr()
    out = tmp_path / "eval.json"
    assert main(["eval-model", str(si), str(ek), str(pairs), "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "fitted on 5 of these pairs, 2 held out" in printed
    doc = json.loads(out.read_text())
    assert [m["model"] for m in doc["models"]] == [str(si), str(ek)]
    for result in doc["models"]:
        roles = {name: entry["role"] for name, entry in result["per_pair"].items()}
        assert [n for n, r in roles.items() if r == "held out"] == ["im2", "im5"]
        held, fitted = result["held_out"], result["fitted"]
        assert held["pairs"] == ["im2", "im5"] and fitted["pairs_count"] == 5
        assert held["mean_scaled"] == pytest.approx(np.mean(
            [result["per_pair"][n]["scaled"] for n in ("im2", "im5")]))
        assert set(held["by_zone"]) == set(ZONE_NAMES)
        assert result["residual_map"]["pairs"] == ["im2", "im5"]
    # the pairs come from an eigen-kernel camera: EK predicts the held-out pairs better
    assert doc["models"][1]["held_out"]["mean_raw"] < doc["models"][0]["held_out"]["mean_raw"]
    assert np.load(tmp_path / "eval_residual.npz")["maps"].shape == (2, *SHAPE)
    # eval-model --holdout must agree with the record
    capsys.readouterr()
    assert main(["eval-model", str(si), str(pairs), "--holdout", "im0"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "im0" in err and "fitted" in err
    assert main(["eval-model", str(si), str(pairs), "--holdout", "im5"]) == 0


def test_eval_model_holdout_declares_the_split_of_an_unrecorded_file(edge_case, tmp_path,
                                                                     capsys):
    pairs, model_file, *_ = edge_case
    out = tmp_path / "e.json"
    assert main(["eval-model", str(model_file), str(pairs), "--holdout", "im1",
                 "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert [e["role"] for e in doc["per_pair"].values()] == ["fitted", "held out", "fitted"]
    assert doc["held_out"]["pairs"] == ["im1"] and doc["fitted"]["pairs_count"] == 2
    # every output refused before any work when one exists (the set is written together)
    capsys.readouterr()
    assert main(["eval-model", str(model_file), str(pairs), "--out", str(out)]) == 2
    assert "exists" in capsys.readouterr().err


def test_fit_pairs_holdout_of_every_pair_or_an_unknown_one_is_one_line(edge_case, tmp_path,
                                                                       capsys):
    pairs, *_ = edge_case
    for holdout, words in (("im0,im1,im2", "every pair is held out"),
                           ("im7", "no pair named im7")):
        assert main(["fit-pairs", str(pairs), "--holdout", holdout,
                     "--out", str(tmp_path / "k.npz"), "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.count("\n") == 0 and words in err
        assert not (tmp_path / "k.npz").exists()


def test_learned_kernels_record_their_training_pairs_for_eval_model(tiny_data, tmp_path,
                                                                   capsys):
    from ekdun.cli import main as ekdun_main
    from ekdun.data.pairs import PairsDataset
    from ekdun.training import TrainOptions, train

    pairs, kernels = tiny_data
    run = tmp_path / "run"
    train(run, "ekdun", kernels, PairsDataset(pairs, holdout=("im6", "im7")), "tiny",
          {"iterations": 2, "prior": {"widths": [4, 8]}},
          TrainOptions(epochs=1, batch_size=4, progress=False, threads=1))
    learned = tmp_path / "learned.npz"
    assert ekdun_main(["export-kernels", str(run / "checkpoint.pt"), "--out",
                       str(learned)]) == 0
    record = load_kernels(learned).provenance
    assert record["holdout"] == ["im6", "im7"] and len(record["names"]) == 6
    out = tmp_path / "e.json"
    assert main(["eval-model", str(learned), str(pairs), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["held_out"]["pairs"] == ["im6", "im7"] and doc["fitted"]["pairs_count"] == 6


def test_a_zone_without_light_is_null_not_an_error(tmp_path, write_pairs):
    model = _camera(11)
    x = _scenes(2, seed=12)
    y = predict(model, x)
    edge = field_zones(SHAPE).labels == 2
    y[0][:, edge] = 0.0                               # no light at the edge of pair 0
    pairs = write_pairs(tmp_path / "pairs", x, y)
    model_file = save_kernels(tmp_path / "m.npz", model)
    out = tmp_path / "e.json"
    assert main(["eval-model", str(model_file), str(pairs), "--out", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["per_pair"]["im0"]["by_zone"]["edge"] == {"raw": None, "scaled": None}
    # the means are over the pairs where the zone has light
    assert doc["by_zone"]["edge"]["raw"] == pytest.approx(
        doc["per_pair"]["im1"]["by_zone"]["edge"]["raw"])
