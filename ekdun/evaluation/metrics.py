"""Image-quality metrics in torch: PSNR, SSIM (Wang et al. 2004) and optional LPIPS.

SSIM uses the standard 11 × 11 Gaussian window (σ = 1.5), ``K1 = 0.01``, ``K2 = 0.03``,
population covariances, the mean over the valid region and over channels: the same numbers as
``skimage.metrics.structural_similarity(..., gaussian_weights=True, sigma=1.5,
use_sample_covariance=False, data_range=1, channel_axis=...)`` (tested).
"""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

import torch
from torch import Tensor
from torch.nn import functional as F

from ekdun.errors import TensorShapeError

LPIPS_ENV = "EKDUN_LPIPS_WEIGHTS"


def psnr(output: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """Per-image PSNR (dB) of ``(B, C, H, W)`` tensors."""
    mse = ((output.double() - target.double()) ** 2).flatten(1).mean(dim=1)
    return 10.0 * torch.log10(data_range ** 2 / mse.clamp_min(1e-20))


def _gaussian_window(sigma: float = 1.5, truncate: float = 3.5) -> Tensor:
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


def ssim(output: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """Per-image SSIM of ``(B, C, H, W)`` tensors (images at least 11 × 11).

    Raises
    ------
    TensorShapeError
        Images smaller than the 11 × 11 Gaussian window.
    """
    x, y = output.double(), target.double()
    _, c, h, w = x.shape
    g = _gaussian_window()
    k = g.numel()
    if h < k or w < k:
        raise TensorShapeError(f"SSIM needs images of at least {k}x{k}, got {h}x{w}")
    gh = g.view(1, 1, k, 1).repeat(c, 1, 1, 1).to(x.device)
    gw = g.view(1, 1, 1, k).repeat(c, 1, 1, 1).to(x.device)

    def blur(t: Tensor) -> Tensor:
        return F.conv2d(F.conv2d(t, gh, groups=c), gw, groups=c)

    mx, my = blur(x), blur(y)
    sxx = blur(x * x) - mx * mx
    syy = blur(y * y) - my * my
    sxy = blur(x * y) - mx * my
    c1, c2 = (0.01 * data_range) ** 2, (0.03 * data_range) ** 2
    s = ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))
    return s.flatten(1).mean(dim=1)


class LPIPSMetric:
    """LPIPS if the ``lpips`` package and its backbone weights are available locally.

    The backbone weights cannot be downloaded here: give their path (a torchvision AlexNet
    state dict) with ``weights`` or ``$EKDUN_LPIPS_WEIGHTS``; otherwise ``available`` is False
    and :attr:`reason` says why (reported as "LPIPS unavailable" in the tables).
    """

    def __init__(self, weights: str | os.PathLike | None = None,
                 device: torch.device | str = "cpu") -> None:
        self.available = False
        self.reason = ""
        self.model: Any = None
        path = weights or os.environ.get(LPIPS_ENV)
        try:
            import lpips  # type: ignore[import-not-found]
        except ImportError:
            self.reason = "LPIPS unavailable: the 'lpips' package is not installed"
            return
        if not path or not Path(path).is_file():
            self.reason = (f"LPIPS unavailable: no local backbone weights (set {LPIPS_ENV} "
                           "or --lpips-weights to an AlexNet state dict)")
            return
        try:
            model = lpips.LPIPS(net="alex", pretrained=True, pnet_rand=True, verbose=False)
            state = torch.load(path, map_location="cpu", weights_only=True)
            model.net.load_state_dict(state, strict=False)
            self.model = model.to(device).eval()
            self.available = True
        except Exception as exc:
            self.reason = f"LPIPS unavailable: {type(exc).__name__}: {str(exc)[:100]}"

    @torch.no_grad()
    def __call__(self, output: Tensor, target: Tensor) -> Tensor:
        if not self.available:
            return torch.full((output.shape[0],), math.nan, dtype=torch.float64)
        d = self.model(output.float() * 2 - 1, target.float() * 2 - 1)
        return d.flatten().double().cpu()
