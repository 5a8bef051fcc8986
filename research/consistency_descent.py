"""How far does training's optimiser get on the measurement-consistency term alone? (issue 24)

Training with ``physics_weight`` λ adds ``L_phys`` (:mod:`research.physics_loss`: the
pairs' relative residual with the best scale per pair) to the reconstruction loss. From one
PSF, 15 epochs of that training leave the difference kernels far from the operator oracle
whatever λ (research/notes/compare-studies.md), while the converged least-squares fit of the
same pairs
(``psfkit fit-pairs --no-nonneg``) reaches it. This benchmark separates the two candidate
causes, the reconstruction loss pulling the kernels away or the optimiser not getting there:
the kernels alone descend ``L_phys`` on the training pairs with nothing else in the loss.

- ``adam``: as training runs it: EK-DUN's kernels built from ``--seed`` (a one-PSF file gives
  ``Kv = Kh = Kbase``), ``--kernel-param``, the kernel parameter group of
  :func:`ekdun.training.trainer._param_groups` (lr × ``kernel_lr_scale`` × the
  parameterisation's multiplier), batches of ``--batch-size`` in a seeded order, ExponentialLR
  (γ = ``--gamma``) per epoch; one row per ``--kernel-lr-scales`` value.
- ``lbfgs``: full-batch L-BFGS (strong Wolfe line search) on the same term: a quasi-Newton
  method, to tell slow first-order steps from a flat objective.

At each of ``--report-at`` (passes over the training pairs: an Adam epoch is one, an L-BFGS
function evaluation one), the row records ``L_phys`` on the training and on the test pairs and
the kernels against the dataset's operator oracle (difference NCC, displacement correlation
and end-point error of ``Kv`` / ``Kh``, principal angles: ``research.compare``). Reference rows
give the same for the seed, the oracle itself and any ``--reference NAME=FILE`` (for example
``fit-pairs --no-nonneg`` of ``DATA/train``, the minimiser of the same term).

Writes ``OUT/results.json`` and prints a Markdown table.

    python -m research.consistency_descent --data DATA --seed ONE_PSF.npz --out OUT \
        --optimisers adam,lbfgs --kernel-lr-scales 0.01,0.1 --report-at 1,5,15,60,120 \
        --reference pairs-free=PAIRS_FREE.npz

Measured (128², 384 / 24 pairs, P = 10⁶; one-PSF seed; CPU, 1 thread; 2026-11-26) in
research/notes/compare-studies.md, "Is it the loss or the optimiser?".
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import torch

from ekdun.data.pairs import PairsDataset
from ekdun.nets.export import export_kernels
from ekdun.training.trainer import _param_groups
from psfkit.errors import PsfkitError
from psfkit.forward.kernelfile import load_kernels
from psfkit.io.jsonable import jsonable, write_json
from research.kernel_models import KERNEL_PARAMETERISATIONS, build_network
from research.kernel_parameterisations import vs_oracle
from research.oracles import oracle_file
from research.physics_loss import measurement_consistency

OPTIMISERS = ("adam", "lbfgs")


class BenchError(Exception):
    """A bad argument or input: one line, exit 2."""


def stacked(split: Path) -> tuple[torch.Tensor, torch.Tensor]:
    """All pairs of a split as ``(N, C, H, W)`` scenes and measurements."""
    pairs = PairsDataset(split)
    xs, ys = zip(*(pairs[i] for i in range(len(pairs))), strict=True)
    return torch.stack(xs), torch.stack(ys)


def full_batch(model: torch.nn.Module, x: torch.Tensor, y: torch.Tensor,
               chunk: int = 32) -> Iterator[torch.Tensor]:
    """``L_phys`` of each chunk of the pairs, weighted by its share of them: they sum to the
    mean over all pairs (chunks keep the FFT buffers of a 384-pair pass small)."""
    op = model.forward_model()
    for b in range(0, len(x), chunk):
        xb, yb = x[b:b + chunk], y[b:b + chunk]
        yield measurement_consistency(op.A(xb), yb) * (len(xb) / len(x))


@torch.no_grad()
def consistency(model: torch.nn.Module, x: torch.Tensor, y: torch.Tensor) -> float:
    """``L_phys`` of the network's forward model over all pairs (mean over pairs)."""
    return sum(float(part) for part in full_batch(model, x, y))


def network(kernels: Any, param: str) -> torch.nn.Module:
    """EK-DUN (tiny preset: only its physics is used) built as training builds it."""
    return build_network("ekdun", kernels, "tiny", {"kernel_param": param})


