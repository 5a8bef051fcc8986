"""Do EK-DUN's learned kernels stay physical? Free / physical / flow kernels, two seeds.

On the virtual bench (``ekdun benchmark-tiny``'s dataset, tiny preset, CPU), EK-DUN last-2 is
trained with each kernel parameterisation (``--kernel-param``), seeded from the measured fit
(``psfkit fit-eigen`` of the dataset's grid) and from one PSF (``Kv = Kh = Kbase`` = the fit's
``Kbase``). For each run: test PSNR/SSIM, the kernel-change split (pedestal fraction, gain,
displacement) against the initial kernels, the displacement-map correlation and difference
NCC against the measured modes, and the principal angles to the top PCA modes
(``psfkit.compare``).

``--measure-lr`` instead reports, at the seed, the RMS of each kernel parameter group and of
its gradient over a few batches next to the network's, and the relative size of one Adam step
(``lr / RMS(parameter)``) each learning rate gives: the measurement behind
``LR_MULTIPLIER``.

Usage::

    python benchmarks/bench_kernel_parameterisations.py --out runs/kparam [--epochs 15]
"""

from __future__ import annotations

import argparse
import itertools
import json
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from ekdun.benchmark import fit_seed_kernels  # noqa: E402
from ekdun.data.pairs import PairsDataset  # noqa: E402
from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench  # noqa: E402
from ekdun.evaluation.metrics import psnr, ssim  # noqa: E402
from ekdun.physics.kernel_parameterisation import LR_MULTIPLIER, seed_support  # noqa: E402
from ekdun.training import TrainOptions, train  # noqa: E402
from ekdun.training.builder import build_network, network_from_checkpoint  # noqa: E402
from ekdun.training.checkpoint import load_checkpoint  # noqa: E402
from ekdun.training.trainer import CHECKPOINT, _param_groups  # noqa: E402
from psfkit.compare import compare_kernels, measure_modes  # noqa: E402
from psfkit.compare.options import CompareOptions  # noqa: E402
from psfkit.io import read_grid  # noqa: E402
from psfkit.kernelfile import load_kernels, save_kernels  # noqa: E402

PARAMS = ("free", "physical", "flow")
#: Model overrides of each run name (``--params``); ``physical-gain`` is not in the default set.
OVERRIDES = {"free": {"kernel_param": "free"}, "physical": {"kernel_param": "physical"},
             "flow": {"kernel_param": "flow"},
             "physical-gain": {"kernel_param": "physical", "kernel_gain": True}}
SEEDS = ("measured", "one-psf")


def prepare(out: Path) -> tuple[Path, dict[str, Path]]:
    """Dataset, the measured fit and the one-PSF seed (cached in ``out``)."""
    data = make_virtual_bench(out / "dataset", VirtualBenchSpec(), progress=False)
    fit = out / "kernels_fit.npz"
    if not fit.is_file():
        fit_seed_kernels(data, fit)
    one = out / "kernels_one_psf.npz"
    if not one.is_file():
        model = load_kernels(fit)
        kernels = np.repeat(model.kernels[:1], len(model.kernels), axis=0)
        save_kernels(one, replace(model, kernels=kernels))
    return data, {"measured": fit, "one-psf": one}


def test_scores(model: torch.nn.Module, data: Path) -> dict[str, float]:
    """Mean PSNR / SSIM over the held-out test pairs (eval mode, batch 1)."""
    model.eval()
    test = PairsDataset(data / "test")
    p, s = [], []
    with torch.no_grad():
        for i in range(len(test)):
            x, y = test[i]
            out = model(y[None]).clamp(0, 1)
            p.append(float(psnr(out, x[None]).mean()))
            s.append(float(ssim(out, x[None]).mean()))
    return {"psnr": float(np.mean(p)), "ssim": float(np.mean(s))}


def kernel_numbers(run: Path, modes: Any) -> dict[str, Any]:
    """psfkit compare of a run's learned kernels (with its initial kernels)."""
    cmp = compare_kernels(run / "kernels_learned.npz", modes,
                          initial=run / "kernels_initial.npz")
    doc = cmp.to_dict()
    row: dict[str, Any] = {}
    for name in ("v", "h"):
        m = doc["learned"]["metrics"][name]
        row[f"{name}_disp_corr"] = m["vs_measured_kernels"]["corr"]
        row[f"{name}_diff_ncc"] = m["difference_ncc"]
        split = doc["kernel_change"]["learned_vs_initial"][name]
        row[f"{name}_gain"] = split["gain"]
        row[f"{name}_fractions"] = split["fractions"]
    change = doc["kernel_change"]["learned_vs_initial"]["all"]
    row["pedestal_share"] = change["pedestal_share_of_change"]
    row["outside_mass"] = change["outside_mass_fraction"]
    row["base_fractions"] = doc["kernel_change"]["learned_vs_initial"]["base"]["fractions"]
    row["angles_pca"] = doc["learned"]["principal_angles_deg_vs_measured_pca"]
    row["angles_eigen"] = doc["learned"]["principal_angles_deg_vs_measured_eigen"]
    row["compare"] = doc
    return row


