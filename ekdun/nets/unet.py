"""The U-Net shared by all reconstruction networks (EK-DUN's prior, the baselines' denoisers).

Per level ``l`` of ``widths``: two ``Conv3×3 → ReLU`` at ``w_l``, 2×2 max-pool down,
``ConvTranspose2d`` 2×2 up with a skip connection, then a final ``1×1`` convolution. Residual
output (default): ``out = x[:, :out_channels] + body(x)``; with ``zero_init_output`` a fresh
U-Net is the identity, so a fresh unrolled network is its stable physics-only iteration. Odd
sizes are handled by zero-padding the upsampled features at the bottom/right. Convolutions run
channels-last (1.8× faster on CPU at 1080×1440; what tensor cores prefer).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from ekdun.errors import ConfigurationError


def channels_last(module: nn.Module, x: Tensor) -> Tensor:
    """``module(x)`` computed in the channels-last layout, returned contiguous (NCHW)."""
    return module(x.contiguous(memory_format=torch.channels_last)).contiguous()


def conv_block(in_channels: int, out_channels: int) -> nn.Sequential:
    """Two ``Conv3×3 → ReLU`` layers."""
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, 3, padding=1), nn.ReLU(inplace=True),
        nn.Conv2d(out_channels, out_channels, 3, padding=1), nn.ReLU(inplace=True))


class UNet(nn.Module):
    """U-Net with max-pool down, transposed-convolution up and skip connections.

    Parameters
    ----------
    in_channels, out_channels : int
        Channels of the input ``(B, in_channels, H, W)`` and of the output.
    widths : tuple of int
        Feature width of each level, top first.
    residual : bool
        Add the first ``out_channels`` input channels to the output.
    zero_init_output : bool
        Start the final ``1×1`` convolution at zero.
    """

    def __init__(self, in_channels: int, out_channels: int,
                 widths: tuple[int, ...] = (32, 64, 128), residual: bool = True,
                 zero_init_output: bool = True) -> None:
        super().__init__()
        if len(widths) < 1 or min(widths) < 1:
            raise ConfigurationError(f"U-Net widths must be positive, got {widths}")
        if residual and in_channels < out_channels:
            raise ConfigurationError(f"a residual U-Net needs in_channels >= out_channels, got "
                                     f"{in_channels} < {out_channels}")
        self.widths = tuple(int(w) for w in widths)
        self.residual = residual
        self.out_channels = out_channels
        ins = (in_channels, *self.widths[:-1])
        self.encoders = nn.ModuleList(conv_block(i, w) for i, w in zip(ins, self.widths,
                                                                       strict=True))
        self.upsamplers = nn.ModuleList(
            nn.ConvTranspose2d(self.widths[level + 1], self.widths[level], 2, stride=2)
            for level in range(len(self.widths) - 1))
        self.decoders = nn.ModuleList(conv_block(2 * w, w) for w in self.widths[:-1])
        self.head = nn.Conv2d(self.widths[0], out_channels, 1)
        if zero_init_output:
            nn.init.zeros_(self.head.weight)
            nn.init.zeros_(self.head.bias)

    def forward(self, x: Tensor) -> Tensor:
        """``(B, in_channels, H, W) → (B, out_channels, H, W)``."""
        skips = []
        features = x.contiguous(memory_format=torch.channels_last)
        for level, encoder in enumerate(self.encoders):
            if level > 0:
                features = F.max_pool2d(features, 2)
            features = encoder(features)
            skips.append(features)
        for level in range(len(self.decoders) - 1, -1, -1):
            up = self.upsamplers[level](features)
            skip = skips[level]
            # an odd size was floored by the max-pool: pad the bottom/right row/column back
            dh, dw = skip.shape[-2] - up.shape[-2], skip.shape[-1] - up.shape[-1]
            if dh or dw:
                up = F.pad(up, (0, dw, 0, dh))
            features = self.decoders[level](torch.cat([up, skip], dim=1))
        out = self.head(features).contiguous()
        if self.residual:
            out = x[:, :self.out_channels] + out
        return out