def score(model: torch.nn.Module, data: dict[str, tuple[torch.Tensor, torch.Tensor]],
          oracle: Any) -> dict[str, Any]:
    """``L_phys`` on both splits and the kernels against the oracle."""
    return {"train_consistency": consistency(model, *data["train"]),
            "test_consistency": consistency(model, *data["test"]),
            # a one-PSF model has no difference kernels: its NCC is undefined (null, not NaN)
            **jsonable(vs_oracle(export_kernels(model), oracle))}


def kernel_parameters(model: torch.nn.Module, lr: float, scale: float) -> dict[str, Any]:
    """The kernel group of training's optimiser (its parameters and learning rate)."""
    return next(g for g in _param_groups(model, lr, scale) if g.get("name") == "kernels")


def descend_adam(seed: Any, args: argparse.Namespace, scale: float,
                 data: dict[str, tuple[torch.Tensor, torch.Tensor]], oracle: Any
                 ) -> dict[str, Any]:
    """Training's Adam on the kernels alone: its settings and one row per ``--report-at``
    epoch (``seconds``: wall time since the start, scoring included)."""
    torch.manual_seed(args.train_seed)
    model = network(seed, args.kernel_param)
    group = kernel_parameters(model, args.lr, scale)
    opt = torch.optim.Adam(group["params"], lr=group["lr"])
    schedule = torch.optim.lr_scheduler.ExponentialLR(opt, args.gamma)
    x, y = data["train"]
    order = torch.Generator().manual_seed(args.train_seed)
    rows, t0 = [], time.perf_counter()
    for epoch in range(1, max(args.report_at) + 1):
        perm = torch.randperm(len(x), generator=order)
        for b in range(0, len(x) - args.batch_size + 1, args.batch_size):
            idx = perm[b:b + args.batch_size]
            opt.zero_grad()
            measurement_consistency(model.forward_model().A(x[idx]), y[idx]).backward()
            opt.step()
        schedule.step()
        if epoch in args.report_at:
            rows.append({"passes": epoch, "seconds": round(time.perf_counter() - t0, 1),
                         **score(model, data, oracle)})
            report(f"adam ×{scale:g}", rows[-1])
    return {"optimiser": "adam", "kernel_lr_scale": scale, "lr": args.lr,
            "kernel_lr": group["lr"], "batch_size": args.batch_size, "gamma": args.gamma,
            "trajectory": rows}


def descend_lbfgs(seed: Any, args: argparse.Namespace,
                  data: dict[str, tuple[torch.Tensor, torch.Tensor]], oracle: Any
                  ) -> list[dict[str, Any]]:
    """Full-batch L-BFGS on the kernels alone; a row when the passes reach a report point."""
    model = network(seed, args.kernel_param)
    params = kernel_parameters(model, args.lr, 1.0)["params"]
    # 10 iterations per call (max_iter=1 leaves the line search one evaluation, too few to
    # move at all); no early stop on a small gradient or change: the question is where the
    # passes asked for lead
    opt = torch.optim.LBFGS(params, lr=1.0, max_iter=10, history_size=20,
                            tolerance_grad=0.0, tolerance_change=0.0,
                            line_search_fn="strong_wolfe")
    x, y = data["train"]
    passes = [0]

    def closure() -> torch.Tensor:
        # one pass over the training pairs, the gradient accumulated chunk by chunk
        passes[0] += 1
        opt.zero_grad()
        total = torch.zeros(())
        for part in full_batch(model, x, y):
            part.backward(retain_graph=True)
            total += part.detach()
        return total

    rows, t0, todo = [], time.perf_counter(), sorted(args.report_at)
    while todo:
        opt.step(closure)
        if passes[0] >= todo[0]:
            # a step with a line search takes several passes: one row for the points it crossed
            todo = [t for t in todo if t > passes[0]]
            rows.append({"passes": passes[0], "seconds": round(time.perf_counter() - t0, 1),
                         **score(model, data, oracle)})
            report("lbfgs", rows[-1])
    return rows


def report(label: str, row: dict[str, Any]) -> None:
    print(f"{label}: {row['passes']} passes, L_phys train {row['train_consistency']:.4e} "
          f"test {row['test_consistency']:.4e}, NCC {fmt(row['oracle_v_diff_ncc'])} / "
          f"{fmt(row['oracle_h_diff_ncc'])} ({row['seconds']} s)", file=sys.stderr, flush=True)


