"""Reconstruct measurements with a trained checkpoint (``ekdun reconstruct``)."""

from __future__ import annotations

import os
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

from ekdun import device as acc
from ekdun.data.pairs import recorded_read_options
from ekdun.errors import InvalidInputError, TensorShapeError
from ekdun.nets.builder import network_from_checkpoint
from ekdun.nets.checkpoint import checkpoint_sensor, load_checkpoint
from psfkit.io.atomic import atomic_directory
from psfkit.io.images import IMAGE_SUFFIXES, read_image_float, write_image
from psfkit.io.read_options import choose
from psfkit.numerics.resample import bin_mean


def measurement_files(inputs: Sequence[str | os.PathLike]) -> list[Path]:
    """Expand folders into their image files (sorted); refuse empty inputs."""
    files: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            found = sorted(f for f in p.iterdir()
                           if f.is_file() and f.suffix.lower() in IMAGE_SUFFIXES)
            if not found:
                raise InvalidInputError(f"{p}: no measurement images in this folder")
            files.extend(found)
        elif p.is_file():
            files.append(p)
        else:
            raise InvalidInputError(f"{p}: no such file or folder")
    if not files:
        raise InvalidInputError("no measurements given")
    stems = [f.stem for f in files]
    if len(set(stems)) != len(stems):
        raise InvalidInputError("two measurements share a file name; outputs would collide")
    return files


def to_preview(image: np.ndarray) -> np.ndarray:
    """8-bit preview of a ``(C, H, W)`` image in ``[0, 1]``."""
    return (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)


@torch.no_grad()
def reconstruct_files(checkpoint: str | os.PathLike, inputs: Sequence[str | os.PathLike],
                      out_dir: str | os.PathLike, channel_order: str | None = None,
                      device: str = "auto", overwrite: bool = False, amp: str = "auto",
                      downsample: int | None = None,
                      notify: Callable[[str], None] | None = None) -> list[Path]:
    """Reconstruct every measurement into ``out_dir`` (``NAME.npy`` HWC float32 RGB and an
    8-bit ``NAME.png`` preview), atomically, all inputs checked first.

    ``channel_order`` and ``downsample`` default to how the checkpoint's training pairs were
    read (also the white level); a flag that contradicts the record is applied and ``notify``
    gets a one-line notice after the work. ``amp`` (:func:`ekdun.device.resolve_amp`) runs the
    network under autocast; the outputs are float32 either way.
    """
    device = acc.resolve_device(device)
    precision = acc.resolve_amp(amp, device)
    doc = load_checkpoint(checkpoint)
    # how the training pairs were read (channel order None where not recorded)
    recorded = recorded_read_options(doc.get("metadata", {}).get("data") or {}, str(checkpoint))
    channel_order, order_notice = choose(channel_order, recorded.channel_order, "RGB",
                                         "--channel-order", str(checkpoint))
    factor, factor_notice = choose(downsample, recorded.downsample, 1, "--downsample",
                                   str(checkpoint))
    factor = int(factor)
    if factor < 1:
        raise InvalidInputError(f"downsample must be >= 1, got {factor}")
    # the inputs are checked against the checkpoint's sensor before its network is built
    channels, *sensor_hw = checkpoint_sensor(doc)
    sensor = tuple(sensor_hw)
    files = measurement_files(inputs)
    images = []
    for f in files:
        y = read_image_float(f, channel_order, recorded.white_level)
        if factor > 1:
            y = bin_mean(y, factor).astype(np.float32)
        if tuple(y.shape[-2:]) != sensor or y.shape[0] != channels:
            raise TensorShapeError(
                f"{f}: measurement is {y.shape[1]}x{y.shape[2]}x{y.shape[0]}"
                + (f" after binning by {factor}" if factor > 1 else "")
                + f" but the model expects {sensor[0]}x{sensor[1]}x{channels}")
        images.append(y)
    model, doc = network_from_checkpoint(doc, where=str(checkpoint))
    model = model.to(device).eval()
    written = []
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        for f, y in zip(files, images, strict=True):
            with acc.autocast(precision, device):
                out = model(torch.from_numpy(y)[None].to(device))
            out = out[0].float().cpu().numpy()
            write_image(tmp / f"{f.stem}.npy", out.astype(np.float32))
            write_image(tmp / f"{f.stem}.png", to_preview(out))
            written.append(Path(out_dir) / f"{f.stem}.npy")
    for text in (order_notice, factor_notice):
        if text and notify is not None:
            notify(text)
    return written
