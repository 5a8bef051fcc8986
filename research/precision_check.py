"""What autocast costs a trained network, pair by pair (issue 45: fp16 against fp32 within
0.05 dB for every network, trained).

    python -m research.precision_check OUT CHECKPOINT [CHECKPOINT ...] --pairs TEST
        [--amp fp16,bf16] [--device auto] [--threads 1]

Each checkpoint's network reconstructs every test pair in float32 and under each ``--amp``
(:func:`ekdun.device.autocast`, the physics in float32 as in ``ekdun reconstruct``); per pair
the PSNR to the scene in both, their difference, and the PSNR of the autocast output against
the float32 one. ``OUT/precision.json`` and ``OUT/precision.md`` hold the rows. On the CPU
this measures the numbers of half-precision arithmetic, not a GPU's kernels; ``--device cuda``
(``auto``: a GPU where there is one) measures the GPU's, with the float32 reference in true
float32 (TF32 off for its convolutions and matrix products).
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import sys
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import torch
from torch import nn

from ekdun.data.pairs import PairsDataset
from ekdun.device import autocast, resolve_device
from ekdun.evaluation.metrics import psnr
from ekdun.nets.builder import network_from_checkpoint
from psfkit.cli.main import add_debug_option, run_cli
from psfkit.cli.parser import OneLineArgumentParser
from research.baseline_checks import name_list, write_study

AMPS = ("fp16", "bf16")


@contextlib.contextmanager
def true_float32() -> Iterator[None]:
    """CUDA's convolutions and matrix products in float32, not TF32 (restored after)."""
    saved = torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32
    torch.backends.cudnn.allow_tf32 = torch.backends.cuda.matmul.allow_tf32 = False
    try:
        yield
    finally:
        torch.backends.cudnn.allow_tf32, torch.backends.cuda.matmul.allow_tf32 = saved


def precision_gap(model: nn.Module, pairs: Sequence[tuple[torch.Tensor, torch.Tensor]],
                  amp: str, device: torch.device | str = "cpu") -> dict[str, Any]:
    """PSNR of ``model`` on ``pairs`` (``(scene, measurement)``, CHW) in float32 and under
    ``amp`` autocast on ``device``, per pair; ``delta_db`` is autocast minus float32 and
    ``agreement_db`` the PSNR of the autocast output against the float32 output."""
    device = torch.device(device)
    model = model.eval().to(device)
    rows = []
    with torch.inference_mode():
        for x, y in pairs:
            x, y = x.to(device), y.to(device)
            with true_float32():
                reference = model(y[None]).float().clamp(0, 1)
            with autocast(amp, device):
                half = model(y[None])
            half = half.float().clamp(0, 1)
            full_db = float(psnr(reference, x[None])[0])
            half_db = float(psnr(half, x[None])[0])
            rows.append({"psnr_fp32": full_db, f"psnr_{amp}": half_db,
                         "delta_db": half_db - full_db,
                         "agreement_db": float(psnr(half, reference)[0])})
    deltas = [r["delta_db"] for r in rows]
    return {"amp": amp, "pairs": rows, "mean_delta_db": statistics.fmean(deltas),
            "max_abs_delta_db": max(abs(d) for d in deltas),
            "min_agreement_db": min(r["agreement_db"] for r in rows)}


def precision_check(out: str | Path, checkpoints: Sequence[str], pairs: str,
                    amps: Sequence[str] = AMPS, device: torch.device | str = "cpu"
                    ) -> dict[str, Any]:
    """:func:`precision_gap` of every checkpoint's network on the ``pairs`` folder, per amp;
    writes ``OUT/precision.json`` and ``OUT/precision.md``."""
    dataset = PairsDataset(pairs)
    items = [dataset[i] for i in range(len(dataset))]
    runs = []
    for path in checkpoints:
        model, doc = network_from_checkpoint(path)
        for amp in amps:
            gap = precision_gap(model, items, amp, device)
            runs.append({"checkpoint": str(path), "model": doc["metadata"].get("model"),
                         **gap})
    where = torch.device(device)
    name = torch.cuda.get_device_name(where) if where.type == "cuda" else "the CPU"
    result = {"pairs": str(pairs), "n_pairs": len(items), "device": str(where),
              "device_name": name, "runs": runs}
    lines = ["| checkpoint | amp | mean Δ (dB) | max abs Δ (dB) | lowest agreement (dB) |",
             "|---|---|---|---|---|"]
    lines += [f"| {r['checkpoint']} | {r['amp']} | {r['mean_delta_db']:+.4f} | "
              f"{r['max_abs_delta_db']:.4f} | {r['min_agreement_db']:.1f} |" for r in runs]
    write_study(Path(out), "precision", result,
                f"{len(items)} test pairs of {pairs}; autocast on {name}\n\n"
                + "\n".join(lines) + "\n")
    return result


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m research.precision_check``."""
    p = OneLineArgumentParser(prog="python -m research.precision_check",
                              description="PSNR under autocast against float32, per pair, "
                                          "of trained checkpoints (issue 45).")
    add_debug_option(p)
    p.add_argument("out", help="output folder")
    p.add_argument("checkpoints", nargs="+", help="checkpoint files")
    p.add_argument("--pairs", required=True, help="test pairs folder")
    p.add_argument("--amp", type=name_list(list(AMPS), "autocast precisions"),
                   default=list(AMPS))
    p.add_argument("--device", default="auto", help="auto (a GPU where there is one), cpu, "
                                                     "cuda or cuda:N")
    p.add_argument("--threads", type=int, default=1)
    p.set_defaults(func=_run)
    return p


def _run(args: argparse.Namespace) -> int:
    torch.set_num_threads(max(1, args.threads))
    result = precision_check(args.out, args.checkpoints, args.pairs, args.amp,
                             resolve_device(args.device))
    for r in result["runs"]:
        print(f"{r['checkpoint']} {r['amp']}: mean {r['mean_delta_db']:+.4f} dB, "
              f"max |Δ| {r['max_abs_delta_db']:.4f} dB", file=sys.stderr)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``python -m research.precision_check`` with ``argv``; returns the exit code."""
    return run_cli("research.precision_check", build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
