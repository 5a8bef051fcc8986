"""A noise-free PSF on a block of sensor pixels (:class:`PsfPatch`): moving it by a sub-pixel
shift and pasting it into a sensor frame."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft as sfft


@dataclass(frozen=True)
class PsfPatch:
    """A noise-free PSF ``image`` ``(C, h, w)`` whose top-left pixel is at sensor pixel ``offset``
    ``(v0, u0)`` (may lie outside the sensor); ``shift_px`` ``(du, dv)`` the exact chief-ray shift.
    """

    image: np.ndarray
    offset: tuple[int, int]
    shift_px: tuple[float, float]


def translate_pixels(image: np.ndarray, shift: tuple[float, float]) -> np.ndarray:
    """``(C, h, w)`` image moved by the sub-pixel ``shift`` ``(du, dv)`` with a Fourier phase
    ramp."""
    du, dv = shift
    ramp = np.exp(-2j * np.pi * (np.fft.fftfreq(image.shape[-2])[:, None] * dv
                                 + np.fft.rfftfreq(image.shape[-1])[None, :] * du))
    moved = sfft.irfft2(sfft.rfft2(image, axes=(-2, -1)) * ramp, s=image.shape[-2:],
                        axes=(-2, -1))
    return moved.astype(image.dtype, copy=False)


def place_patch(patch: PsfPatch, sensor_shape: tuple[int, int]) -> np.ndarray:
    """Paste a :class:`PsfPatch` into a zero ``(C, H, W)`` float32 sensor frame (cropping)."""
    c, h, w = patch.image.shape
    out = np.zeros((c, *sensor_shape), dtype=np.float32)
    v0, u0 = patch.offset
    sv0, su0 = max(v0, 0), max(u0, 0)
    sv1, su1 = min(v0 + h, sensor_shape[0]), min(u0 + w, sensor_shape[1])
    if sv1 > sv0 and su1 > su0:
        out[:, sv0:sv1, su0:su1] = patch.image[:, sv0 - v0:sv1 - v0, su0 - u0:su1 - u0]
    return out
