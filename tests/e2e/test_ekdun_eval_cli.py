"""Metrics, tables, the reconstruct / eval / admm commands and bad-input errors."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import torch
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

from analysis._tables import missing_rows
from ekdun.cli import main as ekdun_main
from ekdun.data.deadleaves import dead_leaves
from ekdun.errors import InvalidInputError, TensorShapeError
from ekdun.evaluation import (
    LPIPSMetric,
    psnr,
    read_results,
    render_table,
    ssim,
    write_results,
    write_table,
    write_tables,
)
from ekdun.evaluation.evaluate import seed_kernels_identity
from ekdun.physics.operators import ShiftInvariantOperator
from ekdun.reconstruction import admm_tv
from ekdun.training import TrainOptions, train
from ekdun.training.trainer import CHECKPOINT
from psfkit.forward.zones import field_zones

SMALL = {"iterations": 2, "prior": {"widths": [4, 8]}}


@pytest.fixture(scope="module")
def tiny_checkpoint(tiny_data, tmp_path_factory):
    pairs, kernels = tiny_data
    from ekdun.data.pairs import PairsDataset

    run = tmp_path_factory.mktemp("run") / "ek"
    train(run, "ekdun", kernels, PairsDataset(pairs, holdout=("im6", "im7")), "tiny", SMALL,
          TrainOptions(epochs=1, batch_size=4, progress=False, threads=1))
    return run / CHECKPOINT


def _one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("ekdun: error:")
    return err[0]


@pytest.mark.parametrize("channels", [1, 3])
def test_metrics_match_skimage(channels):
    rng = np.random.default_rng(0)
    x = rng.random((2, channels, 40, 52))
    y = np.clip(x + 0.1 * rng.standard_normal(x.shape), 0, 1)
    got_ssim = ssim(torch.as_tensor(y), torch.as_tensor(x)).numpy()
    got_psnr = psnr(torch.as_tensor(y), torch.as_tensor(x)).numpy()
    for i in range(2):
        ref = structural_similarity(y[i], x[i], data_range=1.0, channel_axis=0,
                                    gaussian_weights=True, sigma=1.5,
                                    use_sample_covariance=False)
        assert got_ssim[i] == pytest.approx(ref, abs=1e-6)
        assert got_psnr[i] == pytest.approx(peak_signal_noise_ratio(x[i], y[i], data_range=1),
                                            abs=1e-8)


def test_ssim_refuses_images_smaller_than_its_window():
    small = torch.zeros(1, 1, 10, 12)
    with pytest.raises(TensorShapeError, match="SSIM needs images of at least 11x11, got 10x12"):
        ssim(small, small)


def test_one_list_of_model_names_offered_without_importing_torch():
    code = ("import sys, json\n"
            "from ekdun.cli import build_parser\n"
            "sub = build_parser()._subparsers._group_actions[0].choices\n"
            "model = [a for a in sub['train']._actions if a.dest == 'network'][0]\n"
            "print(json.dumps([list(model.choices), 'torch' in sys.modules]))")
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120, check=True)
    choices, torch_loaded = json.loads(run.stdout)
    from ekdun.nets import MODEL_NAMES

    assert choices == list(MODEL_NAMES) == ["ekdun", "le-admm-u", "updn"]
    assert not torch_loaded


def test_lpips_says_clearly_when_unavailable(tmp_path):
    metric = LPIPSMetric(tmp_path / "missing.pth")
    # here the 'lpips' package cannot be imported (its torchvision needs another torch), and
    # the weights are missing: never a value from a random network
    assert not metric.available and metric.reason.startswith("LPIPS n/a")
    assert torch.isnan(metric(torch.zeros(1, 3, 16, 16), torch.zeros(1, 3, 16, 16))).all()


def test_tables_markdown_and_json(tmp_path):
    rows = [
        {"label": "EK-DUN (base)", "model": "ekdun", "schedule": "base", "psnr": 20.0,
         "ssim": 0.5, "lpips": None, "parameters": 10, "runtime_ms_median": 1.0,
         "peak_memory_mib": 2.0},
        {"label": "EK-DUN (last-2)", "model": "ekdun", "schedule": "last-2", "psnr": 21.5,
         "ssim": 0.6, "lpips": None, "parameters": 10, "runtime_ms_median": 1.0,
         "peak_memory_mib": 2.0},
        {"label": "Le-ADMM-U", "model": "le-admm-u", "schedule": None, "psnr": 19.0,
         "ssim": 0.4, "lpips": None, "parameters": 1000, "runtime_ms_median": 3.0,
         "peak_memory_mib": 4.0},
    ]
    written = write_tables(tmp_path, rows, ["LPIPS n/a: test"])
    t1 = (tmp_path / "table1.md").read_text()
    assert "| Le-ADMM-U | 19.00 | 0.4000 | n/a | 1,000 |" in t1
    assert "EK-DUN (last-2)" in t1 and "EK-DUN (base)" not in t1
    t2 = json.loads((tmp_path / "table2.json").read_text())
    assert [r["label"] for r in t2["rows"]] == ["base only", "last-2"]
    assert "LPIPS n/a" in (tmp_path / "table2.md").read_text()
    assert set(written) >= {"table1.md", "table2.md", "results.json"}


def ekdun_row(schedule: str, seed: int, psnr: float, **extra) -> dict:
    return {"label": f"EK-DUN ({schedule})", "model": "ekdun", "schedule": schedule,
            "seed": seed, "psnr": psnr, "ssim": 0.5 + seed / 100, "lpips": None,
            "parameters": 10, "runtime_ms_median": 1.0 + seed, "peak_memory_mib": 2.0,
            "kernel_param": "free", "physics_weight": 0.0, **extra}


def test_table1_over_training_seeds_compares_each_baseline_with_ekdun_seed_by_seed(tmp_path):
    rows = [ekdun_row("last-2", s, p) for s, p in ((0, 22.0), (1, 23.0), (2, 24.0))]
    rows += [{**ekdun_row("last-2", s, p), "model": "updn", "schedule": None, "label": "UPDN"}
             for s, p in ((2, 23.5), (0, 21.0), (1, 22.5))]
    write_tables(tmp_path, rows)
    doc = json.loads((tmp_path / "table1.json").read_text())
    assert [(r["label"], r["seed"]) for r in doc["rows"]] == [
        ("EK-DUN (last-2)", 0), ("EK-DUN (last-2)", 1), ("EK-DUN (last-2)", 2),
        ("UPDN", 0), ("UPDN", 1), ("UPDN", 2)]
    updn = {e["label"]: e for e in doc["over_seeds"]}["UPDN"]
    # paired Δ −1.0, −0.5, −0.5 (the unpaired means differ by −0.67 too, but with a wider sd)
    assert updn["reference"] == "EK-DUN (last-2)"
    assert updn["delta_mean"] == pytest.approx(-2 / 3) and updn["delta_seeds"] == [0, 1, 2]
    assert updn["delta_sd"] == pytest.approx(np.std([-1.0, -0.5, -0.5], ddof=1))
    text = (tmp_path / "table1.md").read_text()
    assert "| UPDN | 22.33 ± 1.26 (n = 3) |" in text and "Δ PSNR to EK-DUN (last-2)" in text


def test_table2_over_training_seeds_pairs_by_seed_and_keeps_variants_apart(tmp_path):
    rows = [ekdun_row("base", s, p) for s, p in ((0, 20.0), (1, 21.0), (2, 22.0))]
    rows += [ekdun_row("last-2", s, p) for s, p in ((2, 22.5), (0, 21.0), (1, 22.5))]
    rows += [ekdun_row("last-2", 0, 20.5, physics_weight=1.0),
             ekdun_row("last-2", 1, 23.0, kernel_param="flow"),
             ekdun_row("all", 0, 19.0), ekdun_row("all", 0, 19.5)]   # one seed twice
    write_tables(tmp_path, rows)
    doc = json.loads((tmp_path / "table2.json").read_text())
    assert [(r["label"], r["seed"]) for r in doc["rows"]] == [
        ("base only", 0), ("base only", 1), ("base only", 2),
        ("last-2", 0), ("last-2", 1), ("last-2", 2), ("last-2 (flow kernels)", 1),
        ("last-2 (λ = 1)", 0), ("all", 0), ("all", 0)]
    summary = {e["label"]: e for e in doc["over_seeds"]}
    last2 = summary["last-2"]           # Δ 1.0, 1.5, 0.5 paired; unpaired means differ by 0.67
    assert last2["delta_mean"] == pytest.approx(1.0)
    assert last2["delta_sd"] == pytest.approx(0.5)
    assert last2["delta_seeds"] == [0, 1, 2]
    assert last2["psnr_mean"] == pytest.approx(22.0) and last2["psnr_sd"] == pytest.approx(
        np.std([21.0, 22.5, 22.5], ddof=1))
    assert last2["runtime_ms_median"] == pytest.approx(2.0)
    assert summary["last-2 (λ = 1)"]["delta_mean"] == pytest.approx(0.5)
    assert summary["last-2 (λ = 1)"]["psnr_sd"] is None
    assert summary["last-2 (flow kernels)"]["delta_mean"] == pytest.approx(2.0)
    assert summary["all"]["delta_seeds"] == [] and summary["all"]["delta_text"] == "n/a"
    assert summary["base only"]["delta_mean"] is None
    text = (tmp_path / "table2.md").read_text()
    assert "| last-2 | 22.00 ± 0.87 (n = 3) | 0.5100 | +1.00 ± 0.50 (n = 3) | 2.00 |" in text
    # Table 1 takes the paper's last-2 rows; variants keep their own labels
    t1 = [r["label"] for r in json.loads((tmp_path / "table1.json").read_text())["rows"]]
    assert t1.count("EK-DUN (last-2)") == 3
    assert {"EK-DUN (last-2, λ = 1)", "EK-DUN (last-2, flow kernels)"} <= set(t1)
    assert missing_rows(rows[-2:], "table2") == ["base only", "last-2"]
    assert missing_rows([rows[6]], "table1") == ["EK-DUN (last-2)", "Le-ADMM-U", "UPDN"]


def test_runs_from_different_seed_kernels_are_not_pooled_as_training_seeds(tmp_path):
    # the Fig. 7 grid on a GPU: the measured and the one-PSF seed, same flags, training seed 0
    one = {"seed_kernels_sha": "aaaa11112222", "seed_kernels_one_psf": True}
    measured = {"seed_kernels_sha": "bbbb11112222", "seed_kernels_one_psf": False}
    pairs = {"seed_kernels_sha": "cccc11112222", "seed_kernels_one_psf": False}
    rows = [ekdun_row("last-2", 0, 24.4, kernel_param="flow", **one),
            ekdun_row("last-2", 0, 24.6, kernel_param="flow", **measured),
            ekdun_row("last-2", 1, 24.2, kernel_param="flow", **measured),
            ekdun_row("last-2", 0, 23.0, kernel_param="flow", **pairs)]
    write_tables(tmp_path, rows)
    doc = json.loads((tmp_path / "table2.json").read_text())
    summary = {e["label"]: e for e in doc["over_seeds"]}
    assert set(summary) == {"last-2 (one-PSF seed, flow kernels)",
                            "last-2 (flow kernels, seed kernels bbbb1111)",
                            "last-2 (flow kernels, seed kernels cccc1111)"}
    assert summary["last-2 (flow kernels, seed kernels bbbb1111)"]["seeds"] == [0, 1]
    assert summary["last-2 (one-PSF seed, flow kernels)"]["psnr_sd"] is None
    # one seed per label: no suffix
    write_tables(tmp_path / "b", rows[1:3])
    doc = json.loads((tmp_path / "b" / "table2.json").read_text())
    assert [e["label"] for e in doc["over_seeds"]] == ["last-2 (flow kernels)"]


def test_seed_kernels_identity_tells_the_one_psf_seed_from_a_fit():
    k = torch.rand(3, 1, 8, 8)
    fit = seed_kernels_identity({"initial_kernels": k})
    assert not fit["seed_kernels_one_psf"] and len(fit["seed_kernels_sha"]) == 12
    one = seed_kernels_identity({"initial_kernels": k[:1].repeat(3, 1, 1, 1)})
    assert one["seed_kernels_one_psf"] and one["seed_kernels_sha"] != fit["seed_kernels_sha"]
    assert seed_kernels_identity({"initial_kernels": k.clone()}) == fit   # content, not object
    assert seed_kernels_identity({}) == {"seed_kernels_sha": None, "seed_kernels_one_psf": None}


def test_one_table_at_a_time_and_results_round_trip(tmp_path):
    rows = [
        {"label": "EK-DUN (all)", "model": "ekdun", "schedule": "all", "psnr": 20.0,
         "ssim": 0.5, "lpips": None, "parameters": 10, "runtime_ms_median": 1.0,
         "peak_memory_mib": 2.0},
        {"label": "UPDN", "model": "updn", "schedule": None, "psnr": 19.0, "ssim": 0.4,
         "lpips": None, "parameters": 20, "runtime_ms_median": 2.0, "peak_memory_mib": 3.0},
    ]
    write_results(tmp_path / "r", rows, ["a note"])
    back, notes = read_results(tmp_path / "r")              # a folder means its results.json
    assert back == rows and notes == ["a note"]
    text = render_table(back, "table2", notes)
    assert "| all | 20.00 | 0.5000 | n/a | 1.00 | n/a | n/a |" in text   # no zones, no seed
    assert text.rstrip().endswith("a note") and "Over training seeds" not in text
    assert missing_rows(back, "table2") == ["base only", "last-2"]
    assert missing_rows(back, "table1") == ["EK-DUN (last-2)", "Le-ADMM-U"]
    written = write_table(tmp_path / "t", back, "table1")
    assert sorted(written) == ["table1.json", "table1.md"]
    assert "| UPDN | 19.00 |" in (tmp_path / "t" / "table1.md").read_text()
    assert [r["label"] for r in json.loads((tmp_path / "t" / "table1.json").read_text())[
        "rows"]] == ["UPDN"]
    with pytest.raises(InvalidInputError, match="no rows for Table 1"):
        write_table(tmp_path / "u", back[:1], "table1")
    assert not (tmp_path / "u").exists()
    bad = tmp_path / "bad.json"
    bad.write_text('{"rows": []}')
    with pytest.raises(InvalidInputError, match="not an ekdun results file"):
        read_results(bad)
    with pytest.raises(InvalidInputError, match="no such results file"):
        read_results(tmp_path / "absent.json")


def test_eval_and_reconstruct_end_to_end(tiny_data, tiny_checkpoint, tmp_path, capsys):
    pairs, _ = tiny_data
    assert ekdun_main(["eval", str(tiny_checkpoint), "--data", str(pairs), "--out",
                       str(tmp_path / "tables"), "--quiet"]) == 0
    res = json.loads((tmp_path / "tables" / "results.json").read_text())["results"][0]
    assert res["pairs"] == ["im6", "im7"]          # only what training held out is scored
    assert len(res["seed_kernels_sha"]) == 12 and res["seed_kernels_one_psf"] is False
    assert np.isfinite(res["psnr"]) and 0 < res["ssim"] <= 1 and res["parameters"] > 0
    assert res["runtime_ms_median"] > 0 and res["model"] == "ekdun"
    assert (tmp_path / "tables" / "table2.md").is_file()

    out = tmp_path / "recon"
    assert ekdun_main(["reconstruct", str(tiny_checkpoint), str(pairs / "measurement"),
                       "--out", str(out)]) == 0
    names = sorted(p.name for p in out.iterdir())
    assert names == sorted([f"im{i}.{s}" for i in range(8) for s in ("npy", "png")])
    image = np.load(out / "im0.npy")
    assert image.shape == (16, 16, 3) and np.isfinite(image).all()
    # the per-pair figures are those of each reconstruction against its scene (skimage's
    # PSNR, independent of ours), and the headline is their mean
    for name, value in zip(res["pairs"], res["psnr_per_pair"], strict=True):
        truth = np.load(pairs / "scene" / f"{name}.npy")
        recon = np.clip(np.load(out / f"{name}.npy"), 0, 1)
        assert value == pytest.approx(peak_signal_noise_ratio(truth, recon, data_range=1.0),
                                      abs=1e-3)
    assert res["psnr"] == pytest.approx(np.mean(res["psnr_per_pair"]), abs=1e-9)
    assert res["ssim"] == pytest.approx(np.mean(res["ssim_per_pair"]), abs=1e-9)
    # by field zone: PSNR of the zone's pixels and the mean of skimage's SSIM map over the
    # zone (inside the window's margin), computed here directly from the files
    zones = field_zones((16, 16))
    assert res["zones"]["pixels"] == [85, 85, 86]
    margin = (11 - 1) // 2
    inner = zones.cropped(margin)
    for i, name in enumerate(res["pairs"]):
        truth = np.load(pairs / "scene" / f"{name}.npy").astype(np.float64)
        recon = np.clip(np.load(out / f"{name}.npy"), 0, 1).astype(np.float64)
        _, local = structural_similarity(truth, recon, data_range=1.0, channel_axis=-1,
                                         gaussian_weights=True, sigma=1.5,
                                         use_sample_covariance=False, full=True)
        local = local[margin:-margin, margin:-margin]
        for zone, mask in zones.masks().items():
            mse = np.mean((truth - recon)[mask] ** 2)
            assert res["by_zone"][zone]["psnr_per_pair"][i] == pytest.approx(
                10 * np.log10(1 / mse), abs=1e-3)
            if inner.masks()[zone].any():
                assert res["by_zone"][zone]["ssim_per_pair"][i] == pytest.approx(
                    local[inner.masks()[zone]].mean(), abs=1e-4)
            else:   # 16 x 16: the window's valid region (6 x 6) lies in the centre zone
                assert res["by_zone"][zone]["ssim"] is None
    for zone in ("centre", "middle", "edge"):
        assert res["by_zone"][zone]["psnr"] == pytest.approx(
            np.mean(res["by_zone"][zone]["psnr_per_pair"]), abs=1e-9)
    table = (tmp_path / "tables" / "table2.md").read_text()
    assert "PSNR centre / middle / edge (dB)" in table
    assert " / ".join(f"{res['by_zone'][z]['psnr']:.2f}" for z in ("centre", "middle", "edge")) \
        in table


def test_eval_rows_carry_seed_parameterisation_and_physics_weight(tiny_data, tiny_checkpoint,
                                                                  tmp_path):
    pairs, kernels = tiny_data
    from ekdun.data.pairs import PairsDataset
    from research.kernel_models import train as train_study

    run = tmp_path / "flow-l05"        # a research run (its settings in metadata "study")
    train_study(run, "ekdun", kernels, PairsDataset(pairs, holdout=("im6", "im7")), "tiny",
                {**SMALL, "kernel_param": "flow"},
                TrainOptions(epochs=1, batch_size=4, progress=False, threads=1, seed=5),
                physics_weight=0.5)
    assert ekdun_main(["eval", str(tiny_checkpoint), str(run), "--data", str(pairs), "--out",
                       str(tmp_path / "t"), "--quiet"]) == 0
    paper, flow = json.loads((tmp_path / "t" / "results.json").read_text())["results"]
    assert (paper["seed"], paper["kernel_param"], paper["physics_weight"]) == (0, "free", 0.0)
    assert (flow["seed"], flow["kernel_param"], flow["physics_weight"]) == (5, "flow", 0.5)
    labels = [r["label"] for r in json.loads((tmp_path / "t" / "table2.json").read_text())[
        "rows"]]
    assert labels == ["last-2", "last-2 (flow kernels, λ = 0.5)"]


def test_bad_inputs_give_one_line_errors_and_no_outputs(tiny_data, tiny_checkpoint,
                                                        tmp_path, capsys):
    pairs, kernels = tiny_data
    # measurement size does not match the model
    wrong = tmp_path / "wrong.npy"
    np.save(wrong, np.zeros((20, 20, 3), np.float32))
    out = tmp_path / "out"
    assert ekdun_main(["reconstruct", str(tiny_checkpoint), str(wrong), "--out",
                       str(out)]) == 2
    assert "20x20x3 but the model expects 16x16x3" in _one_error_line(capsys)
    assert not out.exists()
    # corrupt checkpoint
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"PK\x03\x04 not really a zip")
    assert ekdun_main(["reconstruct", str(bad), str(pairs / "measurement"), "--out",
                       str(out)]) == 2
    assert "not a readable checkpoint" in _one_error_line(capsys)
    assert not out.exists()
    # empty dataset folder
    empty = tmp_path / "empty"
    (empty / "scene").mkdir(parents=True)
    (empty / "measurement").mkdir()
    run = tmp_path / "run"
    assert ekdun_main(["train", str(empty), str(run), "--kernels", str(kernels),
                       "--quiet"]) == 2
    assert "empty pairs folder" in _one_error_line(capsys)
    assert not run.exists()
    # unpaired files
    np.save(empty / "scene" / "a.npy", np.zeros((16, 16, 3), np.float32))
    np.save(empty / "measurement" / "b.npy", np.zeros((16, 16, 3), np.float32))
    assert ekdun_main(["train", str(empty), str(run), "--kernels", str(kernels),
                       "--quiet"]) == 2
    assert "unpaired file(s)" in _one_error_line(capsys)
    assert not run.exists()
    # training pairs of the wrong size for the kernel file
    np.save(empty / "measurement" / "a.npy", np.zeros((16, 16, 3), np.float32))
    (empty / "measurement" / "b.npy").unlink()
    big = tmp_path / "big"
    for sub in ("scene", "measurement"):
        (big / sub).mkdir(parents=True)
        np.save(big / sub / "a.npy", np.zeros((20, 20, 3), np.float32))
    assert ekdun_main(["train", str(big), str(run), "--kernels", str(kernels),
                       "--quiet"]) == 2
    assert "model's sensor is 16x16" in _one_error_line(capsys)
    assert not run.exists()


def test_admm_tv_recovers_a_synthetic_scene():
    rng = np.random.default_rng(0)
    psf = np.zeros((1, 32, 32))
    psf[0, rng.integers(0, 32, 20), rng.integers(0, 32, 20)] = 1.0
    x = torch.as_tensor(dead_leaves((48, 48), 3, channels=1))[None].double()
    op = ShiftInvariantOperator(torch.as_tensor(psf / psf.sum()), (48, 48)).double()
    y = op.A(x)
    y = y + 1e-3 * y.max() * torch.randn(y.shape, generator=torch.Generator().manual_seed(0),
                                         dtype=y.dtype)
    back = op.A_adjoint(y)
    back = back * (back * x).sum() / (back * back).sum()        # best-scaled Aᵀy
    recon = admm_tv(y[0], psf, iterations=200, tau=1e-3)
    baseline = float(psnr(back.clamp(0, 1), x)[0])
    got = float(psnr(recon[None].clamp(0, 1), x)[0])
    assert got > baseline + 5.0, (got, baseline)


def test_admm_cli_on_the_real_diffusercam_tutorial_data(real_data, tmp_path):
    folder = real_data("diffusercam_tutorial")
    out = tmp_path / "hand.npy"
    assert ekdun_main(["admm", str(folder / "psf_sample.tif"),
                       str(folder / "rawdata_hand_sample.tif"), "--out", str(out),
                       "--downsample", "8", "--iterations", "40"]) == 0
    image = np.load(out)
    assert image.shape == (150, 200) and np.isfinite(image).all()
    assert image.std() > 0.05 * image.max() > 0
    assert out.with_suffix(".png").is_file()