def measure_lr(data: Path, seeds: dict[str, Path], batches: int = 6) -> list[dict[str, Any]]:
    """Gradient and parameter scale per group at the measured seed (see module docstring)."""
    train_set = PairsDataset(data / "train")
    lr, scale = 2e-3, 1e-2                     # tiny preset: network lr, kernel_lr_scale
    rows = []
    for param in PARAMS:
        torch.manual_seed(0)
        model = build_network("ekdun", load_kernels(seeds["measured"]), "tiny",
                              {"kernel_param": param})
        groups = _param_groups(model, lr, scale)
        grads: list[list[float]] = [[] for _ in groups]
        per_kernel = []
        for b in range(batches):
            x, y = zip(*(train_set[4 * b + i] for i in range(4)), strict=True)
            model.zero_grad()
            loss = torch.nn.functional.mse_loss(model(torch.stack(y)), torch.stack(x))
            loss.backward()
            if param == "free":
                g = model.physics.kernels.grad.detach()
                inside = seed_support(model.physics.kernels)
                per_kernel.append(torch.cat([
                    g.pow(2).mean(dim=(1, 2, 3)).sqrt(),
                    g[..., inside].pow(2).mean().sqrt()[None],
                    g[..., ~inside].pow(2).mean().sqrt()[None]]))
            for g, group in enumerate(groups):
                flat = torch.cat([p.grad.flatten() for p in group["params"]
                                  if p.grad is not None])
                grads[g].append(float(flat.pow(2).mean().sqrt()))
        for g, group in enumerate(groups):
            values = torch.cat([p.detach().flatten() for p in group["params"]])
            # logits are only defined on the support; fields/gains start at 0 (use 1 px)
            rms = float(values[torch.isfinite(values)].pow(2).mean().sqrt())
            name = "network" if g == 0 else f"kernels ({param})"
            rows.append({"group": name, "param_rms": rms, "grad_rms": float(np.mean(grads[g])),
                         "lr": group["lr"],
                         "relative_step": group["lr"] / max(rms, 1e-12)})
        if per_kernel:
            # how strongly the loss constrains each kernel: RMS gradient per pixel of Kbase,
            # Kv, Kh (the last-2 schedule only uses Kv, Kh in 2 of 10 iterations)
            rows.append({"group": "free pixels: grad RMS per pixel of Kbase, Kv, Kh; inside, "
                                  "outside the caustic support",
                         "per_kernel_grad_rms": torch.stack(per_kernel).mean(0).tolist()})
    return rows


def _f(value: Any, fmt: str = "+.2f") -> str:
    return "n/a" if value is None or value != value else format(value, fmt)


def markdown_table(rows: list[dict[str, Any]]) -> str:
    """The results as the Markdown table of docs/compare.md."""
    head = ("| seed | kernels | PSNR (dB) | SSIM | pedestal share of change | kernel mass outside "
            "support | disp. corr Kv / Kh | diff. NCC Kv / Kh | angles to top-3 PCA (°) |\n"
            "| --- | --- | --- | --- | --- | --- | --- | --- | --- |")
    body = []
    for r in rows:
        angles = ", ".join(f"{a:.1f}" for a in (r.get("angles_pca") or []))
        kernels = r["param"] + (f" (training seed {r['train_seed']})"
                                if r.get("train_seed") else "")
        body.append(f"| {r['seed']} | {kernels} | {r['psnr']:.2f} | {r['ssim']:.4f} | "
                    f"{100 * r['pedestal_share']:.1f} % | {100 * r['outside_mass']:.1f} % | "
                    f"{_f(r['v_disp_corr'])} / {_f(r['h_disp_corr'])} | "
                    f"{_f(r['v_diff_ncc'], '.3f')} / {_f(r['h_diff_ncc'], '.3f')} | {angles} |")
    return "\n".join([head, *body, *_spread_lines(rows)])


