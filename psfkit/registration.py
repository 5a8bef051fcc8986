r"""Sub-pixel registration of PSFs and the map from field position to PSF shift.

Sign convention (``shared/design.md``): the *shift* ``s = (du, dv)`` of a PSF relative to the
reference is its displacement on the sensor, ``psf(x) ≈ g · reference(x − s)``, in sensor
pixels (``u`` = column, ``v`` = row). A source displaced by ``+x`` on the monitor gives
``du < 0``.

:func:`register_shift` is phase correlation without spectral whitening (``normalization=None``:
the 'phase' normalization amplifies noise at frequencies where a smooth caustic has no energy),
coarse to fine: an integer estimate from binned, zero-padded images (a linear correlation, so
shifts up to the image size are unambiguous: no wrap-around), then the upsampled-DFT
refinement of Guizar-Sicairos et al. on the overlapping crops, windowed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import scipy.fft as sfft
from scipy import linalg
from scipy.signal.windows import tukey
from skimage.registration import phase_cross_correlation

from psfkit.errors import InvalidInputError


def _displacement(moving: np.ndarray, reference: np.ndarray, upsample: int) -> np.ndarray:
    """``(dv, du)`` displacement of ``moving`` relative to ``reference`` (skimage returns the
    shift that registers its second argument onto its first)."""
    shift, _, _ = phase_cross_correlation(moving, reference, upsample_factor=upsample,
                                          normalization=None)
    return np.asarray(shift, dtype=np.float64)


def bin_image(image: np.ndarray, factor: int) -> np.ndarray:
    """Sum ``factor × factor`` blocks of a 2-D image (trailing rows/columns dropped)."""
    if factor == 1:
        return image
    h, w = (image.shape[0] // factor) * factor, (image.shape[1] // factor) * factor
    return image[:h, :w].reshape(h // factor, factor, w // factor, factor).sum(axis=(1, 3))


def overlap_slices(shape: tuple[int, int], shift_vu: tuple[int, int]
                   ) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Slices ``(reference_part, moving_part)`` of the region both images see when ``moving``
    is displaced by the integer ``shift_vu`` relative to ``reference``."""
    ref_sl, mov_sl = [], []
    for n, size in zip(shift_vu, shape, strict=True):
        n = int(n)
        if abs(n) >= size:
            raise InvalidInputError(f"shift {n} px leaves no overlap with a {size}-px image")
        ref_sl.append(slice(max(0, -n), size - max(0, n)))
        mov_sl.append(slice(max(0, n), size + min(0, n)))
    return (ref_sl[0], ref_sl[1]), (mov_sl[0], mov_sl[1])


def high_frequency_fraction(image: np.ndarray) -> float:
    """Fraction of an image's (non-DC) power above a quarter of the sampling frequency, i.e.
    what 2× binning would alias."""
    power = np.abs(sfft.rfft2(image - image.mean(), workers=-1)) ** 2
    gy = np.abs(np.fft.fftfreq(image.shape[0]))[:, None]
    gx = np.fft.rfftfreq(image.shape[1])[None, :]
    total = float(power.sum())
    return float(power[(gy > 0.25) | (gx > 0.25)].sum()) / total if total > 0 else 0.0


