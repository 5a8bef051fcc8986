"""A torch dataset over a pairs folder (:func:`psfkit.io.pairs.read_pairs`)."""

from __future__ import annotations

import os

import numpy as np
import torch
from torch.utils.data import Dataset

from psfkit.io.pairs import PairSet, read_pairs


class PairsDataset(Dataset):
    """``(scene, measurement)`` pairs as ``(C, H, W)`` float32 tensors (RGB).

    Reads folders of ground-truth / measurement images (npy, png, tiff) including the
    DiffuserCam Lensless Mirflickr layout (``lensed/`` + ``diffuser/``, BGR on disk, read as
    RGB); see :mod:`psfkit.io.pairs` for the conventions (channel order, flip).

    Parameters
    ----------
    root : path-like
        Pairs folder.
    channel_order : {"RGB", "BGR"}, optional
        Overrides the folder's channel order.
    preload : bool
        Read every pair once into memory (small datasets).
    """

    def __init__(self, root: str | os.PathLike, channel_order: str | None = None,
                 preload: bool = True) -> None:
        self.pairs: PairSet = read_pairs(root, channel_order)
        self._cache: tuple[np.ndarray, np.ndarray] | None = (
            self.pairs.load_all() if preload else None)

    @property
    def image_shape(self) -> tuple[int, int, int]:
        """``(C, H, W)`` of every image."""
        return tuple(int(v) for v in self.pairs.shape)  # type: ignore[return-value]

    @property
    def names(self) -> tuple[str, ...]:
        return self.pairs.names

    def __len__(self) -> int:
        return len(self.pairs)

    def __getitem__(self, index: int) -> tuple[torch.Tensor, torch.Tensor]:
        if self._cache is not None:
            scene, measurement = self._cache[0][index], self._cache[1][index]
        else:
            scene, measurement = self.pairs.load(index)
        return torch.from_numpy(np.array(scene)), torch.from_numpy(np.array(measurement))
