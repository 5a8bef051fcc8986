"""Bringing a grid's PSFs and a kernel file's kernels onto one comparison grid (the kernel
file's sensor): aspect check, resampling, zero-padding of smaller kernels."""

from __future__ import annotations

import cv2
import numpy as np

from psfkit.errors import InvalidInputError
from psfkit.numerics.resample import bin_image

#: relative difference of aspect ratios (H/W) beyond which two sensor grids are not the same
ASPECT_TOLERANCE = 0.02


def check_shapes(sensor_shape: tuple[int, int], grid_shape: tuple[int, int], where: str
                 ) -> None:
    """Refuse two sensor grids whose aspect ratios differ (they cannot be the same sensor)."""
    ratio_a = sensor_shape[0] / sensor_shape[1]
    ratio_b = grid_shape[0] / grid_shape[1]
    if abs(ratio_a - ratio_b) > ASPECT_TOLERANCE * ratio_b:
        raise InvalidInputError(
            f"{where}: sensor {sensor_shape[0]}x{sensor_shape[1]} of the kernel file and PSFs "
            f"{grid_shape[0]}x{grid_shape[1]} of the grid have different aspect ratios; they "
            "cannot be the same camera at two resolutions")


def resample(images: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """Resample ``(..., H, W)`` images to ``shape``: block averages for an integer factor,
    area interpolation to shrink, cubic to enlarge (pixel values keep their density)."""
    h, w = images.shape[-2:]
    if (h, w) == tuple(shape):
        return images.astype(np.float32, copy=False)
    flat = images.reshape(-1, h, w).astype(np.float32)
    fv, fu = h / shape[0], w / shape[1]
    out = np.empty((len(flat), *shape), np.float32)
    integer = fv == fu and float(fv).is_integer() and h % shape[0] == 0 and w % shape[1] == 0
    for i, img in enumerate(flat):
        if integer:
            out[i] = bin_image(img, int(fv)) / fv**2
        else:
            interp = cv2.INTER_AREA if fv > 1 else cv2.INTER_CUBIC
            out[i] = cv2.resize(img, (shape[1], shape[0]), interpolation=interp)
    return out.reshape(*images.shape[:-2], *shape)


def pad_kernels(kernels: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """``(K, C, Hk, Wk)`` kernels zero-padded to ``shape`` keeping the origin at the centre
    (``(Hk//2, Wk//2)`` lands on ``(H//2, W//2)``)."""
    hk, wk = kernels.shape[-2:]
    h, w = shape
    if (hk, wk) == (h, w):
        return kernels
    out = np.zeros((*kernels.shape[:-2], h, w), np.float32)
    r0, c0 = h // 2 - hk // 2, w // 2 - wk // 2
    out[..., r0:r0 + hk, c0:c0 + wk] = kernels
    return out
