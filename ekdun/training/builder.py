"""Build networks from a seed kernel model and rebuild them from checkpoints."""

from __future__ import annotations

import os
from dataclasses import fields
from typing import Any

import numpy as np
import torch

from ekdun.errors import ConfigurationError
from ekdun.models.configs import UNetConfig
from ekdun.models.factory import build_model
from ekdun.models.unrolled import UnrolledNetwork
from ekdun.training.checkpoint import CheckpointError, load_checkpoint
from psfkit.kernelfile import KernelModel, load_kernels
from psfkit.weights import get_basis


def seed_kernel_model(source: KernelModel | np.ndarray | str | os.PathLike) -> KernelModel:
    """A kernel model from a kernel file, a loaded model or a measured PSF ``(C, H, W)``."""
    if isinstance(source, KernelModel):
        return source
    if isinstance(source, (str, os.PathLike)):
        path = str(source)
        if path.endswith(".npz"):
            return load_kernels(path)
        from psfkit.io.images import read_image
        from psfkit.validation import require_finite

        source = require_finite(read_image(path), str(path)).astype(np.float32)
    psf = np.asarray(source, dtype=np.float32)
    if psf.ndim == 2:
        psf = psf[None]
    return KernelModel.shift_invariant(psf, normalization="measured PSF as given",
                                       provenance={"source": "measured PSF"})


def kernel_metadata(model: KernelModel) -> dict[str, Any]:
    """JSON-able description of a kernel model without its kernels."""
    return {"basis": model.basis, "convention": model.convention,
            "sensor_shape": list(model.sensor_shape), "channels": list(model.channels),
            "optical_center": None if model.optical_center is None
            else list(model.optical_center),
            "scene_padding": model.scene_padding, "normalization": model.normalization,
            "provenance": model.provenance}


def kernel_model_from(kernels: np.ndarray, meta: dict[str, Any]) -> KernelModel:
    """Inverse of :func:`kernel_metadata` with the kernels given."""
    return KernelModel(kernels=np.asarray(kernels, dtype=np.float32), basis=meta["basis"],
                       convention=meta["convention"],
                       sensor_shape=tuple(meta["sensor_shape"]),
                       channels=tuple(meta["channels"]),
                       optical_center=None if meta.get("optical_center") is None
                       else tuple(meta["optical_center"]),
                       scene_padding=int(meta.get("scene_padding", 2)),
                       normalization=meta.get("normalization", "unspecified"),
                       provenance=meta.get("provenance", {}))


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
            value = {f.name: (list(getattr(value, f.name)) if f.name == "widths"
                              else getattr(value, f.name)) for f in fields(UNetConfig)}
        out[key] = value
    return out


def build_network(name: str, seed: KernelModel, preset: str,
                  overrides: dict[str, Any] | None = None) -> UnrolledNetwork:
    """:func:`ekdun.models.factory.build_model` from a seed model, remembering the seed."""
    overrides = decode_overrides(overrides or {})
    source: Any = seed
    if seed.basis == "si" or seed.kernels.shape[0] == 1:
        source = seed.kernels[0]
    model = build_model(name, source, preset, **overrides)
    if name == "ekdun" and source is not seed:
        # EK-DUN built from a PSF: Kv = Kh = Kbase, paper basis, the seed's geometry.
        config_basis = getattr(model, "config", None)
        basis = getattr(config_basis, "basis", "paper")
        n = get_basis(basis).n_kernels
        seed = kernel_model_from(np.repeat(seed.kernels[:1], n, axis=0),
                                 {**kernel_metadata(seed), "basis": basis})
    model.seed_kernels = seed  # type: ignore[attr-defined]
    return model


def network_from_checkpoint(checkpoint: str | os.PathLike | dict[str, Any]
                            ) -> tuple[UnrolledNetwork, dict[str, Any]]:
    """Rebuild the network of a checkpoint and load its weights.

    Returns ``(model, checkpoint dict)``; raises :class:`CheckpointError` when the file is not
    a usable ekdun checkpoint.
    """
    doc = checkpoint if isinstance(checkpoint, dict) else load_checkpoint(checkpoint)
    meta = doc["metadata"]
    where = "checkpoint" if isinstance(checkpoint, dict) else str(checkpoint)
    try:
        seed = kernel_model_from(doc["initial_kernels"].numpy(), meta["kernel_metadata"])
        model = build_network(meta["model"], seed, meta["preset"], meta.get("overrides", {}))
        model.load_state_dict(doc["model"])
    except (KeyError, RuntimeError, TypeError, ValueError, AttributeError,
            ConfigurationError) as exc:
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise CheckpointError(f"{where}: cannot rebuild the network ({first[:160]})") from None
    model.seed_kernels = seed  # type: ignore[attr-defined]
    return model, doc


def to_device(model: torch.nn.Module, device: str) -> torch.nn.Module:
    return model.to(torch.device(device))