def _spread_lines(rows: list[dict[str, Any]]) -> list[str]:
    """Mean ± standard deviation over training seeds, where a set-up ran with several."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault((r["seed"], r["param"]), []).append(r)
    lines = []
    for (seed, param), runs in groups.items():
        if len(runs) < 2:
            continue
        psnrs = np.array([r["psnr"] for r in runs])
        disp = np.array([[r["v_disp_corr"], r["h_disp_corr"]] for r in runs], float)
        ncc = np.array([[r["v_diff_ncc"], r["h_diff_ncc"]] for r in runs], float)
        lines.append(f"\n{seed} / {param}, {len(runs)} training seeds: PSNR "
                     f"{psnrs.mean():.2f} ± {psnrs.std(ddof=1):.2f} dB (range "
                     f"{psnrs.min():.2f}–{psnrs.max():.2f}); disp. corr "
                     f"{disp.mean(0)[0]:+.2f} / {disp.mean(0)[1]:+.2f}; diff. NCC "
                     f"{ncc.mean(0)[0]:.3f} / {ncc.mean(0)[1]:.3f}")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="runs/kparam")
    ap.add_argument("--epochs", type=int, default=15)
    ap.add_argument("--params", default=",".join(PARAMS))
    ap.add_argument("--seeds", default=",".join(SEEDS))
    ap.add_argument("--train-seeds", default="0",
                    help="training seeds (weights, batch order) of every set-up, e.g. 0,1,2: "
                         "the spread says which PSNR differences are resolved")
    ap.add_argument("--measure-lr", action="store_true")
    ap.add_argument("--table", action="store_true", help="print OUT/results.json as Markdown")
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    out = Path(args.out)
    if args.table:
        print(markdown_table(json.loads((out / "results.json").read_text())))
        return 0
    data, seeds = prepare(out)
    if args.measure_lr:
        rows = measure_lr(data, seeds)
        for r in rows:
            if "per_kernel_grad_rms" in r:
                print(r["group"], ", ".join(f"{v:.3g}" for v in r["per_kernel_grad_rms"]))
                continue
            print(f"{r['group']:22s} param RMS {r['param_rms']:.3g}  grad RMS "
                  f"{r['grad_rms']:.3g}  lr {r['lr']:.3g}  lr/RMS {r['relative_step']:.3g}")
        (out / "lr_measurement.json").write_text(json.dumps(rows, indent=1) + "\n")
        return 0
    modes = measure_modes(read_grid(data / "grid"), "paper",
                          load_kernels(seeds["measured"]).convention, (64, 64),
                          CompareOptions())
    results = []
    for seed, param, train_seed in itertools.product(
            args.seeds.split(","), args.params.split(","),
            [int(t) for t in args.train_seeds.split(",")]):
        options = TrainOptions(epochs=args.epochs, progress=False, threads=1,
                               seed=train_seed)
        run = out / "runs" / (f"{seed}-{param}" + (f"-t{train_seed}" if train_seed else ""))
        ckpt = run / CHECKPOINT
        t0 = time.perf_counter()
        if not (ckpt.is_file() and load_checkpoint(ckpt)["metadata"]["epoch"]
                >= args.epochs):
            train(run, "ekdun", seeds[seed], PairsDataset(data / "train"), "tiny",
                  OVERRIDES[param], options, resume=ckpt.is_file())
        model, _ = network_from_checkpoint(ckpt)
        row = {"seed": seed, "param": param, "train_seed": train_seed, "epochs": args.epochs,
               "train_s": round(time.perf_counter() - t0, 1), **test_scores(model, data),
               **kernel_numbers(run, modes)}
        (run / "numbers.json").write_text(json.dumps(row, indent=1, default=float))
        results.append(row)
        print(f"{seed:8s} {param:8s} PSNR {row['psnr']:.2f} SSIM {row['ssim']:.4f} "
              f"pedestal {row['pedestal_share']:.3f} outside {row['outside_mass']:.3f} "
              f"disp {row['v_disp_corr']} / {row['h_disp_corr']} "
              f"ncc {row['v_diff_ncc']:.3f} / {row['h_diff_ncc']:.3f}", flush=True)
    summary = [{k: v for k, v in r.items() if k != "compare"} for r in results]
    # merged with the rows of earlier invocations on the same folder (other set-ups or seeds)
    def key(r: dict[str, Any]) -> tuple:
        return r["seed"], r["param"], r.get("train_seed", 0), r["epochs"]

    path = out / "results.json"
    earlier = json.loads(path.read_text()) if path.is_file() else []
    done = {key(r) for r in summary}
    summary = [r for r in earlier if key(r) not in done] + summary
    path.write_text(json.dumps(summary, indent=1, default=float) + "\n")
    print(markdown_table(summary))
    print(f"LR multipliers: {LR_MULTIPLIER}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
