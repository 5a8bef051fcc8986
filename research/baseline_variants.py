"""What each difference of our baselines from their authors' code costs (issue 45 item 1).

    python -m research.baseline_variants OUT [--variants le-admm-u,le-admm-u-normalised,...]
        [--sensor 64 64] [--n-train 128] [--n-test 16] [--epochs 8] [--seeds 0,1,2]

Each variant is one network of the ``tiny`` preset trained at its recipe on the varying
virtual bench (the sweep's data and budget, :mod:`research.baseline_checks`) with one choice
changed to the reference's; held-out PSNR over training seeds and the difference to the
network as we build it, paired by seed. Variants:

``le-admm-u-normalised``
    Le-ADMM-U with the reference's per-image normalisation between ADMM and U-Net
    (Waller-Lab/LenslessLearning ``normalize_image``: the cropped ADMM image divided by its
    maximum over channels and pixels).
``le-admm-u-reference-unet``
    Le-ADMM-U with a U-Net shaped as the reference's ``UNet270480`` at our widths: a 2×2
    max-pool after every encoder level, a centre block, bilinear upsampling, three
    convolutions per decoder level, BatchNorm after every convolution (no bias), a plain
    (not residual) output (:class:`ReferenceUNet`).
``le-admm-u-reference``
    Both: the reference's normalisation and U-Net.
``updn-sigmoid``
    UPDN with the reference's sigmoid on the output (oliland/lensless-primal-dual).
``updn-5``
    UPDN with 5 iterations, ``tiny``'s before it took the reference's 10 (measured at 128² by
    ``research.benchmark_tiny``: research/notes/baselines-measurements.md).
``updn-psf-rate``
    UPDN with its PSFs trained at the network's learning rate, as the reference (ours: 1e-2
    of it, ``kernel_lr_scale``).
``updn-unet-fast``, ``updn-blocks-slow``
    Not the reference's (one rate for all): UPDN's U-Net at twice the network's rate, or its
    primal-dual blocks at a quarter of it; whether its joint fit is held by one part chasing
    the other (research/notes/baselines-measurements.md, overfitting).

A variant that changes a method is applied by replacing the method for the duration of its
training and evaluation (:func:`applied`); the product's classes are not changed.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ekdun.data.virtual_bench import VirtualBenchSpec
from ekdun.evaluation import LPIPSMetric
from ekdun.evaluation.tables import markdown_table, seed_summary
from ekdun.nets.le_admm_u import LeADMMU
from ekdun.nets.updn import UPDN
from ekdun.training import trainer
from ekdun.training.trainer import TrainOptions
from psfkit.cli import run_cli
from psfkit.cli.main import add_debug_option
from psfkit.cli.parser import OneLineArgumentParser
from psfkit.forward.convolution import crop
from research.baseline_checks import (
    add_bench_arguments,
    bench_pairs,
    bench_setup,
    name_list,
    write_study,
)
from research.benchmark_tiny import int_list, train_and_evaluate


def _normalised_output(self: LeADMMU, state: dict[str, Tensor], context: dict[str, Any]
                       ) -> Tensor:
    """The reference's ``normalize_image``: each ADMM image over its maximum, then the U-Net."""
    x = crop(state["x"], self.physics.sensor_shape)
    peak = x.flatten(1).amax(dim=1).clamp_min(1e-12)[:, None, None, None]
    return self.denoiser(x / peak)


def _sigmoid_output(self: UPDN, state: dict[str, Tensor], context: dict[str, Any]) -> Tensor:
    """The reference's output: a sigmoid on the first copy's image plus the U-Net's."""
    return torch.sigmoid(self.denoiser(crop(state["primal"], self.physics.sensor_shape)))


