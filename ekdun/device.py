"""The torch device of ``--device`` and the speed options of training and inference:
autocast precision (the physics FFTs stay float32, ``tests/ekdun/test_training_speed.py``) and
channels_last."""

from __future__ import annotations

import contextlib

import torch
from torch import nn

from ekdun.choices import AMP_CHOICES
from ekdun.errors import ConfigurationError

_DTYPES = {"bf16": torch.bfloat16, "fp16": torch.float16}


def resolve_device(device: str | torch.device, local_rank: int = 0) -> torch.device:
    """The torch device named by ``--device`` (``auto``, ``cpu``, ``cuda``, ``cuda:N``, ``mps``);
    :class:`ConfigurationError` when this machine does not have it."""
    if isinstance(device, torch.device):
        return device
    if device == "auto":
        return torch.device(f"cuda:{local_rank}" if torch.cuda.is_available() else "cpu")
    from ekdun.flag_ranges import DEVICE_PATTERN
    from psfkit.io.validation import escape_line

    if not DEVICE_PATTERN.fullmatch(device):
        raise ConfigurationError(f"--device {escape_line(device)}: expected auto, cpu, cuda, "
                                 "cuda:N or mps")
    dev = torch.device(device)
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ConfigurationError(f"--device {device}: CUDA is not available on this "
                                     "machine (use --device cpu)")
        if (dev.index or 0) >= torch.cuda.device_count():
            raise ConfigurationError(f"--device {device}: this machine has "
                                     f"{torch.cuda.device_count()} CUDA device(s)")
    if dev.type == "mps" and not (getattr(torch.backends, "mps", None)
                                  and torch.backends.mps.is_available()):
        raise ConfigurationError(f"--device {device}: MPS is not available on this machine")
    return dev


def resolve_amp(amp: str | bool, device: torch.device) -> str:
    """``"off"``, ``"bf16"`` or ``"fp16"`` for ``device`` (``True``: ``"auto"``, ``False``:
    ``"off"``); :class:`ConfigurationError` for an unknown value or one the device lacks."""
    if amp is True:
        amp = "auto"
    elif amp is False or amp is None:
        amp = "off"
    if amp not in AMP_CHOICES:
        raise ConfigurationError(f"--amp must be one of {', '.join(AMP_CHOICES)}, got {amp!r}")
    cuda = device.type == "cuda"
    if amp == "auto":
        return "fp16" if cuda else "off"
    if amp == "fp16" and not cuda:
        raise ConfigurationError("fp16 autocast needs a CUDA device; use --amp bf16 on CPU")
    if amp == "bf16" and cuda and not torch.cuda.is_bf16_supported():
        raise ConfigurationError(f"{device} does not support bf16; use --amp fp16")
    if amp != "off" and device.type not in ("cuda", "cpu"):
        raise ConfigurationError(f"autocast is not supported on {device.type}")
    return amp


def autocast(amp: str, device: torch.device) -> contextlib.AbstractContextManager:
    """The autocast context of a resolved ``amp`` (a no-op for ``"off"``)."""
    if amp == "off":
        return contextlib.nullcontext()
    return torch.autocast(device.type, dtype=_DTYPES[amp])


def use_channels_last(option: bool | None, device: torch.device) -> bool:
    """``option``, or (``None``) whether channels_last is worth it on ``device``: CUDA."""
    return device.type == "cuda" if option is None else bool(option)


def convolutions_channels_last(model: nn.Module) -> int:
    """Put every 2-D convolution's weights in channels_last format; how many were converted."""
    count = 0
    for module in model.modules():
        if isinstance(module, (nn.Conv2d, nn.ConvTranspose2d)):
            module.to(memory_format=torch.channels_last)
            count += 1
    return count


def cuda_synchronize(device: torch.device) -> None:
    """Wait for ``device`` (timings; a no-op on CPU)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)
