"""Build a reconstruction network from a kernel file (or a measured PSF) and a preset."""

from __future__ import annotations

import dataclasses
import os
from typing import Any

import numpy as np
import torch

from ekdun.choices import MODEL_NAMES
from ekdun.errors import ConfigurationError, KernelShapeError
from ekdun.nets.configs import (
    EKDUNConfig,
    LeADMMUConfig,
    Preset,
    UPDNConfig,
    get_preset,
)
from ekdun.nets.ekdun_net import EKDUN
from ekdun.nets.le_admm_u import LeADMMU
from ekdun.nets.unrolled import UnrolledNetwork
from ekdun.nets.updn import UPDN
from ekdun.physics.multi_psf import MultiPSFOperator
from ekdun.physics.operators import EigenKernelOperator, ShiftInvariantOperator, psf_tensor
from psfkit.forward.kernelfile import KernelModel, load_kernels
from psfkit.forward.weights import get_basis

__all__ = ["MODEL_NAMES", "Source", "build_model"]


Source = KernelModel | np.ndarray | torch.Tensor | str | os.PathLike


def build_model(name: str, source: Source, preset: str | Preset = "tiny", *,
                config: EKDUNConfig | LeADMMUConfig | UPDNConfig | None = None,
                dtype: torch.dtype = torch.float32, **overrides: Any) -> UnrolledNetwork:
    """Build ``"ekdun"``, ``"le-admm-u"`` or ``"updn"``.

    Parameters
    ----------
    name : str
        Model name (:data:`MODEL_NAMES`).
    source : KernelModel, array, tensor or path
        A kernel file (path or loaded) or a centred PSF ``(C, H', W')`` / ``(H', W')``, which
        also sets the sensor size. EK-DUN starts from all its kernels (from a PSF:
        ``Kv = Kh = Kbase = PSF``); the baselines use the base kernel as the measured PSF.
    preset : str or Preset
        ``"tiny"`` or ``"paper"``.
    config : optional
        The model's configuration, replacing the preset's.
    dtype : torch.dtype
    **overrides
        Fields of the model's configuration to change, e.g. ``schedule="base"``.
    """
    chosen = get_preset(preset)
    if isinstance(source, (str, os.PathLike)):
        source = load_kernels(source)
    key = name.lower().replace("_", "-")
    if key not in MODEL_NAMES:
        raise ConfigurationError(f"unknown model {name!r} (use {', '.join(MODEL_NAMES)})")
    # the preset's configuration of the model: Preset.ekdun, .le_admm_u or .updn
    cfg = config if config is not None else getattr(chosen, key.replace("-", "_"))
    try:
        cfg = dataclasses.replace(cfg, **overrides)
    except TypeError as exc:
        raise ConfigurationError(f"{key}: {exc}") from None
    psf, sensor, padding, centre = _measured_psf(source, chosen, dtype)
    if key == "ekdun":
        assert isinstance(cfg, EKDUNConfig)
        if isinstance(source, KernelModel) and source.kernels.shape[0] > 1:
            physics = EigenKernelOperator.from_kernel_model(source, trainable=True, dtype=dtype)
        else:
            n = get_basis(cfg.basis).n_kernels
            physics = EigenKernelOperator.from_basis(
                psf[None].repeat(n, 1, 1, 1), cfg.basis, sensor, optical_center=centre,
                scene_padding=padding, trainable=True)
        return EKDUN(physics, cfg)
    if key == "le-admm-u":
        assert isinstance(cfg, LeADMMUConfig)
        return LeADMMU(ShiftInvariantOperator(psf, sensor, padding, trainable=False), cfg)
    assert isinstance(cfg, UPDNConfig)
    if cfg.copies < 1:
        raise ConfigurationError(f"copies must be >= 1, got {cfg.copies}")
    return UPDN(MultiPSFOperator(psf[None].repeat(cfg.copies, 1, 1, 1), sensor, padding), cfg)


def _measured_psf(source: KernelModel | np.ndarray | torch.Tensor, preset: Preset,
                  dtype: torch.dtype) -> tuple[torch.Tensor, tuple[int, int], int,
                                               tuple[float, float] | None]:
    """``(psf (C, H, W), sensor shape, scene padding, optical centre)`` of a source."""
    if isinstance(source, KernelModel):
        return (torch.as_tensor(source.kernels[0], dtype=dtype), source.sensor_shape,
                source.scene_padding, source.optical_center)
    psf = psf_tensor(source, dtype)
    if psf.shape[0] not in (1, 3):
        raise KernelShapeError(f"a measured PSF must be (C, H, W) with C = 1 or 3, got shape "
                               f"{tuple(psf.shape)}")
    return psf, (int(psf.shape[-2]), int(psf.shape[-1])), preset.scene_padding, None
