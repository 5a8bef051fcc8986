r"""Sub-pixel registration of PSFs (:class:`ShiftRegistrar`) and the sub-pixel shift that undoes
a displacement (:func:`shift_image`).

Sign convention (``docs/architecture.md``): the *shift* ``s = (du, dv)`` of a PSF is its
displacement on the sensor relative to the reference, ``psf(x) ≈ g · reference(x − s)``, in
sensor pixels (``u`` = column, ``v`` = row); a source displaced by ``+x`` gives ``du < 0``.

Registration is phase correlation without whitening (which amplifies noise where a smooth
caustic has no energy), coarse to fine: a linear correlation of binned, zero-padded images (no
wrap-around), then the cross-correlation of the windowed overlapping crops evaluated by matrix
DFTs on ever finer grids around its peak (Guizar-Sicairos, Thurman & Fienup, Opt. Lett. 33, 156
(2008), in ×10 stages).
"""

from __future__ import annotations

import numpy as np
import scipy.fft as sfft

from psfkit.errors import InvalidInputError
from psfkit.numerics.resample import bin_image, binning_factor
from psfkit.numerics.windows import tukey_window


def _cross_spectrum(moving: np.ndarray, reference: np.ndarray, shape: tuple[int, int]
                    ) -> np.ndarray:
    """Cross-correlation spectrum ``FFT(moving) · conj(FFT(reference))`` of two real images
    zero-filled to ``shape``, non-negative column frequencies only (real FFTs)."""
    return sfft.rfft2(moving, s=shape, workers=-1) * np.conj(
        sfft.rfft2(reference, s=shape, workers=-1))