def _conv_bn_relu(in_channels: int, out_channels: int) -> list[nn.Module]:
    return [nn.Conv2d(in_channels, out_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(out_channels, eps=1e-4), nn.ReLU(inplace=True)]


class ReferenceUNet(nn.Module):
    """The shape of Le-ADMM-U's ``UNet270480`` (Waller-Lab/LenslessLearning) at any widths:
    encoder level ``l``: two ``Conv3×3 → BN → ReLU`` at ``w_l``, then a 2×2 max-pool (after
    every level, the last included); a centre ``Conv3×3 → BN → ReLU`` at ``w_{L-1}``;
    decoder level ``l``: bilinear upsampling to the skip's size, concatenation, three
    ``Conv3×3 → BN → ReLU`` to ``w_{l-1}`` (``w_0`` at the top); a ``1×1`` head with bias."""

    def __init__(self, channels: int, widths: Sequence[int]) -> None:
        super().__init__()
        ins = (channels, *widths[:-1])
        self.encoders = nn.ModuleList(nn.Sequential(*_conv_bn_relu(i, w), *_conv_bn_relu(w, w))
                                      for i, w in zip(ins, widths, strict=True))
        self.centre = nn.Sequential(*_conv_bn_relu(widths[-1], widths[-1]))
        outs = (widths[0], *widths[:-1])
        self.decoders = nn.ModuleList(
            nn.Sequential(*_conv_bn_relu(2 * w, o), *_conv_bn_relu(o, o), *_conv_bn_relu(o, o))
            for w, o in zip(widths, outs, strict=True))
        self.head = nn.Conv2d(widths[0], channels, 1)

    def forward(self, x: Tensor) -> Tensor:
        """``(B, C, H, W) → (B, C, H, W)``."""
        skips = []
        for encoder in self.encoders:
            x = encoder(x)
            skips.append(x)
            x = F.max_pool2d(x, 2)
        x = self.centre(x)
        for decoder, skip in zip(reversed(self.decoders), reversed(skips), strict=True):
            x = F.interpolate(x, size=skip.shape[-2:], mode="bilinear", align_corners=False)
            x = decoder(torch.cat([x, skip], dim=1))
        return self.head(x)


_LE_ADMM_U_INIT = LeADMMU.__init__
_PARAM_GROUPS = trainer._param_groups


def _scaled_groups(prefix: str | tuple[str, ...], scale: float
                   ) -> Callable[..., list[dict[str, Any]]]:
    """The trainer's parameter groups with the parameters named ``prefix…`` at ``scale`` × the
    network's rate, in a group of their own."""

    def groups(model: nn.Module, lr: float, kernel_lr_scale: float) -> list[dict[str, Any]]:
        out = _PARAM_GROUPS(model, lr, kernel_lr_scale)
        chosen = {id(p) for name, p in model.named_parameters() if name.startswith(prefix)}
        rest = [p for p in out[0]["params"] if id(p) not in chosen]
        picked = [p for p in out[0]["params"] if id(p) in chosen]
        return [{"params": rest, "lr": lr}, {"params": picked, "lr": lr * scale}, *out[1:]]

    return groups


def _reference_unet_init(self: LeADMMU, physics: Any, config: Any = None) -> None:
    """Le-ADMM-U as built, its U-Net replaced by :class:`ReferenceUNet` at the same widths."""
    _LE_ADMM_U_INIT(self, physics, config)
    self.denoiser = ReferenceUNet(physics.channels, self.config.denoiser.widths)


@dataclass(frozen=True)
class Variant:
    """A network (``model``, as ``ekdun train`` names it) with config ``overrides``, training
    options changed (``training``: fields of :class:`TrainOptions`) and methods replaced
    (``patches``: ``(class, name, function)``); it is compared with the variant labelled
    ``model``, the network as we build it."""

    label: str
    model: str
    overrides: dict[str, Any] = field(default_factory=dict)
    training: dict[str, Any] = field(default_factory=dict)
    patches: tuple[tuple[type, str, Callable[..., Any]], ...] = ()


VARIANTS = {v.label: v for v in (
    Variant("le-admm-u", "le-admm-u"),
    Variant("le-admm-u-normalised", "le-admm-u",
            patches=((LeADMMU, "output", _normalised_output),)),
    Variant("le-admm-u-reference-unet", "le-admm-u",
            patches=((LeADMMU, "__init__", _reference_unet_init),)),
    Variant("le-admm-u-reference", "le-admm-u",
            patches=((LeADMMU, "__init__", _reference_unet_init),
                     (LeADMMU, "output", _normalised_output))),
    Variant("updn", "updn"),
    Variant("updn-sigmoid", "updn", patches=((UPDN, "output", _sigmoid_output),)),
    Variant("updn-5", "updn", overrides={"iterations": 5}),
    Variant("updn-psf-rate", "updn", training={"kernel_lr_scale": 1.0}),
    Variant("updn-unet-fast", "updn",
            patches=((trainer, "_param_groups", _scaled_groups("denoiser.", 2.0)),)),
    Variant("updn-blocks-slow", "updn",
            patches=((trainer, "_param_groups", _scaled_groups(("dual_updates.",
                                                                 "primal_updates."), 0.25)),)),
)}


@contextmanager
def applied(variant: Variant) -> Iterator[None]:
    """Within the block the variant's methods replace the product's; restored after."""
    saved = [(cls, name, cls.__dict__[name]) for cls, name, _f in variant.patches]
    try:
        for cls, name, function in variant.patches:
            setattr(cls, name, function)
        yield
    finally:
        for cls, name, original in saved:
            setattr(cls, name, original)


def variants_check(out: str | Path, spec: VirtualBenchSpec, labels: Sequence[str],
                   seeds: Sequence[int], options: TrainOptions, preset: str = "tiny",
                   log: Any = print) -> dict[str, Any]:
    """Train every variant over ``seeds`` on the varying bench; PSNR and each variant's
    difference to its base network, paired by seed."""
    out = Path(out)
    kernels, train_set, test_set = bench_pairs(out, spec, options.progress)
    lpips = LPIPSMetric(None)
    rows = []
    for label in labels:
        variant = VARIANTS[label]
        for seed in seeds:
            with applied(variant):
                row = train_and_evaluate((label, variant.model, dict(variant.overrides)), seed,
                                         kernels, train_set, test_set, preset,
                                         replace(options, **variant.training), lpips,
                                         out / "runs" / f"{label}-s{seed}")
            row["label"] = label
            rows.append(row)
            log(f"{label} seed {seed}: {row['psnr']:.2f} dB")
    summaries = {}
    for base in sorted({VARIANTS[label].model for label in labels}):
        group = [r for r in rows if VARIANTS[r["label"]].model == base]
        if any(r["label"] == base for r in group):
            summaries[base] = seed_summary(group, reference=base)
    doc = {"spec": spec.to_dict(), "preset": preset, "seeds": list(seeds),
           "epochs": options.epochs,
           "rows": [{k: r[k] for k in ("label", "seed", "psnr", "ssim", "lr", "epochs",
                                       "train_seconds", "parameters")} for r in rows],
           "summary": summaries}
    columns = [("label", "Variant", -1), ("psnr_text", "PSNR (dB), mean ± sd", -1),
               ("ssim_mean", "SSIM", 4), ("delta_text", "Δ to ours, paired by seed (dB)", -1)]
    text = "".join(f"### {base}: variants, seeds {list(seeds)}\n\n"
                   f"{markdown_table(s, columns)}\n\n" for base, s in summaries.items())
    write_study(out, "variants", doc,
                text + f"Virtual bench {spec.sensor_shape}, {spec.n_train} / {spec.n_test} "
                       f"pairs, preset {preset} (recipes).\n")
    return doc


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m research.baseline_variants``."""
    p = OneLineArgumentParser(prog="python -m research.baseline_variants",
                              description="The cost of each difference of the baselines "
                                          "from their authors' code (issue 45).")
    add_debug_option(p)
    add_bench_arguments(p, 64, 128)
    p.add_argument("--variants", type=name_list(list(VARIANTS), "variants"),
                   default=list(VARIANTS))
    p.add_argument("--epochs", type=int, default=8)
    p.add_argument("--seeds", type=int_list, default=[0, 1, 2])
    p.set_defaults(func=_run)
    return p


def _run(args: argparse.Namespace) -> int:
    spec, log = bench_setup(args, args.epochs)
    options = TrainOptions(epochs=args.epochs, progress=not args.quiet, threads=args.threads)
    variants_check(args.out, spec, args.variants, args.seeds, options, log=log)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``python -m research.baseline_variants`` with ``argv``; returns the exit code."""
    return run_cli("research.baseline_variants", build_parser(), argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