def register_shift(reference: np.ndarray, moving: np.ndarray, upsample: int = 100,
                   coarse_size: int = 256, fine_limit: int = 1024,
                   allow_binning: bool | None = None) -> tuple[float, float]:
    """Sub-pixel shift ``(du, dv)`` of ``moving`` relative to ``reference`` (2-D images).

    Parameters
    ----------
    reference, moving : numpy.ndarray
        ``(H, W)`` images of the same shape (e.g. PSF luminance).
    upsample : int
        Upsampling factor of the refinement (precision 1/upsample px).
    coarse_size : int
        Images are binned to about this size for the integer search.
    fine_limit : int
        Images whose smaller side is at least this may be refined at half resolution...
    allow_binning : bool, optional
        ...when they carry (almost) no power that 2× binning would alias: ``None`` checks the
        reference (< 1% of its power above a quarter of the sampling frequency); pass the
        answer when registering many images to one reference.

    Returns
    -------
    (float, float)
        ``(du, dv)`` in pixels.
    """
    if reference.shape != moving.shape or reference.ndim != 2:
        raise InvalidInputError(f"register_shift needs two 2-D images of one shape, got "
                                f"{reference.shape} and {moving.shape}")
    if min(reference.shape) >= fine_limit and (
            allow_binning if allow_binning is not None
            else high_frequency_fraction(reference) < 0.01):
        # Refine on 2× binned images: a quarter of the work, the same errors on
        # full-resolution virtual-bench grids (the step, 2/upsample full-size px, adds
        # ≈ 0.006 px RMS for upsample = 100). Binned pixel centres sit at x_b = (x − 0.5)/2,
        # so shifts scale by exactly 2.
        du, dv = register_shift(bin_image(reference, 2), bin_image(moving, 2),
                                upsample=upsample, coarse_size=coarse_size,
                                fine_limit=fine_limit, allow_binning=allow_binning)
        return 2.0 * du, 2.0 * dv
    h, w = reference.shape
    # unit-peak copies: skimage multiplies spectral amplitudes, which overflows float32 otherwise
    reference = reference / max(float(np.max(np.abs(reference))), 1e-30)
    moving = moving / max(float(np.max(np.abs(moving))), 1e-30)
    factor = max(1, math.ceil(max(h, w) / coarse_size))
    rb, mb = bin_image(reference, factor), bin_image(moving, factor)
    canvas = np.zeros((2, 2 * rb.shape[0], 2 * rb.shape[1]), dtype=np.float64)
    canvas[0, :rb.shape[0], :rb.shape[1]] = rb
    canvas[1, :mb.shape[0], :mb.shape[1]] = mb
    estimate = _displacement(canvas[1], canvas[0], upsample=8) * factor
    for _ in range(3):
        integer = np.round(estimate).astype(int)
        ref_sl, mov_sl = overlap_slices((h, w), tuple(integer))
        ref_crop, mov_crop = reference[ref_sl], moving[mov_sl]
        window = (tukey(ref_crop.shape[0], 0.25)[:, None] * tukey(ref_crop.shape[1], 0.25)[None])
        # zero-fill the windowed crops to FFT-friendly sizes (harmless: the window is 0 there)
        fast = tuple(sfft.next_fast_len(n) for n in ref_crop.shape)
        pads = [(0, f - n) for f, n in zip(fast, ref_crop.shape, strict=True)]
        residual = _displacement(np.pad(mov_crop * window, pads),
                                 np.pad(ref_crop * window, pads), upsample)
        estimate = integer + residual
        if np.all(np.abs(residual) <= 1.0):
            break
    return float(estimate[1]), float(estimate[0])


def shift_image(image: np.ndarray, shift: tuple[float, float], margin: int = 8
                ) -> tuple[np.ndarray, np.ndarray]:
    """Undo a displacement: ``aligned(x) = image(x + s)`` for ``s = (du, dv)``.

    The integer part moves the array; the sub-pixel part is an exact Fourier phase ramp on a
    zero-padded copy (no interpolation blur, no wrap-around).

    Parameters
    ----------
    image : numpy.ndarray
        ``(H, W)`` or ``(C, H, W)``.
    shift : (float, float)
        ``(du, dv)`` displacement of ``image`` relative to the frame to align to.

    Returns
    -------
    aligned : numpy.ndarray
        Same shape and dtype as ``image``; zero where ``x + s`` is outside the image.
    valid : numpy.ndarray
        ``(H, W)`` bool, pixels whose source ``x + s`` lies inside the original image (and,
        after a sub-pixel shift, 2 px away from the data's edges).
    """
    du, dv = shift
    nv, nu = int(np.round(dv)), int(np.round(du))
    rv, ru = dv - nv, du - nu
    squeeze = image.ndim == 2
    stack = image[None] if squeeze else image
    h, w = stack.shape[-2:]
    moved = np.zeros_like(stack)
    # aligned_int(x) = image(x + n): destination rows [max(0,-n), h - max(0,n))
    (dst_v, dst_u), (src_v, src_u) = overlap_slices((h, w), (nv, nu))
    moved[:, dst_v, dst_u] = stack[:, src_v, src_u]
    valid = np.zeros((h, w), dtype=bool)
    if ru or rv:  # the Fourier ramp rings within a pixel or two of the data's edges
        valid[dst_v.start + 2:dst_v.stop - 2, dst_u.start + 2:dst_u.stop - 2] = True
    else:
        valid[dst_v, dst_u] = True
    if ru or rv:
        # zero margin against wrap-around, grown to FFT-friendly sizes
        pad_v = sfft.next_fast_len(h + 2 * margin, real=True) - h - margin
        pad_u = sfft.next_fast_len(w + 2 * margin, real=True) - w - margin
        padded = np.pad(moved, ((0, 0), (margin, pad_v), (margin, pad_u)))
        spec = sfft.rfft2(padded, axes=(-2, -1), workers=-1)
        # separable phase ramp, in the spectrum's own precision (no complex128 upcast)
        ramp_v = np.exp(2j * np.pi * np.fft.fftfreq(padded.shape[-2]) * rv).astype(spec.dtype)
        ramp_u = np.exp(2j * np.pi * np.fft.rfftfreq(padded.shape[-1]) * ru).astype(spec.dtype)
        spec *= ramp_v[:, None]
        spec *= ramp_u[None, :]
        moved = sfft.irfft2(spec, s=padded.shape[-2:], axes=(-2, -1), workers=-1)[
            :, margin:margin + h, margin:margin + w].astype(stack.dtype, copy=False)
    return (moved[0] if squeeze else moved), valid