def _correlation_at(spectrum: np.ndarray, rows: np.ndarray, cols: np.ndarray,
                    width: int | None = None) -> np.ndarray:
    """Cross-correlation at the (sub-pixel) displacements ``rows × cols`` by a separable matrix
    DFT of its ``spectrum`` (real part).

    ``width``: the full number of columns when ``spectrum`` holds only the non-negative column
    frequencies (:func:`_cross_spectrum`). Each negative column is the conjugate of its partner
    at the negated row frequency, the same row except the Nyquist row of an even height, which
    a rank-one update corrects: the values equal those of the full spectrum up to rounding.
    """
    h, w = spectrum.shape
    e_v = np.exp(2j * np.pi * np.outer(rows, np.fft.fftfreq(h)))
    if width is None or width == w:
        e_u = np.exp(2j * np.pi * np.outer(np.fft.fftfreq(w), cols))
        return (e_v @ spectrum @ e_u).real
    e_u = np.exp(2j * np.pi * np.outer(np.fft.fftfreq(width)[:w], cols))
    if width % 2 == 0:                  # the Nyquist column (frequency −½) has no partner
        e_u[-1] = np.exp(-1j * np.pi * cols)
    direct = e_v @ spectrum                                     # (rows, w)
    partner = direct
    if h % 2 == 0:
        nyquist = e_v[:, h // 2]
        partner = direct + np.outer(np.conj(nyquist) - nyquist, spectrum[h // 2])
    inner = slice(1, w - 1 if width % 2 == 0 else w)            # columns with a partner
    return (direct @ e_u).real + (partner[:, inner] @ e_u[inner]).real


def _refine_peak(spectrum: np.ndarray, start: np.ndarray, upsample: int,
                 width: int | None = None) -> np.ndarray:
    """Maximise the cross-correlation near ``start`` (``(dv, du)``) to ``1/upsample`` px, on
    grids of ±1.5 px at 0.1 px, then of ±1.5 steps around the best point at each 10× finer step
    until the step is ``1/upsample`` (``width`` as in :func:`_correlation_at`)."""
    best = np.asarray(start, dtype=np.float64)
    radius, step = 1.5, 0.1
    while True:
        offsets = np.arange(-round(radius / step), round(radius / step) + 1) * step
        values = _correlation_at(spectrum, best[0] + offsets, best[1] + offsets, width)
        i, j = np.unravel_index(np.argmax(values), values.shape)
        best = best + np.array([offsets[i], offsets[j]])
        if step <= 1.0 / upsample + 1e-12:
            return np.round(best * upsample) / upsample
        radius, step = 1.5 * step, max(step / 10.0, 1.0 / upsample)


def _integer_peak(spectrum: np.ndarray, width: int | None = None) -> np.ndarray:
    """Integer ``(dv, du)`` of the correlation maximum, wrapped to ±half the size."""
    if width is None or width == spectrum.shape[1]:
        correlation = sfft.ifft2(spectrum, workers=-1).real
    else:
        correlation = sfft.irfft2(spectrum, s=(spectrum.shape[0], width), workers=-1)
    peak = np.array(np.unravel_index(np.argmax(correlation), correlation.shape), float)
    size = np.array(correlation.shape, float)
    peak[peak > size / 2] -= size[peak > size / 2]
    return peak


def overlap_slices(shape: tuple[int, int], shift_vu: tuple[int, int],
                   region: tuple[slice, slice] | None = None
                   ) -> tuple[tuple[slice, slice], tuple[slice, slice]]:
    """Slices ``(reference_part, moving_part)`` of what both images see when ``moving`` is
    displaced by the integer ``shift_vu`` relative to ``reference``: of that, only ``region``
    of the reference and the same region of the moving image when given (the whole overlap
    where less than 4 px of it is left)."""
    ref_sl, mov_sl = [], []
    for k, (n, size) in enumerate(zip(shift_vu, shape, strict=True)):
        n = int(n)
        if abs(n) >= size:
            raise InvalidInputError(f"shift {n} px leaves no overlap with a {size}-px image")
        lo, hi = max(0, -n), size - max(0, n)
        if region is not None:
            lo, hi = max(region[k].start, lo), min(region[k].stop, hi)
            if hi - lo < 4:
                return overlap_slices(shape, shift_vu)
        ref_sl.append(slice(lo, hi))
        mov_sl.append(slice(lo + n, hi + n))
    return (ref_sl[0], ref_sl[1]), (mov_sl[0], mov_sl[1])


def high_frequency_fraction(image: np.ndarray) -> float:
    """Fraction of an image's (non-DC) power above a quarter of the sampling frequency, i.e.
    what 2× binning would alias."""
    power = np.abs(sfft.rfft2(image - image.mean(), workers=-1)) ** 2
    gy = np.abs(np.fft.fftfreq(image.shape[0]))[:, None]
    gx = np.fft.rfftfreq(image.shape[1])[None, :]
    total = float(power.sum())
    return float(power[(gy > 0.25) | (gx > 0.25)].sum()) / total if total > 0 else 0.0


def _prepared(image: np.ndarray) -> np.ndarray:
    # A constant background (an unsubtracted black level) would dominate an unwhitened
    # correlation and pin it at zero shift: remove the median; unit peak for the FFTs.
    # (in place on one float64 copy: the same values as the expression form, without its
    # three full-size temporaries)
    out = image.astype(np.float64)
    out -= np.median(image[::4, ::4])
    out /= max(float(out.max()), -float(out.min()), 1e-30)
    return out


def _prepared_binned(image: np.ndarray, factor: int) -> np.ndarray:
    """``bin_image(_prepared(image), factor)`` up to rounding (~1e-16), without the
    full-resolution float64 copy (the full-resolution median and scale applied to the sums)."""
    median = float(np.median(image[::4, ::4]))
    scale = max(float(image.max()) - median, median - float(image.min()), 1e-30)
    out = bin_image(image, factor, dtype=np.float64)
    out -= factor**2 * median
    out /= scale
    return out


class ShiftRegistrar:
    """Sub-pixel registration of many images to one reference (module docstring).

    Parameters
    ----------
    reference : numpy.ndarray
        ``(H, W)``, e.g. the centre PSF's luminance.
    upsample : int
        Precision ``1/upsample`` px.
    coarse_size : int
        Size the images are binned to for the coarse search.
    fine_limit, allow_binning : int, bool or None
        Images of at least ``fine_limit`` px a side are refined at half resolution when they
        carry (almost) no power that 2× binning would alias (``None``: < 1% in the reference).
    region : (slice, slice), optional
        Where the reference's light is (:func:`psf_region`): the refinement correlates this
        region with the same region of the moving image displaced by the coarse estimate, at
        full resolution (a compact PSF: the numbers of a cut-out, cheaply); ``None``: the
        whole overlap.
    """

    def __init__(self, reference: np.ndarray, upsample: int = 100, coarse_size: int = 256,
                 fine_limit: int = 1024, allow_binning: bool | None = None,
                 region: tuple[slice, slice] | None = None) -> None:
        if reference.ndim != 2:
            raise InvalidInputError(f"registration needs a 2-D reference, got {reference.shape}")
        self.shape = reference.shape
        self.upsample = upsample
        self.region = region
        reference = _prepared(reference)
        binning = region is None and min(self.shape) >= fine_limit and (
            allow_binning if allow_binning is not None
            else high_frequency_fraction(reference) < 0.01)
        # Refining on 2× binned images costs a quarter and gives the same errors on
        # full-resolution bench grids. Binned pixel centres sit at x_b = (x − 0.5)/2, so
        # shifts scale by exactly 2.
        self.fine_factor = 2 if binning else 1
        self.fine_reference = bin_image(reference, self.fine_factor)
        self.coarse_factor = binning_factor(self.fine_reference.shape, coarse_size)
        coarse = bin_image(self.fine_reference, self.coarse_factor)
        # zero-filled to twice the size: a linear correlation, no wrap-around
        self._coarse_canvas = (2 * coarse.shape[0], 2 * coarse.shape[1])
        self._coarse_reference = np.conj(sfft.fft2(coarse, s=self._coarse_canvas, workers=-1))

    def register(self, moving: np.ndarray) -> tuple[float, float]:
        """Shift ``(du, dv)`` of ``moving`` relative to the reference, in pixels."""
        if moving.shape != self.shape:
            raise InvalidInputError(f"cannot register a {moving.shape} image to a "
                                    f"{self.shape} reference")
        fine = _prepared(moving) if self.fine_factor == 1 else \
            _prepared_binned(moving, self.fine_factor)
        coarse = bin_image(fine, self.coarse_factor)
        spectrum = sfft.fft2(coarse, s=self._coarse_canvas, workers=-1) * self._coarse_reference
        if self.region is None:
            estimate = _refine_peak(spectrum, _integer_peak(spectrum), 10) * self.coarse_factor
        else:   # the refinement's window around the PSF finds its integer peak itself
            estimate = _integer_peak(spectrum) * self.coarse_factor
        h, w = fine.shape
        for _ in range(3):
            integer = np.round(estimate).astype(int)
            ref_sl, mov_sl = overlap_slices((h, w), tuple(integer), self.region)
            ref_crop, mov_crop = self.fine_reference[ref_sl], fine[mov_sl]
            window = tukey_window(ref_crop.shape[0], 0.25)[:, None] \
                * tukey_window(ref_crop.shape[1], 0.25)[None]
            # zero-fill the windowed crops to FFT-friendly sizes (harmless: the window is 0
            # there)
            fast = tuple(sfft.next_fast_len(n) for n in ref_crop.shape)
            spectrum = _cross_spectrum(mov_crop * window, ref_crop * window, fast)
            residual = _refine_peak(spectrum, _integer_peak(spectrum, fast[1]),
                                    self.upsample * self.fine_factor, fast[1])
            estimate = integer + residual
            if np.all(np.abs(residual) <= 1.0):
                break
        return (float(estimate[1] * self.fine_factor), float(estimate[0] * self.fine_factor))


def psf_region(support: np.ndarray) -> tuple[slice, slice] | None:
    """:class:`ShiftRegistrar`'s ``region``: the bounding box of a PSF's ``(H, W)`` bool support
    grown by half its size and 8 px a side (clear of the Tukey taper), clipped to the frame;
    ``None`` when that is the whole frame (a caustic)."""
    rows, cols = np.flatnonzero(support.any(axis=1)), np.flatnonzero(support.any(axis=0))
    if len(rows) == 0:
        return None
    h, w = support.shape
    slices = []
    for lo, hi, size in ((rows[0], rows[-1] + 1, h), (cols[0], cols[-1] + 1, w)):
        grow = (hi - lo) // 2 + 8
        slices.append(slice(max(0, int(lo) - grow), min(size, int(hi) + grow)))
    whole = (slices[0].stop - slices[0].start, slices[1].stop - slices[1].start) == (h, w)
    return None if whole else (slices[0], slices[1])


def register_shift(reference: np.ndarray, moving: np.ndarray, upsample: int = 100,
                   coarse_size: int = 256, fine_limit: int = 1024,
                   allow_binning: bool | None = None) -> tuple[float, float]:
    """Sub-pixel shift ``(du, dv)`` of ``moving`` relative to ``reference`` (2-D images): a
    one-off :class:`ShiftRegistrar` (make one to register many images to one reference)."""
    return ShiftRegistrar(reference, upsample, coarse_size, fine_limit,
                          allow_binning).register(moving)


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
        ``(du, dv)`` of ``image`` relative to the frame to align to.

    Returns
    -------
    aligned : numpy.ndarray
        Same shape and dtype; zero where ``x + s`` is outside the image.
    valid : numpy.ndarray
        ``(H, W)`` bool: ``x + s`` inside the image (and 2 px from its edges after a
        sub-pixel shift).
    """
    du, dv = shift
    nv, nu = int(np.round(dv)), int(np.round(du))
    rv, ru = dv - nv, du - nu
    squeeze = image.ndim == 2
    stack = image[None] if squeeze else image
    h, w = stack.shape[-2:]
    # aligned_int(x) = image(x + n): destination rows [max(0,-n), h - max(0,n))
    (dst_v, dst_u), (src_v, src_u) = overlap_slices((h, w), (nv, nu))
    valid = np.zeros((h, w), dtype=bool)
    if not (ru or rv):
        valid[dst_v, dst_u] = True
        moved = np.zeros_like(stack)
        moved[:, dst_v, dst_u] = stack[:, src_v, src_u]
        return (moved[0] if squeeze else moved), valid
    # the Fourier ramp rings within a pixel or two of the data's edges
    valid[dst_v.start + 2:dst_v.stop - 2, dst_u.start + 2:dst_u.stop - 2] = True
    # zero margin against wrap-around, grown to FFT-friendly sizes; the integer move is
    # written straight into the padded canvas (one copy of the image, not three)
    size_v = sfft.next_fast_len(h + 2 * margin, real=True)
    size_u = sfft.next_fast_len(w + 2 * margin, real=True)
    padded = np.zeros((stack.shape[0], size_v, size_u), dtype=stack.dtype)
    padded[:, margin + dst_v.start:margin + dst_v.stop,
           margin + dst_u.start:margin + dst_u.stop] = stack[:, src_v, src_u]
    spec = sfft.rfft2(padded, axes=(-2, -1), workers=-1, overwrite_x=True)
    del padded
    # separable phase ramp, in the spectrum's own precision (no complex128 upcast)
    ramp_v = np.exp(2j * np.pi * np.fft.fftfreq(size_v) * rv).astype(spec.dtype)
    ramp_u = np.exp(2j * np.pi * np.fft.rfftfreq(size_u) * ru).astype(spec.dtype)
    spec *= ramp_v[:, None]
    spec *= ramp_u[None, :]
    # the inverse as its two 1-D passes: the same transform, 25 % faster here than scipy's
    # irfft2 (full resolution, 3 channels)
    spec = sfft.ifft(spec, axis=-2, workers=-1, overwrite_x=True)
    moved = sfft.irfft(spec, n=size_u, axis=-1, workers=-1,
                       overwrite_x=True)[:, margin:margin + h, margin:margin + w]
    moved = moved.astype(stack.dtype, copy=False)
    return (moved[0] if squeeze else moved), valid


def normalized_cross_correlation(a: np.ndarray, b: np.ndarray, mask: np.ndarray,
                                 degenerate: float = 0.0, min_values: int = 1) -> float:
    """Pearson correlation of ``a`` and ``b`` (``(..., H, W)``) over the ``(H, W)`` bool
    ``mask``, all leading components pooled (1 for identical patterns); ``degenerate`` when
    either is constant there or fewer than ``min_values`` values are compared."""
    x = a[..., mask].astype(np.float64).ravel()
    y = b[..., mask].astype(np.float64).ravel()
    if x.size < min_values:
        return degenerate
    x -= x.mean()
    y -= y.mean()
    denom = float(np.sqrt(np.sum(x * x) * np.sum(y * y)))
    return float(np.sum(x * y) / denom) if denom > 0 else degenerate
