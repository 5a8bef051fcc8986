"""Image-quality metrics in torch: PSNR, SSIM (Wang et al. 2004) and optional LPIPS.

SSIM: 11 × 11 Gaussian window (σ = 1.5), ``K1 = 0.01``, ``K2 = 0.03``, population covariances,
mean over the valid region and channels: skimage's ``structural_similarity`` with
``gaussian_weights=True, use_sample_covariance=False`` (tested).
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


def psnr(output: Tensor, target: Tensor, data_range: float = 1.0,
         mask: Tensor | None = None) -> Tensor:
    """Per-image PSNR (dB) of ``(B, C, H, W)`` tensors; with an ``(H, W)`` bool ``mask``, of
    the pixels inside it (every channel)."""
    err = (output.double() - target.double()) ** 2
    mse = (err[..., mask] if mask is not None else err).flatten(1).mean(dim=1)
    return 10.0 * torch.log10(data_range ** 2 / mse.clamp_min(1e-20))


def _gaussian_window(sigma: float = 1.5, truncate: float = 3.5) -> Tensor:
    radius = int(truncate * sigma + 0.5)
    x = torch.arange(-radius, radius + 1, dtype=torch.float64)
    g = torch.exp(-0.5 * (x / sigma) ** 2)
    return g / g.sum()


#: Pixels lost on each side by the SSIM window (its radius): SSIM map pixel ``(i, j)`` is the
#: window centred on image pixel ``(i + SSIM_MARGIN, j + SSIM_MARGIN)``.
SSIM_MARGIN = (_gaussian_window().numel() - 1) // 2


def ssim(output: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """Per-image SSIM of ``(B, C, H, W)`` tensors: the mean of :func:`ssim_map`
    (:class:`TensorShapeError` for images smaller than 11 × 11)."""
    return ssim_map(output, target, data_range).flatten(1).mean(dim=1)


def ssim_map(output: Tensor, target: Tensor, data_range: float = 1.0) -> Tensor:
    """Local SSIM of ``(B, C, H, W)`` tensors on the valid region, ``(B, C, H − 2m, W − 2m)``
    float64 with ``m =`` :data:`SSIM_MARGIN` (:class:`TensorShapeError` below 11 × 11)."""
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
    return ((2 * mx * my + c1) * (2 * sxy + c2)) / ((mx * mx + my * my + c1) * (sxx + syy + c2))


# torchvision AlexNet ``features`` convolutions → the slices of ``lpips``' AlexNet backbone
# (lpips.pretrained_networks.alexnet keeps torchvision's layer indices inside five slices)
_ALEXNET_SLICES = {0: 1, 3: 2, 6: 3, 8: 4, 10: 5}
_ALEXNET_SHAPES = {0: (64, 3, 11, 11), 3: (192, 64, 5, 5), 6: (384, 192, 3, 3),
                   8: (256, 384, 3, 3), 10: (256, 256, 3, 3)}


def alexnet_backbone_state(state: dict[str, Tensor], where: str) -> dict[str, Tensor]:
    """A torchvision AlexNet state dict as the state of the ``lpips`` package's backbone,
    strictly: every ``features`` convolution with AlexNet's shapes, ``classifier`` dropped,
    anything else a :class:`ValueError` naming the keys and ``where``."""
    out: dict[str, Tensor] = {}
    for index, sl in _ALEXNET_SLICES.items():
        for part, shape in (("weight", _ALEXNET_SHAPES[index]),
                            ("bias", _ALEXNET_SHAPES[index][:1])):
            key = f"features.{index}.{part}"
            if key not in state:
                raise ValueError(f"{where}: not a torchvision AlexNet state dict ({key} missing)")
            if tuple(state[key].shape) != shape:
                raise ValueError(f"{where}: {key} has shape {tuple(state[key].shape)}, AlexNet's "
                                 f"is {shape}")
            out[f"slice{sl}.{index}.{part}"] = state[key]
    unknown = sorted(k for k in state
                     if not k.startswith("classifier.") and k not in
                     {f"features.{i}.{p}" for i in _ALEXNET_SLICES for p in ("weight", "bias")})
    if unknown:
        raise ValueError(f"{where}: unexpected keys for AlexNet: {', '.join(unknown[:4])}")
    return out


class LPIPSMetric:
    """LPIPS (Zhang et al. 2018; AlexNet backbone, linear layers v0.1), or "n/a".

    Needs the ``lpips`` package and a local torchvision AlexNet state dict (``weights`` or
    ``$EKDUN_LPIPS_WEIGHTS``; nothing is downloaded), both loaded strictly; otherwise
    ``available`` is False and :attr:`reason` says why.
    """

    def __init__(self, weights: str | os.PathLike | None = None,
                 device: torch.device | str = "cpu") -> None:
        self.available = False
        self.reason = ""
        self.model: Any = None
        path = weights or os.environ.get(LPIPS_ENV)
        try:
            import lpips  # type: ignore[import-not-found]
        except Exception as exc:   # absent, or its torchvision does not import beside torch
            self.reason = (f"LPIPS n/a: the 'lpips' package cannot be imported "
                           f"({type(exc).__name__})")
            return
        if not path or not Path(path).is_file():
            self.reason = (f"LPIPS n/a: no local AlexNet weights (set {LPIPS_ENV} or "
                           "--lpips-weights to a torchvision AlexNet state dict)")
            return
        try:
            state = torch.load(path, map_location="cpu", weights_only=True)
            if not isinstance(state, dict):
                raise ValueError(f"{path}: not a state dict")
            backbone = alexnet_backbone_state(state, str(path))
            model = lpips.LPIPS(net="alex", version="0.1", pretrained=True, pnet_rand=True,
                                verbose=False)
            model.net.load_state_dict(backbone, strict=True)
        except Exception as exc:
            self.reason = f"LPIPS n/a: {str(exc).splitlines()[0][:160]}"
            return
        self.model = model.to(device).eval()
        self.available = True

    @torch.no_grad()
    def __call__(self, output: Tensor, target: Tensor) -> Tensor:
        """Per-image LPIPS of ``(B, 3, H, W)`` images in ``[0, 1]`` (NaN when unavailable)."""
        if not self.available:
            return torch.full((output.shape[0],), math.nan, dtype=torch.float64)
        d = self.model(output.float() * 2 - 1, target.float() * 2 - 1)
        return d.flatten().double().cpu()