def fmt(value: float | None, digits: int = 3) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def table(doc: dict[str, Any]) -> str:
    """Markdown: reference rows, then every report point of every descent."""
    lines = ["| kernels | passes | L_phys train | L_phys test | vs oracle: diff. NCC Kv / Kh "
             "| disp. corr Kv / Kh | principal angles (°) |",
             "| --- | --- | --- | --- | --- | --- | --- |"]

    def line(name: str, passes: str, r: dict[str, Any]) -> str:
        angles = ", ".join(f"{a:.1f}" for a in r["oracle_angles"])
        return (f"| {name} | {passes} | {r['train_consistency']:.4e} | "
                f"{r['test_consistency']:.4e} | {fmt(r['oracle_v_diff_ncc'])} / "
                f"{fmt(r['oracle_h_diff_ncc'])} | {fmt(r['oracle_v_disp_corr'], 2)} / "
                f"{fmt(r['oracle_h_disp_corr'], 2)} | {angles} |")

    lines += [line(r["reference"], "", r) for r in doc["references"]]
    for run in doc["runs"]:
        name = run["optimiser"] + (f" (kernel lr × {run['kernel_lr_scale']:g})"
                                   if run["optimiser"] == "adam" else "")
        lines += [line(name, str(r["passes"]), r) for r in run["trajectory"]]
    return "\n".join(lines)


def parse(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", type=Path, required=True,
                   help="virtual-bench dataset with an operator oracle (ekdun make-dataset)")
    p.add_argument("--seed", type=Path, required=True, help="kernel file the kernels start at")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--optimisers", default="adam,lbfgs")
    p.add_argument("--kernel-lr-scales", default="0.01",
                   help="Adam: kernel lr = --lr × this × the parameterisation's multiplier")
    p.add_argument("--lr", type=float, default=2e-3, help="the network lr (tiny preset's)")
    p.add_argument("--gamma", type=float, default=0.95)
    p.add_argument("--batch-size", type=int, default=4)
    p.add_argument("--kernel-param", default="free", choices=KERNEL_PARAMETERISATIONS)
    p.add_argument("--report-at", default="1,5,15",
                   help="passes over the training pairs at which to score the kernels")
    p.add_argument("--reference", action="append", default=[], metavar="NAME=FILE")
    p.add_argument("--train-seed", type=int, default=0)
    p.add_argument("--threads", type=int, default=1)
    args = p.parse_args(argv)
    try:
        args.optimisers = [o for o in args.optimisers.split(",") if o]
        args.kernel_lr_scales = [float(s) for s in args.kernel_lr_scales.split(",") if s]
        args.report_at = sorted({int(s) for s in args.report_at.split(",") if s})
        args.reference = [tuple(r.split("=", 1)) for r in args.reference]
    except ValueError as exc:
        raise BenchError(f"bad list argument: {exc}") from None
    if bad := [o for o in args.optimisers if o not in OPTIMISERS]:
        raise BenchError(f"--optimisers: unknown {', '.join(bad)} (choose from "
                         f"{', '.join(OPTIMISERS)})")
    if not args.report_at or args.report_at[0] < 1:
        raise BenchError("--report-at: passes must be integers >= 1")
    if any(len(r) != 2 or not r[0] for r in args.reference):
        raise BenchError("--reference takes NAME=FILE")
    if args.batch_size < 1 or any(s <= 0 for s in args.kernel_lr_scales):
        raise BenchError("--batch-size and --kernel-lr-scales must be positive")
    return args


def run(args: argparse.Namespace) -> dict[str, Any]:
    seed = load_kernels(args.seed)
    oracle_path = oracle_file(args.data, seed.convention)
    if oracle_path is None:
        raise BenchError(f"{args.data}: no operator oracle of the {seed.convention} side "
                         f"(python -m research.oracle {args.data} --write-dataset writes it)")
    for split in ("train", "test"):
        if not (args.data / split).is_dir():
            raise BenchError(f"{args.data}: no {split}/ split (not a virtual-bench dataset)")
    oracle = load_kernels(oracle_path)
    data = {s: stacked(args.data / s) for s in ("train", "test")}
    references = []
    for name, kernels in [("seed", seed), ("the oracle itself", oracle),
                          *((n, load_kernels(f)) for n, f in args.reference)]:
        references.append({"reference": name, **score(network(kernels, "free"), data, oracle)})
    runs = []
    for opt in args.optimisers:
        if opt == "adam":
            runs += [descend_adam(seed, args, scale, data, oracle)
                     for scale in args.kernel_lr_scales]
        else:
            runs.append({"optimiser": "lbfgs",
                         "trajectory": descend_lbfgs(seed, args, data, oracle)})
    return {"data": str(args.data), "seed": str(args.seed), "oracle": str(oracle_path),
            "kernel_param": args.kernel_param, "train_seed": args.train_seed,
            "references": references, "runs": runs}


def main(argv: list[str] | None = None) -> int:
    try:
        args = parse(argv)
        torch.set_num_threads(args.threads)
        doc = run(args)
    except (BenchError, PsfkitError, OSError) as exc:
        print(f"bench_consistency_descent: error: {exc}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    write_json(args.out / "results.json", doc)
    print(table(doc))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
