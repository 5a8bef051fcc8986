"""Are the baselines trained fairly, and do they work? (issue 45)

    python -m research.baseline_checks sweep OUT [--sensor 64 64] [--n-train 128] [--epochs 8]
        [--seeds 0,1] [--lrs 5e-4,1e-3,2e-3,4e-3,8e-3,1.6e-2] [--networks updn,le-admm-u,ekdun]
    python -m research.baseline_checks field-free OUT [--sensor 64 64] [--n-train 128]
        [--epochs 15] [--seeds 0,1,2]
    python -m research.baseline_checks overfit OUT [--sensor 32 32] [--pairs 8] [--steps 1500]
        [--networks ekdun,le-admm-u,updn] [--field-free]

``sweep``: each network trained at each learning rate on the varying virtual bench, same
budget (pairs, epochs, batch, decay) for all; held-out PSNR per rate, the best rate, and how far
the preset's recipe (:meth:`ekdun.nets.configs.Preset.training_for`) lies from the best.

``field-free``: a bench camera whose PSF does *not* vary (every field point sees the bench's
noise-free centre PSF; the bench's scenes and noise), every network seeded with that PSF. There
EK-DUN *base only* and UPDN are both ten unrolled iterations with learned priors and the right
physics, so at equal budget they should reach the same quality; a large gap means a broken
baseline (or a broken EK-DUN). Le-ADMM-U learns only ADMM's scalars inside its iterations and a
U-Net after them; its distance from the two is its architecture's.

``overfit``: each network fitted to a few pairs, full batch, Adam with a cosine-annealed rate:
a network that cannot drive its training loss far below the scenes' variance is broken. For a
network that ends in a U-Net (Le-ADMM-U, UPDN) it also measures what that U-Net is handed
(the part of the scenes a per-pixel affine map of its input leaves unexplained) and where the
same U-Net gets alone (:func:`denoiser_floor`): from noise (memorising only), from the
network's own input held fixed (below the network's floor: the joint fit holds it), and from
the scenes plus noise (what it reaches when handed them).

Each writes ``OUT/<check>.json`` and ``OUT/<check>.md``; trainings are resumable under
``OUT/runs``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ekdun.data.bench_spec import make_scenes, node_psfs
from ekdun.data.dense_model import DenseShiftVariantModel
from ekdun.data.pairs import PairsDataset
from ekdun.data.virtual_bench import VirtualBenchSpec, make_virtual_bench, simulate_measurements
from ekdun.errors import ConfigurationError
from ekdun.evaluation import LPIPSMetric
from ekdun.evaluation.tables import markdown_table, seed_summary
from ekdun.nets.builder import build_network, seed_kernel_model
from ekdun.nets.configs import get_preset
from ekdun.nets.unet import UNet
from ekdun.training.trainer import TrainOptions, make_optimizer
from psfkit.cli import run_cli
from psfkit.cli.main import add_debug_option
from psfkit.cli.parser import OneLineArgumentParser
from psfkit.io.atomic import atomic_directory, atomic_file
from psfkit.io.images import write_image
from research.benchmark_tiny import comma_list, fit_seed_kernels, int_list, train_and_evaluate

NETWORKS = {"ekdun": ("ekdun-last-2", "ekdun", {"schedule": "last-2"}),
            "ekdun-base": ("ekdun-base", "ekdun", {"schedule": "base"}),
            "le-admm-u": ("le-admm-u", "le-admm-u", {}),
            "updn": ("updn", "updn", {})}
LRS = (5e-4, 1e-3, 2e-3, 4e-3, 8e-3, 1.6e-2)
#: Issue 45's targets: a recipe within this of its own sweep's best; UPDN within this of
#: EK-DUN base only on the field-free bench.
RECIPE_MARGIN_DB = 0.3
FIELD_FREE_MARGIN_DB = 1.0


def write_study(out: Path, name: str, doc: dict[str, Any], text: str) -> None:
    """A study's results: ``OUT/NAME.json`` (``doc``) and ``OUT/NAME.md`` (``text``), each
    written atomically."""
    out.mkdir(parents=True, exist_ok=True)
    with atomic_file(out / f"{name}.json") as tmp:
        tmp.write_text(json.dumps(doc, indent=1, default=float) + "\n", encoding="utf-8")
    with atomic_file(out / f"{name}.md") as tmp:
        tmp.write_text(text, encoding="utf-8")


def bench_pairs(out: Path, spec: VirtualBenchSpec, progress: bool
                ) -> tuple[Path, PairsDataset, PairsDataset]:
    """The varying bench of ``spec`` in ``OUT/dataset`` and its grid's seed kernels (both
    reused when there): the kernel file, the training and the test pairs."""
    data = make_virtual_bench(out / "dataset", spec, progress=progress)
    kernels = out / "kernels_fit.npz"
    if not kernels.is_file():
        fit_seed_kernels(data, kernels)
    return kernels, PairsDataset(data / "train"), PairsDataset(data / "test")


# --- learning-rate sweep -------------------------------------------------------------------

def lr_sweep(out: str | os.PathLike, spec: VirtualBenchSpec, networks: Sequence[str],
             lrs: Sequence[float], seeds: Sequence[int], options: TrainOptions,
             preset: str = "tiny", log: Any = print) -> dict[str, Any]:
    """Train every network at every rate and seed; held-out PSNR and the recipe's distance
    from the best rate (``recipe_gap_db``: recipe minus best, mean over seeds)."""
    out = Path(out)
    kernels, train_set, test_set = bench_pairs(out, spec, options.progress)
    lpips = LPIPSMetric(None)
    rows = []
    for name in networks:
        run = NETWORKS[name]
        for lr in lrs:
            for seed in seeds:
                run_dir = out / "runs" / f"{name}-lr{lr:g}-s{seed}"
                row = train_and_evaluate(run, seed, kernels, train_set, test_set,
                                          preset, replace(options, lr=lr), lpips, run_dir)
                rows.append({"network": name, "lr": lr, "seed": seed, "psnr": row["psnr"],
                             "ssim": row["ssim"], "train_seconds": row["train_seconds"]})
                log(f"{name} lr {lr:g} seed {seed}: {row['psnr']:.2f} dB")
    summary = {name: _sweep_summary([r for r in rows if r["network"] == name],
                                    get_preset(preset).training_for(NETWORKS[name][1]).lr)
               for name in networks}
    doc = {"spec": spec.to_dict(), "preset": preset, "epochs": options.epochs,
           "seeds": list(seeds), "rows": rows, "summary": summary}
    write_study(out, "sweep", doc, _sweep_markdown(doc, lrs))
    return doc


def _sweep_summary(rows: list[dict[str, Any]], recipe_lr: float) -> dict[str, Any]:
    by_lr: dict[float, list[float]] = {}
    for r in rows:
        by_lr.setdefault(r["lr"], []).append(r["psnr"])
    means = {lr: statistics.fmean(v) for lr, v in by_lr.items()}
    best = max(means, key=means.__getitem__)
    recipe = next((lr for lr in means if np.isclose(lr, recipe_lr)), None)
    gap = None if recipe is None else means[recipe] - means[best]
    return {"mean_psnr_by_lr": {f"{lr:g}": m for lr, m in means.items()}, "best_lr": best,
            "best_psnr": means[best], "recipe_lr": recipe_lr, "recipe_gap_db": gap,
            "recipe_within_margin": None if gap is None else gap >= -RECIPE_MARGIN_DB}


def _sweep_markdown(doc: dict[str, Any], lrs: Sequence[float]) -> str:
    names = list(doc["summary"])
    cells = {(r["network"], r["lr"]): [] for r in doc["rows"]}
    for r in doc["rows"]:
        cells[(r["network"], r["lr"])].append(f"{r['psnr']:.2f}")
    lines = ["| lr | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    lines += [f"| {lr:g} | " + " | ".join(" / ".join(cells.get((n, lr), ["-"])) for n in names)
              + " |" for lr in lrs]
    lines += ["", "| network | best lr | recipe lr | recipe − best (dB) |", "|---|---|---|---|"]
    for n, s in doc["summary"].items():
        gap = "n/a" if s["recipe_gap_db"] is None else f"{s['recipe_gap_db']:+.2f}"
        lines.append(f"| {n} | {s['best_lr']:g} | {s['recipe_lr']:g} | {gap} |")
    spec = doc["spec"]
    return (f"### Learning-rate sweep (held-out PSNR, dB; seeds {doc['seeds']})\n\n"
            + "\n".join(lines) + f"\n\nVirtual bench {spec['sensor_shape']}, "
            f"{spec['n_train']} / {spec['n_test']} pairs, preset {doc['preset']}, "
            f"{doc['epochs']} epochs.\n")


# --- field-free bench -----------------------------------------------------------------------

def centre_psf(spec: VirtualBenchSpec) -> np.ndarray:
    """The bench's noise-free PSF at the centre of the field, ``(C, H', W')`` float32 (the
    dense model's units: measurement per unit scene radiance)."""
    kernels, _shifts, _rows, _cols = node_psfs(spec)
    return kernels[kernels.shape[0] // 2, kernels.shape[1] // 2].astype(np.float32)


def make_field_free_pairs(root: str | os.PathLike, spec: VirtualBenchSpec,
                          progress: bool = False) -> Path:
    """The bench's scenes measured through one PSF everywhere (its centre PSF, the bench's
    noise), as a pairs folder ``root/{train,test}/{scene,measurement}``; kept when there."""
    root = Path(root)
    if (root / "centre_psf.npy").is_file():
        return root
    psf = centre_psf(spec)
    h, w = spec.sensor_shape
    model = DenseShiftVariantModel(psf[None, None], np.array([h // 2]), np.array([w // 2]),
                                   spec.sensor_shape, spec.convention)
    with atomic_directory(root, overwrite=True) as tmp:
        for split_id, split in enumerate(("train", "test")):
            scenes = make_scenes(spec, split, progress=progress)
            measured = simulate_measurements(model, scenes, spec, split_id, progress=progress)
            for sub, arrays in (("scene", scenes), ("measurement", measured)):
                (tmp / split / sub).mkdir(parents=True)
                for i, image in enumerate(arrays):
                    write_image(tmp / split / sub / f"{split}{i:04d}.npy",
                                image.astype(np.float32))
        np.save(tmp / "centre_psf.npy", psf)
    return root


def field_free_check(out: str | os.PathLike, spec: VirtualBenchSpec, seeds: Sequence[int],
                     options: TrainOptions, preset: str = "tiny",
                     networks: Sequence[str] = ("ekdun-base", "updn", "le-admm-u"),
                     log: Any = print) -> dict[str, Any]:
    """Train ``networks`` on the field-free bench at equal budget; PSNR over seeds and each
    one's difference to EK-DUN base only, paired by seed."""
    out = Path(out)
    data = make_field_free_pairs(out / "field_free", spec, options.progress)
    psf = np.load(data / "centre_psf.npy")
    train_set, test_set = PairsDataset(data / "train"), PairsDataset(data / "test")
    lpips = LPIPSMetric(None)
    rows = []
    for seed in seeds:
        for name in networks:
            row = train_and_evaluate(NETWORKS[name], seed, psf, train_set, test_set,
                                      preset, options, lpips,
                                      out / "runs" / f"field-free-{name}-s{seed}")
            rows.append(row)
            log(f"field-free {name} seed {seed}: {row['psnr']:.2f} dB")
    summary = seed_summary(rows, reference="EK-DUN (base)")
    updn = next((e for e in summary if e["label"] == "UPDN"), None)
    gap = None if updn is None else updn["delta_mean"]
    doc = {"spec": spec.to_dict(), "preset": preset, "seeds": list(seeds),
           "rows": [{k: r[k] for k in ("label", "seed", "psnr", "ssim", "lr", "epochs",
                                       "train_seconds", "parameters")} for r in rows],
           "summary": summary, "updn_minus_base_db": gap,
           "updn_within_margin": None if gap is None else abs(gap) <= FIELD_FREE_MARGIN_DB}
    columns = [("label", "Method", -1), ("psnr_text", "PSNR (dB), mean ± sd", -1),
               ("ssim_mean", "SSIM", 4),
               ("delta_text", "Δ PSNR to EK-DUN base only, paired by seed (dB)", -1)]
    text = (f"### Field-free bench (one PSF everywhere), seeds {list(seeds)}\n\n"
            f"{markdown_table(summary, columns)}\n\nVirtual bench {spec.sensor_shape}, "
            f"{spec.n_train} / {spec.n_test} pairs, preset {preset} (each network's recipe), "
            f"every network seeded with the noise-free centre PSF.\n")
    write_study(out, "field_free", doc, text)
    return doc


# --- overfitting a few pairs ----------------------------------------------------------------

def overfit_check(out: str | os.PathLike, spec: VirtualBenchSpec, steps: int,
                  lr: float | None = None,
                  networks: Sequence[str] = ("ekdun", "le-admm-u", "updn"),
                  preset: str = "tiny", seed: int = 0, field_free: bool = False,
                  log: Any = print) -> dict[str, Any]:
    """Fit each network to the bench's ``spec.n_train`` training pairs (full batch, ``steps``
    steps of training's own optimiser: Adam with the kernels' group, from ``lr`` or the
    network's recipe, annealed to 0 along a cosine); the training MSE along the way, against
    the scenes' variance (the MSE of predicting their mean). With ``field_free`` the pairs are
    the field-free bench's (one PSF everywhere, :func:`make_field_free_pairs`), every network
    seeded with that PSF: what a single-PSF network's floor owes to the field's variation."""
    out = Path(out)
    if field_free:
        data = make_field_free_pairs(out / "field_free", spec)
        kernels, train_set = np.load(data / "centre_psf.npy"), PairsDataset(data / "train")
    else:
        kernels, train_set, _test = bench_pairs(out, spec, progress=False)
    x = torch.stack([train_set[i][0] for i in range(len(train_set))])
    y = torch.stack([train_set[i][1] for i in range(len(train_set))])
    variance = float(x.var())
    results = {}
    for name in networks:
        _run, model_name, overrides = NETWORKS[name]
        torch.manual_seed(seed)
        model = build_network(model_name, seed_kernel_model(kernels), preset, overrides)
        cfg = TrainOptions(lr=lr).resolve(preset, model_name)
        started = time.perf_counter()
        curve = _fit_pairs(model, x, y, steps, make_optimizer(model, cfg, torch.device("cpu")))
        results[name] = {"lr": cfg.lr, "mse": curve, "final_mse": curve[-1][1],
                         "final_over_variance": curve[-1][1] / variance,
                         "seconds": time.perf_counter() - started}
        log(f"overfit {name}: MSE {curve[0][1]:.4g} -> {curve[-1][1]:.4g} "
            f"({curve[-1][1] / variance:.1%} of the scenes' variance)")
        if hasattr(model, "denoiser"):
            results[name]["denoiser"] = denoiser_floor(model, x, y, steps, cfg.lr, seed)
            floor = results[name]["denoiser"]
            log(f"  its U-Net's input leaves {floor['unexplained']:.1%} unexplained; the "
                f"U-Net alone from noise {floor['noise_floor']:.1%}, from that input "
                f"{floor['own_floor']:.1%}, from the scenes plus "
                f"noise ({floor['informed_unexplained']:.1%} unexplained) "
                f"{floor['informed_floor']:.1%}")
    doc = {"spec": spec.to_dict(), "steps": steps, "variance": variance,
           "field_free": field_free, "networks": results}
    lines = ["| network | lr | MSE at step 0 | final MSE | final / variance | U-Net's input: "
             "unexplained | U-Net alone: from noise | from that input | from the scenes + "
             "noise | time (s) |", "|---|---|---|---|---|---|---|---|---|---|"]
    lines += [f"| {n} | {r['lr']:g} | {r['mse'][0][1]:.4g} | {r['final_mse']:.4g} | "
              f"{r['final_over_variance']:.1%} | {_floor_cells(r)} | {r['seconds']:.0f} |"
              for n, r in results.items()]
    write_study(out, "overfit", doc, f"### Overfitting {spec.n_train} "
                f"{'field-free ' if field_free else ''}pairs ({steps} full-batch steps, "
                f"scenes' variance {variance:.4f})\n\n" + "\n".join(lines) + "\n")
    return doc


def _floor_cells(result: dict[str, Any]) -> str:
    floor = result.get("denoiser")
    return "– | – | – | –" if floor is None else (
        f"{floor['unexplained']:.1%} | {floor['noise_floor']:.1%} | {floor['own_floor']:.1%} | "
        f"{floor['informed_floor']:.1%} ({floor['informed_unexplained']:.1%} unexplained)")


def denoiser_floor(model: torch.nn.Module, x: torch.Tensor, y: torch.Tensor, steps: int,
                   lr: float, seed: int = 0) -> dict[str, float]:
    """What a network that ends in a U-Net (``model.denoiser``: Le-ADMM-U, UPDN) can owe to
    that U-Net, once the network has been fitted to the pairs ``(x, y)``:

    * ``unexplained``: the part of the scenes' variance that the best per-pixel affine map of
      the U-Net's input (least squares per colour over all its channels) leaves, i.e. how
      little of the scenes the physics stage hands the U-Net;
    * ``noise_floor``: the same U-Net (fresh, same seed), fitted alone in the same way
      (``steps``, ``lr``, cosine) from uniform noise to the scenes, over their variance: what
      it reaches by memorising alone. A network whose own floor sits at this one gets nothing
      from its physics that the U-Net can use;
    * ``own_floor``: the same from the network's own fitted input, held fixed: below the
      network's floor, the joint fit (not what the U-Net is handed) holds the network;
    * ``informed_floor`` (and ``informed_unexplained``): the same from an input that does hold
      the scenes (the scenes plus white noise of half their standard deviation, each colour
      repeated over the U-Net's input channels of that colour, so that every network is
      handed the same): what the U-Net reaches when it is handed the scenes.
    """
    captured: list[torch.Tensor] = []
    hook = model.denoiser.register_forward_pre_hook(lambda _m, args: captured.append(args[0]))
    try:
        with torch.no_grad():
            model(y)
    finally:
        hook.remove()
    features = captured[0].detach()
    variance = float(x.var())
    generator = torch.Generator().manual_seed(seed)
    noise = torch.rand(features.shape, generator=generator, dtype=features.dtype)
    colours = torch.arange(features.shape[1]) % x.shape[1]
    informed = (x + 0.5 * variance ** 0.5 * torch.randn(
        x.shape, generator=generator, dtype=features.dtype))[:, colours]
    config = model.config.denoiser
    floors = {}
    for name, inputs in (("noise_floor", noise), ("own_floor", features),
                         ("informed_floor", informed)):
        torch.manual_seed(seed)                    # every U-Net starts from the same weights
        unet = UNet(features.shape[1], x.shape[1], config.widths, config.residual,
                    config.zero_init_output)
        curve = _fit_pairs(lambda _y, unet=unet, inputs=inputs: unet(inputs), x, y, steps,
                           torch.optim.Adam(unet.parameters(), lr=lr))
        floors[name] = curve[-1][1] / variance
    return {"unexplained": _affine_unexplained(features, x) / variance,
            "informed_unexplained": _affine_unexplained(informed, x) / variance, **floors}


def _affine_unexplained(features: torch.Tensor, x: torch.Tensor) -> float:
    """Mean squared residual of the least-squares per-pixel affine map from ``features``
    ``(B, F, H, W)`` to ``x`` ``(B, C, H, W)`` (one map per colour, pooled over pixels)."""
    design = features.double().permute(0, 2, 3, 1).reshape(-1, features.shape[1])
    design = torch.cat([design, torch.ones(len(design), 1, dtype=design.dtype)], dim=1)
    target = x.double().permute(0, 2, 3, 1).reshape(-1, x.shape[1])
    solution = torch.linalg.lstsq(design, target).solution
    return float((design @ solution - target).pow(2).mean())


def _fit_pairs(model: Callable[[torch.Tensor], torch.Tensor], x: torch.Tensor,
               y: torch.Tensor, steps: int, optimizer: torch.optim.Optimizer
               ) -> list[tuple[int, float]]:
    """Full-batch steps, the learning rate annealed to 0 along a cosine (at a constant rate
    Adam hovers at a loss floor set by the rate, not by the network's capacity); ``(step,
    MSE)`` at 0, every tenth of the run and the end."""
    marks = set(np.linspace(0, steps, 11).astype(int).tolist())
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(1, steps))
    curve = []
    for step in range(steps + 1):
        loss = torch.nn.functional.mse_loss(model(y), x)
        if step in marks:
            curve.append((step, float(loss.detach())))
        if step == steps:
            break
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()
    return curve


# --- command line ---------------------------------------------------------------------------

def name_list(known: Sequence[str], what: str) -> Callable[[str], list[str]]:
    """An argparse type: a comma-separated list of names out of ``known``."""
    def parse(text: str) -> list[str]:
        names = [n.strip() for n in text.split(",") if n.strip()]
        if not names or any(n not in known for n in names):
            raise argparse.ArgumentTypeError(f"{what} are {', '.join(known)}; got {text!r}")
        return names
    return parse


def add_bench_arguments(q: argparse.ArgumentParser, size: int, n_train: int,
                        pairs_flag: str = "--n-train") -> None:
    """The output folder and the virtual bench's size, pairs, threads and quiet flags."""
    q.add_argument("out", help="output folder (resumable)")
    q.add_argument("--sensor", type=int, nargs=2, default=(size, size), metavar=("H", "W"))
    q.add_argument(pairs_flag, dest="n_train", type=int, default=n_train)
    q.add_argument("--n-test", type=int, default=16)
    q.add_argument("--threads", type=int, default=1)
    q.add_argument("--quiet", action="store_true", help="no progress bars")


def bench_setup(args: argparse.Namespace, *counts: int,
                rule: str = "--sensor must be >= 16 16 and the counts >= 1"
                ) -> tuple[VirtualBenchSpec, Callable[[str], None]]:
    """The bench of :func:`add_bench_arguments`' flags (checked, ``rule`` otherwise) and the
    log (stderr unless ``--quiet``); sets the threads."""
    if min(args.sensor) < 16 or min(args.n_train, args.n_test, args.threads, *counts) < 1:
        raise ConfigurationError(rule)
    torch.set_num_threads(args.threads)
    spec = VirtualBenchSpec(sensor_shape=tuple(args.sensor), n_train=args.n_train,
                            n_test=args.n_test)
    log = (lambda text: None) if args.quiet else (lambda text: print(text, file=sys.stderr))
    return spec, log


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m research.baseline_checks``."""
    p = OneLineArgumentParser(prog="python -m research.baseline_checks",
                              description="Learning-rate sweep, field-free bench and "
                                          "overfitting checks of the baselines (issue 45).")
    add_debug_option(p)
    sub = p.add_subparsers(dest="check", required=True, metavar="CHECK")
    for name, epochs, n_train, size in (("sweep", 8, 128, 64), ("field-free", 15, 128, 64),
                                        ("overfit", None, 8, 32)):
        q = sub.add_parser(name, help=f"the {name} check")
        add_bench_arguments(q, size, n_train, "--n-train" if name != "overfit" else "--pairs")
        if epochs:
            q.add_argument("--epochs", type=int, default=epochs)
            q.add_argument("--seeds", type=int_list, default=[0, 1] if name == "sweep"
                           else [0, 1, 2])
        q.set_defaults(func=_run)
    sweep = sub.choices["sweep"]
    sweep.add_argument("--lrs", type=comma_list(float, "positive numbers", lambda v: v > 0),
                       default=list(LRS))
    sweep.add_argument("--networks", type=name_list(list(NETWORKS), "networks"),
                       default=["updn", "le-admm-u", "ekdun"])
    sub.choices["overfit"].add_argument("--steps", type=int, default=1500)
    sub.choices["overfit"].add_argument("--lr", type=float, default=None,
                                        help="default: each network's recipe")
    sub.choices["overfit"].add_argument("--networks", type=name_list(list(NETWORKS),
                                                                     "networks"),
                                        default=["ekdun", "le-admm-u", "updn"])
    sub.choices["overfit"].add_argument("--field-free", action="store_true",
                                        help="the field-free bench's pairs (one PSF)")
    return p


def _run(args: argparse.Namespace) -> int:
    rule = "--sensor must be >= 16 16, the counts >= 1 and --lr > 0"
    if (getattr(args, "lr", None) or 1) <= 0:
        raise ConfigurationError(rule)
    spec, log = bench_setup(args, getattr(args, "epochs", 1), getattr(args, "steps", 1),
                            rule=rule)
    if args.check == "overfit":
        overfit_check(args.out, spec, args.steps, args.lr, args.networks,
                      field_free=args.field_free, log=log)
        return 0
    options = TrainOptions(epochs=args.epochs, progress=not args.quiet, threads=args.threads)
    if args.check == "sweep":
        lr_sweep(args.out, spec, args.networks, args.lrs, args.seeds, options, log=log)
    else:
        field_free_check(args.out, spec, args.seeds, options, log=log)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``python -m research.baseline_checks`` with ``argv``; returns the exit code."""
    return run_cli("research.baseline_checks", build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
