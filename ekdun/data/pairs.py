"""A torch dataset over a pairs folder (:func:`psfkit.io.pairs.read_pairs`), and the match
between a pairs folder's pixel grid and a kernel file's sensor. The DiffuserCam Lensless
Mirflickr layout (``lensed/`` + ``diffuser/``, BGR on disk) trains as stored: its ground truth
and measurements share one orientation, and so do the reconstructions.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from ekdun.errors import InvalidInputError
from psfkit.forward.kernelfile import KernelModel
from psfkit.io.pairs import PairSet, parse_names, read_pairs
from psfkit.io.read_options import ReadOptions
from psfkit.io.validation import MIN_PAIR_SIDE
from psfkit.numerics.resample import bin_mean


def recorded_read_options(data: dict[str, Any], where: str = "checkpoint") -> ReadOptions:
    """The :class:`~psfkit.io.read_options.ReadOptions` of a checkpoint's training pairs,
    from its ``metadata["data"]`` (older checkpoints: what they record, the rest default);
    :class:`InvalidInputError` naming ``where`` for an option out of range."""
    if isinstance(data.get("read_options"), dict):
        return ReadOptions.from_json(data["read_options"], where)
    order = data.get("channel_order") if data.get("channel_order") in ("RGB", "BGR") else None
    flip = data.get("flip") if data.get("flip") in ("none", "ud", "lr", "both") else "none"
    factor = data.get("downsample")
    factor = factor if isinstance(factor, int) and 1 <= factor <= 64 else None
    return ReadOptions(channel_order=order, flip=flip, downsample=factor)


class PairsDataset(Dataset):
    """``(scene, measurement)`` pairs as ``(C, H, W)`` float32 tensors (RGB).

    Parameters
    ----------
    root : path-like or PairSet
        Pairs folder, or one already listed by :func:`psfkit.io.pairs.read_pairs` (then
        ``channel_order`` and ``recorded`` are not used).
    channel_order : {"RGB", "BGR"}, optional
        Overrides the folder's channel order.
    recorded : ReadOptions, optional
        Read options recorded with the model, for what the folder does not declare.
    preload : bool
        Read every pair once into memory.
    holdout : iterable of str
        Names (file stems) of pairs to leave out.
    only : iterable of str
        If given, keep only the pairs of these names.
    downsample : int
        Average ``downsample × downsample`` blocks (as ``psfkit fit-pairs --downsample``).

    Raises
    ------
    InvalidInputError
        An unknown held-out name, nothing left to train on, or too few pixels left a side.
    """

    def __init__(self, root: str | os.PathLike | PairSet, channel_order: str | None = None,
                 preload: bool = True, holdout: Iterable[str] = (), downsample: int = 1,
                 only: Iterable[str] = (), recorded: ReadOptions | None = None) -> None:
        self.pairs: PairSet = (root if isinstance(root, PairSet) else
                               read_pairs(root, channel_order, check_pixels=False,
                                          recorded=recorded))
        self.holdout = parse_names(holdout)
        self.indices = list(self.pairs.select(self.holdout, only))
        if int(downsample) != downsample or downsample < 1:
            raise InvalidInputError(f"downsample must be a positive integer, got {downsample}")
        self.downsample = int(downsample)
        _, h, w = self.pairs.shape
        if h // self.downsample < MIN_PAIR_SIDE or w // self.downsample < MIN_PAIR_SIDE:
            binning = (f" binned by --downsample {self.downsample} to {h // self.downsample}x"
                       f"{w // self.downsample}" if self.downsample > 1 else "")
            raise InvalidInputError(f"{self.pairs.root}: {h}x{w} px pairs{binning} leave too "
                                    f"few pixels to train on (at least {MIN_PAIR_SIDE}x"
                                    f"{MIN_PAIR_SIDE})")
        self._cache: tuple[np.ndarray, np.ndarray] | None = None
        if preload:
            pairs = [self._read(i) for i in self.indices]
            self._cache = (np.stack([p[0] for p in pairs]), np.stack([p[1] for p in pairs]))

    def _read(self, pair: int) -> tuple[np.ndarray, np.ndarray]:
        scene, measurement = self.pairs.load(pair)
        if self.downsample > 1:
            scene = bin_mean(scene, self.downsample).astype(np.float32)
            measurement = bin_mean(measurement, self.downsample).astype(np.float32)
        return scene, measurement

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """``(C, H, W)`` of every image (after binning)."""
        c, h, w = self.pairs.shape
        return int(c), int(h) // self.downsample, int(w) // self.downsample

    @property
    def names(self) -> tuple[str, ...]:
        """Names of the pairs in the dataset (held-out pairs excluded), in index order."""
        return tuple(self.pairs.names[i] for i in self.indices)

    def describe(self) -> dict[str, Any]:
        """What the dataset is, JSON-able (recorded in checkpoints)."""
        options = self.read_options
        return {"root": str(Path(self.pairs.root).resolve()), "names": list(self.names),
                "holdout": list(self.holdout), "channel_order": options.channel_order,
                "flip": options.flip, "downsample": options.downsample,
                "read_options": options.to_json(), "image_shape": list(self.image_shape)}

    @property
    def read_options(self) -> ReadOptions:
        """How the pairs are read (channel order, flip, binning, white level)."""
        return self.pairs.read_options(self.downsample)

    def __len__(self) -> int:
        return len(self.indices)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        if self._cache is not None:
            scene, measurement = self._cache[0][index], self._cache[1][index]
        else:
            scene, measurement = self._read(self.indices[index])
        return torch.from_numpy(np.array(scene)), torch.from_numpy(np.array(measurement))


def match_downsample(image_shape: tuple[int, ...], model: KernelModel,
                     requested: int | None = None, where: str = "the pairs",
                     model_name: str = "the kernel file") -> int:
    """The binning factor that brings images of ``image_shape`` onto ``model``'s sensor.

    Parameters
    ----------
    image_shape : (int, int) or (int, int, int)
        ``(H, W)`` of the stored images, or ``(C, H, W)`` (channels checked too).
    model : KernelModel
        The seed kernels.
    requested : int, optional
        The user's factor; ``None``: 1 if the sizes agree, else the kernel file's recorded one.

    Raises
    ------
    InvalidInputError
        The binned images are not the model's sensor size (the message says which factor
        would fit), or have another number of channels.
    """
    if len(image_shape) == 3 and int(image_shape[0]) != len(model.channels):
        raise InvalidInputError(f"{where} have {int(image_shape[0])} channel(s) but the model "
                                f"{model_name} has {len(model.channels)} "
                                f"({'/'.join(model.channels)})")
    h, w = int(image_shape[-2]), int(image_shape[-1])
    sensor = (int(model.sensor_shape[0]), int(model.sensor_shape[1]))
    fitted = model.data_read_options().downsample

    def fits(factor: int) -> bool:
        return (h // factor, w // factor) == sensor

    if requested is None:   # 1 if the sizes agree, else the kernel file's factor
        requested = fitted if fitted and not fits(1) and fits(fitted) else 1
    if fits(requested):
        return int(requested)
    match = next((factor for factor in range(1, 33) if fits(factor)), None)
    hint = (f"; --downsample {match} matches it" if match else
            "; fit the kernels on these images (psfkit fit-pairs, with --downsample)")
    raise InvalidInputError(
        f"{where} are {h}x{w}" + (f" (binned by {requested}: {h // requested}x{w // requested})"
                                  if requested > 1 else "")
        + f" but the model's sensor is {sensor[0]}x{sensor[1]} ({model_name}"
        + (f", fitted with --downsample {fitted}" if fitted and fitted > 1 else "") + ")"
        + hint)
