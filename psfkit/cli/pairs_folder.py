"""Reading a pairs folder for ``psfkit fit-pairs`` and ``psfkit eval-model``: the pairs
(less the held-out ones), checked for blank images and implausible light, binned."""

from __future__ import annotations

from typing import Any

import numpy as np

from psfkit.errors import InvalidInputError
from psfkit.io import read_pairs
from psfkit.io.read_options import ReadOptions


def _refuse_blank(pairs: Any, scenes: np.ndarray, measurements: np.ndarray) -> None:
    """An all-zero scene or measurement carries no information and makes the per-pair scale
    0/0: name the file instead of reporting NaN kernels or errors later. Measurements whose
    light is out of all proportion to their scenes' would need kernels no kernel file may hold
    (``MIN_KERNEL_GAIN`` … ``MAX_KERNEL_GAIN``): the folder is named, not the model."""
    from psfkit.io.validation import MAX_KERNEL_GAIN, MIN_KERNEL_GAIN

    for stack, folder, files in ((scenes, pairs.scene_dir, pairs.scene_files),
                                 (measurements, pairs.measurement_dir, pairs.measurement_files)):
        blank = [i for i in range(len(stack)) if not np.any(stack[i])]
        if blank:
            raise InvalidInputError(f"{pairs.root / folder / files[blank[0]]}: all-zero image "
                                    "(nothing to fit or predict)")
    # a PSF's kernels sum to about the light a measurement holds per unit of scene light
    ratio = float(np.abs(measurements).sum(dtype=np.float64)
                  / np.abs(scenes).sum(dtype=np.float64))
    if not MIN_KERNEL_GAIN <= ratio <= MAX_KERNEL_GAIN:
        raise InvalidInputError(f"{pairs.root}: the measurements hold {ratio:.3g} times the "
                                "light of their scenes, beyond what kernels may sum to "
                                f"({MIN_KERNEL_GAIN:g} to {MAX_KERNEL_GAIN:g}); check the "
                                "units of the files (full scale is 1)")


def load_pairs(folder: str, factor: int, channel_order: str | None = None,
               recorded: ReadOptions | None = None, holdout: list[str] | None = None
               ) -> tuple[Any, np.ndarray, np.ndarray]:
    """The pairs of ``folder`` (less those ``holdout`` names), binned ``factor`` times."""
    from psfkit.fitting.pairs.fit import downsample_pairs

    if factor < 1:
        raise InvalidInputError(f"--downsample must be >= 1, got {factor}")
    # load_all() checks every pair
    pairs = read_pairs(folder, channel_order, check_pixels=False, recorded=recorded)
    if holdout:
        pairs = pairs.subset(pairs.select(holdout))
    scenes, measurements = pairs.load_all()
    _refuse_blank(pairs, scenes, measurements)
    scenes, measurements = downsample_pairs(scenes, measurements, factor, str(folder))
    return pairs, scenes, measurements
