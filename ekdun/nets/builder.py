"""Build networks from a seed kernel model and rebuild them from checkpoints."""

from __future__ import annotations

import os
from dataclasses import asdict, fields, replace
from typing import Any

import numpy as np

from ekdun.errors import CheckpointError, ConfigurationError
from ekdun.nets.checkpoint import load_checkpoint
from ekdun.nets.configs import UNetConfig
from ekdun.nets.ekdun_net import EKDUN
from ekdun.nets.factory import build_model
from ekdun.nets.unrolled import UnrolledNetwork
from psfkit.errors import ModelFileError
from psfkit.forward.kernelfile import KernelModel, load_kernels
from psfkit.forward.weights import get_basis

#: EK-DUN settings that moved to research/kernel_models.py (issue 44)
MOVED_OVERRIDES = ("kernel_param", "kernel_support_dilate", "flow_grid", "flow_residual",
                   "kernel_gain")


def seed_kernel_model(source: KernelModel | np.ndarray | str | os.PathLike) -> KernelModel:
    """A kernel model from a kernel file, a loaded model, a PSF image file
    (:func:`psfkit.calibration.psf_image.load_psf_image`) or a PSF array ``(C, H, W)``."""
    if isinstance(source, KernelModel):
        return source
    if isinstance(source, (str, os.PathLike)):
        path = str(source)
        if path.endswith(".npz"):
            return load_kernels(path)
        from psfkit.calibration.psf_image import load_psf_image

        source = load_psf_image(path)
    psf = np.asarray(source, dtype=np.float32)
    if psf.ndim == 2:
        psf = psf[None]
    return KernelModel.shift_invariant(psf, normalization="measured PSF",
                                       provenance={"source": "measured PSF"})


def decode_overrides(overrides: dict[str, Any]) -> dict[str, Any]:
    """JSON overrides → config values (U-Net widths lists become :class:`UNetConfig`)."""
    out = {}
    for key, value in overrides.items():
        if isinstance(value, dict) and "widths" in value:
            names = {f.name for f in fields(UNetConfig)}
            value = UNetConfig(**{k: tuple(v) if k == "widths" else v
                                  for k, v in value.items() if k in names})
        out[key] = value
    return out


def encode_overrides(overrides: dict[str, Any]) -> dict[str, Any]:
    """Config overrides → JSON-able values."""
    out = {}
    for key, value in overrides.items():
        if isinstance(value, UNetConfig):
            value = {**asdict(value), "widths": list(value.widths)}
        out[key] = value
    return out


def build_network(name: str, seed: KernelModel, preset: str,
                  overrides: dict[str, Any] | None = None) -> UnrolledNetwork:
    """:func:`ekdun.nets.factory.build_model` from a seed model, remembering the seed."""
    overrides = decode_overrides(overrides or {})
    source: Any = seed
    if seed.basis == "si" or seed.kernels.shape[0] == 1:
        source = seed.kernels[0]
    model = build_model(name, source, preset, **overrides)
    if isinstance(model, EKDUN) and source is not seed:
        # EK-DUN built from a PSF: Kv = Kh = Kbase in the configured basis, the seed's geometry.
        basis = model.config.basis
        seed = replace(seed, basis=basis,
                       kernels=np.repeat(seed.kernels[:1], get_basis(basis).n_kernels, axis=0))
    model.set_seed_kernels(seed)
    return model


def _recorded_overrides(meta: dict[str, Any], state: dict[str, Any]) -> dict[str, Any]:
    """The checkpoint's config overrides, with UPDN's iterations read from its weights when
    not recorded (older ``tiny`` checkpoints had 5, without an override), without the kernel
    module's settings older EK-DUN runs recorded there (research/kernel_models.py)."""
    overrides = {k: v for k, v in meta.get("overrides", {}).items() if k not in MOVED_OVERRIDES}
    if meta.get("model") == "updn" and "iterations" not in overrides:
        blocks = {key.split(".")[1] for key in state if key.startswith("dual_updates.")}
        if blocks:
            overrides["iterations"] = len(blocks)
    return overrides


def network_from_checkpoint(checkpoint: str | os.PathLike | dict[str, Any],
                            where: str | None = None) -> tuple[UnrolledNetwork, dict[str, Any]]:
    """Rebuild a checkpoint's network with its weights: ``(model, checkpoint dict)``, or
    :class:`CheckpointError`. ``where`` names a checkpoint given as a loaded dict."""
    doc = checkpoint if isinstance(checkpoint, dict) else load_checkpoint(checkpoint)
    meta = doc["metadata"]
    where = where or ("checkpoint" if isinstance(checkpoint, dict) else str(checkpoint))
    try:
        seed = KernelModel.from_metadata(doc["initial_kernels"].numpy(),
                                         meta["kernel_metadata"],
                                         where="initial kernels")
        model = build_network(meta["model"], seed, meta["preset"],
                              _recorded_overrides(meta, doc["model"]))
        # a kernel module's weights (a study's: research/) are not rebuilt here; physics.kernels
        # holds what it made
        model.load_state_dict({k: v for k, v in doc["model"].items()
                               if not k.startswith("kernel_param.")})
    except (KeyError, RuntimeError, TypeError, ValueError, AttributeError,
            ConfigurationError, ModelFileError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{where}: cannot rebuild the network ({first[:160]})") from None
    # build_network remembered the checkpoint's seed (an EK-DUN from a PSF: its expansion).
    return model, doc