def normalized_cross_correlation(a: np.ndarray, b: np.ndarray, mask: np.ndarray) -> float:
    """Pearson correlation of two images over ``mask`` (1 for identical patterns)."""
    x = a[mask].astype(np.float64)
    y = b[mask].astype(np.float64)
    x -= x.mean()
    y -= y.mean()
    denom = np.sqrt(np.sum(x * x) * np.sum(y * y))
    return float(np.sum(x * y) / denom) if denom > 0 else 0.0


@dataclass(frozen=True)
class ShiftMapFit:
    """Affine fit ``shift = A · p + t`` of PSF shifts against field positions ``p``.

    ``A`` is decomposed as ``R(rotation) · P`` (polar decomposition, ``P`` symmetric): a
    shift-invariant lensless camera has ``A ≈ −m·I`` (an inverted image, rotation ≈ 180°) with
    magnification ``m``. ``residuals`` (``(N, M, 2)``, px) are the distortion the affine map
    does not explain.
    """

    matrix: np.ndarray
    offset: np.ndarray
    field_units: str
    rotation_deg: float
    magnification_u: float
    magnification_v: float
    shear: float
    mirrored: bool
    residuals: np.ndarray = field(repr=False)

    @property
    def magnification(self) -> float:
        """Mean magnification ``sqrt(det P)`` (sensor px per field unit)."""
        return float(np.sqrt(max(self.magnification_u * self.magnification_v - self.shear**2,
                                 0.0)))

    @property
    def rms_residual(self) -> float:
        return float(np.sqrt(np.mean(np.sum(self.residuals**2, axis=-1))))

    def to_dict(self) -> dict:
        return {"field_units": self.field_units, "matrix": self.matrix.tolist(),
                "offset_px": self.offset.tolist(), "rotation_deg": self.rotation_deg,
                "magnification": self.magnification, "magnification_u": self.magnification_u,
                "magnification_v": self.magnification_v, "shear": self.shear,
                "mirrored": self.mirrored, "rms_residual_px": self.rms_residual}


def fit_shift_map(positions: np.ndarray, shifts: np.ndarray, field_units: str,
                  weights: np.ndarray | None = None) -> ShiftMapFit:
    """Least-squares affine map from field positions to PSF shifts.

    Parameters
    ----------
    positions : numpy.ndarray
        ``(N, M, 2)`` field coordinates ``(x, y)`` (monitor px, tan θ, or grid steps).
    shifts : numpy.ndarray
        ``(N, M, 2)`` measured ``(du, dv)``.
    field_units : str
        Unit of ``positions`` (recorded with the result).
    weights : numpy.ndarray, optional
        ``(N, M)`` non-negative weights (e.g. registration quality).
    """
    p = positions.reshape(-1, 2).astype(np.float64)
    s = shifts.reshape(-1, 2).astype(np.float64)
    wts = np.ones(len(p)) if weights is None else np.clip(weights.reshape(-1), 0, None)
    design = np.column_stack([p, np.ones(len(p))])
    if np.linalg.matrix_rank(design[wts > 0]) < 3:
        raise InvalidInputError("the field positions do not span two directions; cannot fit "
                                "the shift map (need a 2-D grid)")
    sw = np.sqrt(wts)[:, None]
    coef, *_ = np.linalg.lstsq(design * sw, s * sw, rcond=None)
    matrix, offset = coef[:2].T, coef[2]
    unitary, positive = linalg.polar(matrix)
    mirrored = bool(np.linalg.det(unitary) < 0)
    rotation = float(np.degrees(np.arctan2(unitary[1, 0], unitary[0, 0])))
    residuals = (s - design @ coef).reshape(shifts.shape)
    return ShiftMapFit(matrix=matrix, offset=offset, field_units=field_units,
                       rotation_deg=rotation, magnification_u=float(positive[0, 0]),
                       magnification_v=float(positive[1, 1]), shear=float(positive[0, 1]),
                       mirrored=mirrored, residuals=residuals)
