r"""Eigen-kernel fits of a registered PSF grid (paper, Eq. 7), in closed form.

Model. The PSF of the point source at grid position ``p``, whose image is displaced by ``s_p``
relative to the centre PSF, is written with the weight basis of :mod:`psfkit.forward.weights`

- *sensor-side* weights (Eq. 7 as written: the weights are functions of the sensor pixel)
  :math:`h_p(u) = \sum_k W_k(u)\,K_k(u - s_p)`;
- *source-side* weights (functions of the source position)
  :math:`h_p(u) = \sum_k W_k(s_p)\,K_k(u - s_p)`.

In the frame of the centre PSF (``v = u − s_p``, where the aligned PSFs of
:mod:`psfkit.calibration.alignment` live) both become, at every kernel pixel ``v`` separately, a
linear
model in the K kernel values with design vector :math:`w_p(v) = W(v + s_p)` (sensor) or
:math:`W(s_p)` (source). The least-squares kernels therefore solve a K × K system per pixel,
:math:`\big(\sum_p m_p w_p w_p^\top + \lambda R\big) K(v) = \sum_p m_p w_p a_p(v)` (``m_p`` the
valid-pixel mask), accumulated one PSF at a time and solved for all pixels at once. The small
ridge ``λR`` pulls the correction kernels towards the base kernel
(:math:`R = \sum_{k\ge1}(e_k - e_0)(e_k - e_0)^\top`) where the data do not constrain them.
Both conventions are linear with exact adjoints in :mod:`ekdun.physics`.
"""

from __future__ import annotations

import math
import os
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from typing import Any

import numpy as np

from psfkit.calibration.alignment import AlignedPsf
from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.fitting.verdict import HeldOutErrors
from psfkit.forward.geometry import kernel_origin
from psfkit.forward.kernelfile import CONVENTIONS
from psfkit.forward.weights import WeightBasis, get_basis
from psfkit.numerics.resample import bin_image, binning_factor
from psfkit.numerics.significance import Estimate, checked, undetermined

BLOCK_ELEMENTS = 16384      # pixels per block of rows in NormalEquations.add (cache-sized)
SOLVE_BLOCK = 65536         # pixels per block of NormalEquations.solve
#: Default ridge ``λ`` (relative to the mean diagonal of each pixel's normalised Gram matrix).
#: Where the data do not constrain a pixel (the edges, seen by one or two PSFs) the ridge alone
#: sets its correction kernels; at 1e-9 it sat below the rounding of the sums, so a one-ulp
#: change of the PSFs moved the demo's kernels there by 15 % of their peak (issue 21,
#: ``research/golden_spread.py``). At 1e-4 that spread is 1.5e-6 of the peak, and the in-sample
#: error of the demo's fit changes by 3e-5 of itself.
DEFAULT_RIDGE = 1e-4


@dataclass(frozen=True)
class PixelFrame:
    """Where the pixels of an ``(h, w)`` grid lie in the sensor's normalized coordinates
    (``psfkit.forward.weights``), for the weights of a fit on that grid.

    The whole sensor (:meth:`of`), or a working copy cropped and binned from it
    (:meth:`crop`): a compact PSF is fitted on a crop around it instead of a whole frame
    binned until the PSF is a pixel wide, and its weights must still be those of the pixels'
    places on the sensor. All lengths are in the grid's own pixels: ``center`` ``(v_c, u_c)``
    the optical centre, ``half`` ``(H/2, W/2)`` the sensor's half size, ``origin`` the
    kernel origin (where the centre PSF's origin lies, :func:`kernel_origin` of the sensor).
    """

    shape: tuple[int, int]
    center: tuple[float, float]
    half: tuple[float, float]
    origin: tuple[float, float]

    @classmethod
    def of(cls, sensor_shape: tuple[int, int],
           optical_center: tuple[float, float] | None = None) -> PixelFrame:
        """The sensor's own pixel grid (optical centre: the middle, unless given)."""
        h, w = sensor_shape
        center = optical_center if optical_center is not None else ((h - 1) / 2, (w - 1) / 2)
        origin = kernel_origin(sensor_shape)
        return cls((h, w), (center[0], center[1]), (h / 2.0, w / 2.0),
                   (float(origin[0]), float(origin[1])))

    @classmethod
    def crop(cls, sensor_shape: tuple[int, int], corner: tuple[int, int], factor: int,
             shape: tuple[int, int]) -> PixelFrame:
        """An ``shape`` grid of ``factor × factor`` blocks whose first block's corner is at
        sensor pixel ``corner`` ``(row, col)`` (sensor centre as the optical centre)."""
        h, w = sensor_shape
        offset = (factor - 1) / 2.0          # a block's centre from its corner, sensor px

        def local(v: float, axis: int) -> float:
            return (v - corner[axis] - offset) / factor

        origin = kernel_origin(sensor_shape)
        return cls((int(shape[0]), int(shape[1])),
                   (local((h - 1) / 2, 0), local((w - 1) / 2, 1)),
                   (h / 2.0 / factor, w / 2.0 / factor),
                   (local(origin[0], 0), local(origin[1], 1)))

    def axes(self, shift: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        """Normalized coordinates ``u_n`` ``(1, w)`` and ``v_n`` ``(h, 1)`` of the pixels
        plus ``shift`` (grid px): where the sensor-side weights of a PSF displaced by
        ``shift`` are read in its aligned frame."""
        h, w = self.shape
        (v_c, u_c), (hh, hw) = self.center, self.half
        du, dv = shift
        return (((np.arange(w) - u_c) / hw)[None, :] + du / hw,
                ((np.arange(h) - v_c) / hh)[:, None] + dv / hh)

    def source(self, shift: tuple[float, float]) -> tuple[float, float]:
        """Normalized ``(u_n, v_n)`` of the source whose PSF origin lands at the kernel
        origin displaced by ``shift`` (grid px)."""
        (v_c, u_c), (hh, hw), (o_v, o_u) = self.center, self.half, self.origin
        du, dv = shift
        return (o_u + du - u_c) / hw, (o_v + dv - v_c) / hh


def position_weights(basis: WeightBasis, sensor_shape: tuple[int, int],
                     shift: tuple[float, float], convention: str,
                     optical_center: tuple[float, float] | None = None,
                     frame: PixelFrame | None = None) -> np.ndarray:
    """Weights of the K kernels for the PSF displaced by ``shift``, in its aligned frame.

    Returns ``(K, H, W)`` (sensor-side: :math:`W_k(v + s)`) or ``(K, 1, 1)`` (source-side:
    :math:`W_k(s)`, the source at the sensor pixel where its PSF origin lands). ``frame``
    places a cropped or binned grid on the sensor (default: ``sensor_shape`` is the sensor).
    """
    frame = frame if frame is not None else PixelFrame.of(sensor_shape, optical_center)
    if convention == "sensor":
        u_n, v_n = frame.axes(shift)
        return basis.evaluate(u_n, v_n)
    if convention == "source":
        u_s, v_s = frame.source(shift)
        return basis.evaluate(np.array([[u_s]]), np.array([[v_s]]))
    raise ConfigurationError(f"convention must be one of {CONVENTIONS}, got {convention!r}")


def _difference_prior(n_kernels: int) -> np.ndarray:
    r = np.zeros((n_kernels, n_kernels))
    for k in range(1, n_kernels):
        e = np.zeros(n_kernels)
        e[0], e[k] = -1.0, 1.0
        r += np.outer(e, e)
    return r


class NormalEquations:
    """Per-pixel normal equations of an eigen-kernel fit, accumulated one PSF at a time.

    Two accumulation paths give the same sums (to rounding):

    - a PSF whose valid mask is a rectangle (the common case: the sensor's overlap after the
      shift, nothing saturated) adds to the right-hand sides only the weighted image inside
      the rectangle. Every weight of :mod:`psfkit.forward.weights` is a sum of products
      ``f(u)·g(v)``, so that PSF's Gram term ``m·w_i·w_j`` is a sum of outer products of
      row and column vectors; these are kept (a few vectors per PSF) and summed for all PSFs
      at once as one matrix product per Gram entry when the equations are read. Because the
      weights sum to 1, the base kernel's right-hand side is the masked image minus the
      correction terms' ones, and is formed then;
    - any other mask goes through the per-pixel products (:meth:`_add_masked`).

    Parameters
    ----------
    basis : WeightBasis
    convention : {"sensor", "source"}
    image_shape : (int, int, int)
        ``(C, H, W)`` of the PSFs (H, W is also the sensor grid of the weights).
    optical_center : (float, float), optional
    frame : PixelFrame, optional
        Where the ``(H, W)`` pixels lie on the sensor (a cropped working copy); default: they
        are the sensor (with ``optical_center``).
    """

    def __init__(self, basis: WeightBasis, convention: str, image_shape: tuple[int, int, int],
                 optical_center: tuple[float, float] | None = None,
                 frame: PixelFrame | None = None) -> None:
        if convention not in CONVENTIONS:
            raise ConfigurationError(f"convention must be one of {CONVENTIONS}, "
                                     f"got {convention!r}")
        self.basis, self.convention = basis, convention
        self.channels, self.h, self.w = image_shape
        self.optical_center = optical_center
        self.frame = frame if frame is not None else PixelFrame.of((self.h, self.w),
                                                                   optical_center)
        self._iu = np.triu_indices(basis.n_kernels)
        # per-pixel sums (upper triangle of the Gram matrices; right-hand sides), allocated
        # when first needed, in the first image's precision
        self._gram: np.ndarray | None = None
        self._rhs: np.ndarray | None = None
        # rectangle path: [Σ m·a, Σ m·w_j·a (j ≥ 1)] per channel, and per PSF and kernel the
        # masked row and column factors ``(S, H)``, ``(S, W)`` of its weight
        self._rect_rhs: np.ndarray | None = None
        self._factors: list[list[tuple[np.ndarray, np.ndarray]]] = []
        self.count = 0

    @property
    def gram(self) -> np.ndarray:
        """``(K(K+1)/2, H, W)`` upper triangle of the per-pixel Gram matrices ``Σ m w wᵀ``."""
        self._materialize()
        assert self._gram is not None
        return self._gram

    @property
    def rhs(self) -> np.ndarray:
        """``(C, K, H, W)`` per-pixel right-hand sides ``Σ m w a``."""
        self._materialize()
        assert self._rhs is not None
        return self._rhs

    def add(self, image: np.ndarray, valid: np.ndarray, shift: tuple[float, float]) -> None:
        """Add one aligned ``(C, H, W)`` PSF with its ``(H, W)`` valid mask and shift.

        Products are formed and accumulated in the image's own precision: float32 for grid
        data (half the memory traffic of float64; its rounding, ~1e-7 per PSF, is far below
        any sensor's noise), float64 for float64 input (the exact-recovery tests). The Gram
        sums of the rectangle path are float64 matrix products.
        """
        dtype = np.dtype(image.dtype if np.issubdtype(image.dtype, np.floating)
                         else np.float64)
        rect = _rectangle(valid)
        if rect is None:
            self._add_masked(image, valid, shift, dtype)
        else:
            self._add_rectangle(image, rect, shift, dtype)
        self.count += 1

    def _axis_weights(self, shift: tuple[float, float]
                      ) -> list[list[tuple[np.ndarray | float | None, np.ndarray | None]]]:
        """The weights of the PSF displaced by ``shift`` as sums of ``row(v) ⊗ col(u)``
        products, per kernel (``None``: a factor of 1)."""
        if self.convention == "source":
            w = position_weights(self.basis, (self.h, self.w), shift, "source",
                                 frame=self.frame)[:, 0, 0]
            return [[(float(wk), None)] for wk in w]
        u_n, v_n = self.frame.axes(shift)
        u_n, v_n = u_n[0], v_n[:, 0]
        terms = [term.factors(u_n, v_n) for term in self.basis.terms]
        # base weight 1 − Σ φ_j: the terms of u alone merged into one column factor, those of
        # v alone into one row factor, products of both kept apart
        col = np.ones(self.w)
        row = np.zeros(self.h)
        base: list[tuple[np.ndarray | float | None, np.ndarray | None]] = []
        for fu, fv in terms:
            if fv is None:
                col = col - (fu if fu is not None else 1.0)
            elif fu is None:
                row = row - fv
            else:
                base.append((-fv, fu))
        base.insert(0, (None, col))
        if np.any(row):
            base.insert(1, (row, None))
        return [base] + [[(fv, fu)] for fu, fv in terms]

    def _add_rectangle(self, image: np.ndarray, rect: tuple[slice, slice],
                       shift: tuple[float, float], dtype: np.dtype) -> None:
        if self._rect_rhs is None:
            self._rect_rhs = np.zeros((self.channels, self.basis.n_kernels, self.h, self.w),
                                      dtype)
        rows, cols = rect
        weights = self._axis_weights(shift)
        # Gram factors: full-length vectors, zero outside the rectangle
        row_mask = np.zeros(self.h)
        row_mask[rows] = 1.0
        col_mask = np.zeros(self.w)
        col_mask[cols] = 1.0
        factors = []
        for terms in weights:
            r = np.stack([row_mask * (1.0 if fv is None else fv) for fv, _ in terms])
            c = np.stack([col_mask * (1.0 if fu is None else fu) for _, fu in terms])
            factors.append((r, c))
        self._factors.append(factors)
        # right-hand sides inside the rectangle, in blocks of rows that stay in the cache:
        # Σ m·a (slot 0) and Σ m·φ_j·a, each product with the row factor, then the column one
        n_rows, width = rows.stop - rows.start, cols.stop - cols.start
        scaling = []                             # per term: ((R, 1) or None, (W,) or None)
        for ((fv, fu),) in weights[1:]:
            row = None if fv is None else np.broadcast_to(
                np.asarray(fv, dtype)[rows] if np.ndim(fv) else dtype.type(fv), (n_rows,))
            scaling.append((None if row is None else row[:, None],
                            None if fu is None else fu[cols].astype(dtype)))
        block_rows = max(1, BLOCK_ELEMENTS // width)
        buffer = np.empty((block_rows, width), dtype)
        acc = self._rect_rhs
        for r0 in range(rows.start, rows.stop, block_rows):
            block = slice(r0, min(r0 + block_rows, rows.stop))
            tmp = buffer[:block.stop - r0]
            local = slice(block.start - rows.start, block.stop - rows.start)
            for c in range(self.channels):
                data = image[c, block, cols]
                acc[c, 0, block, cols] += data
                for k, (row, col) in enumerate(scaling, start=1):
                    np.multiply(data, col if row is None else row[local], out=tmp)
                    if row is not None and col is not None:
                        tmp *= col
                    acc[c, k, block, cols] += tmp

    def _add_masked(self, image: np.ndarray, valid: np.ndarray, shift: tuple[float, float],
                    dtype: np.dtype) -> None:
        """Per-pixel products over blocks of rows small enough to stay in the CPU cache
        (weights, masked products and accumulators of a block are touched once each per PSF
        instead of once per product at full size)."""
        if self._gram is None:
            k = self.basis.n_kernels
            self._gram = np.zeros((len(self._iu[0]), self.h, self.w), dtype)
            self._rhs = np.zeros((self.channels, k, self.h, self.w), dtype)
        assert self._rhs is not None
        sensor = self.convention == "sensor"
        if sensor:
            u_n, v_n = self.frame.axes(shift)
        else:
            weights = position_weights(self.basis, (self.h, self.w), shift, self.convention,
                                       frame=self.frame).astype(dtype)
        rows = max(1, BLOCK_ELEMENTS // self.w)
        product = np.empty((rows, self.w), dtype)
        for r0 in range(0, self.h, rows):
            block = slice(r0, min(r0 + rows, self.h))
            prod = product[:block.stop - r0]
            if sensor:                                   # weights of these rows only
                weights = self.basis.evaluate(u_n, v_n[block]).astype(dtype)
            mask = valid[block].astype(dtype)
            mw = weights * mask                   # (K, R, W); source-side weights broadcast
            gram = self._gram[:, block]
            for index, (i, j) in enumerate(zip(*self._iu, strict=True)):
                np.multiply(mw[i], weights[j], out=prod)
                gram[index] += prod
            rhs = self._rhs[:, :, block]
            for c in range(self.channels):
                masked = image[c, block] * mask
                for k in range(self.basis.n_kernels):
                    np.multiply(weights[k], masked, out=prod)
                    rhs[c, k] += prod

    def _materialize(self) -> None:
        """Fold the rectangle path's factors and sums into the per-pixel arrays."""
        if self._factors:
            gram = np.zeros((len(self._iu[0]), self.h, self.w)) if self._gram is None \
                else self._gram.astype(np.float64)
            for index, (i, j) in enumerate(zip(*self._iu, strict=True)):
                left = np.concatenate([(f[i][0][:, None] * f[j][0][None]).reshape(-1, self.h)
                                       for f in self._factors])
                right = np.concatenate([(f[i][1][:, None] * f[j][1][None]).reshape(-1, self.w)
                                        for f in self._factors])
                gram[index] += left.T @ right
            self._gram = gram
            self._factors = []
            assert self._rect_rhs is not None
            sums = self._rect_rhs
            base = sums[:, 0].astype(np.float64) - sums[:, 1:].astype(np.float64).sum(axis=1)
            sums[:, 0] = base
            if self._rhs is None:
                self._rhs = sums
            else:
                self._rhs = self._rhs + sums
            self._rect_rhs = None
        if self._gram is None:      # nothing added
            k = self.basis.n_kernels
            self._gram = np.zeros((len(self._iu[0]), self.h, self.w))
            self._rhs = np.zeros((self.channels, k, self.h, self.w))

    def _from_arrays(self, gram: np.ndarray, rhs: np.ndarray, count: int) -> NormalEquations:
        out = NormalEquations(self.basis, self.convention, (self.channels, self.h, self.w),
                              self.optical_center, self.frame)
        out._gram, out._rhs, out.count = gram, rhs, count
        return out

    def minus(self, other: NormalEquations) -> NormalEquations:
        """The equations of this set of PSFs without those of ``other`` (a subset)."""
        return self._from_arrays(self.gram - other.gram, self.rhs - other.rhs,
                                 self.count - other.count)

    def __iadd__(self, other: NormalEquations) -> NormalEquations:
        self._gram = self.gram + other.gram     # may change precision: not in place
        self._rhs = self.rhs + other.rhs
        self.count += other.count
        return self

    def solve(self, ridge: float = DEFAULT_RIDGE, conditioning: bool = True
              ) -> tuple[np.ndarray, np.ndarray | None]:
        """Kernels ``(K, C, H, W)`` and (if ``conditioning``) the per-pixel smallest
        eigenvalue of the normalized Gram matrix ``(H, W)`` (0 where a kernel pixel is not
        constrained by the data)."""
        k = self.basis.n_kernels
        n = self.h * self.w
        gram = self.gram.reshape(len(self._iu[0]), n)
        rhs = self.rhs.reshape(self.channels, k, n)
        prior = (ridge * _difference_prior(k) + 1e-12 * np.eye(k))[:, :, None]
        solution = np.empty((k, self.channels, n))
        smallest = np.empty(n) if conditioning else None

        def solve_pixels(block: slice) -> None:
            # every operation is per pixel: blocks of pixels give the same numbers as one
            # pass over the image, in cache-sized pieces, on two threads
            flat = gram[:, block].astype(np.float64)
            scale = np.zeros(flat.shape[1])
            for index, (i, j) in enumerate(zip(*self._iu, strict=True)):
                if i == j:
                    scale += flat[index]
            scale = np.maximum(scale / k, 1e-300)
            # (K, K, n) systems, pixels last (contiguous vector operations over the pixels)
            system = np.empty((k, k, flat.shape[1]))
            for index, (i, j) in enumerate(zip(*self._iu, strict=True)):
                np.divide(flat[index], scale, out=system[i, j])
                system[j, i] = system[i, j]
            if smallest is not None:
                smallest[block] = np.linalg.eigvalsh(np.moveaxis(system, -1, 0))[:, 0]
            system += prior
            b = np.moveaxis(rhs[:, :, block].astype(np.float64), 0, 1) / scale   # (K, C, n)
            solution[:, :, block] = _solve_spd(system, b)

        blocks = [slice(a, min(a + SOLVE_BLOCK, n)) for a in range(0, n, SOLVE_BLOCK)]
        if len(blocks) == 1:
            solve_pixels(blocks[0])
        else:   # numpy releases the GIL in these vector operations
            with ThreadPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as pool:
                list(pool.map(solve_pixels, blocks))
        kernels = solution.reshape(k, self.channels, self.h, self.w)
        smallest = None if smallest is None else smallest.reshape(self.h, self.w)
        return kernels, smallest


def _solve_spd(system: np.ndarray, rhs: np.ndarray) -> np.ndarray:
    """Solve ``system[:, :, n] x[:, :, n] = rhs[:, :, n]`` for every pixel ``n``.

    ``system`` ``(K, K, N)`` symmetric positive definite, ``rhs`` ``(K, C, N)``; returns
    ``(K, C, N)``. A Cholesky factorization vectorized over the pixels (K is small, N is
    millions: one LAPACK call per pixel costs ~1 µs, ten times the arithmetic); pixels where a
    pivot loses more than 10 of its 16 digits are re-solved by LAPACK with partial pivoting.
    """
    k = system.shape[0]
    chol = np.zeros_like(system)
    weak = np.zeros(system.shape[-1], bool)
    for j in range(k):
        pivot = system[j, j] - sum(chol[j, p] ** 2 for p in range(j))
        weak |= pivot <= 1e-10 * np.abs(system[j, j])
        chol[j, j] = np.sqrt(np.where(weak, 1.0, pivot))   # weak pixels: placeholder
        for i in range(j + 1, k):
            chol[i, j] = (system[i, j] - sum(chol[i, p] * chol[j, p] for p in range(j))) \
                / chol[j, j]
    y = np.empty_like(rhs)
    for i in range(k):
        y[i] = (rhs[i] - sum(chol[i, p] * y[p] for p in range(i))) / chol[i, i]
    x = np.empty_like(rhs)
    for i in reversed(range(k)):
        x[i] = (y[i] - sum(chol[p, i] * x[p] for p in range(i + 1, k))) / chol[i, i]
    if weak.any():
        x[:, :, weak] = np.moveaxis(np.linalg.solve(
            np.moveaxis(system[:, :, weak], -1, 0), np.moveaxis(rhs[:, :, weak], -1, 0)), 0, -1)
    return x


def _rectangle(valid: np.ndarray) -> tuple[slice, slice] | None:
    """The slices of ``valid``'s bounding box if ``valid`` is exactly that box, else None."""
    rows = np.flatnonzero(valid.any(axis=1))
    if len(rows) == 0:
        return None
    cols = np.flatnonzero(valid[rows[0]])
    rect = (slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
    area = (rect[0].stop - rect[0].start) * (rect[1].stop - rect[1].start)
    if int(np.count_nonzero(valid)) != area or not valid[rect].all():
        return None
    return rect


def predict_aligned(kernels: np.ndarray, basis: WeightBasis, shift: tuple[float, float],
                    convention: str, optical_center: tuple[float, float] | None = None,
                    frame: PixelFrame | None = None) -> np.ndarray:
    """The model's PSF for a source displaced by ``shift``, in the aligned frame, ``(C,H,W)``
    (``frame``: where the kernels' pixels lie on the sensor, as :func:`position_weights`)."""
    weights = position_weights(basis, kernels.shape[-2:], shift, convention, optical_center,
                               frame)
    return np.einsum("khw,kchw->chw", np.broadcast_to(weights, (len(kernels), *kernels.shape[-2:])),
                     kernels)


def check_design(basis: WeightBasis, shifts: np.ndarray, sensor_shape: tuple[int, int],
                 where: str, left_out: str = "") -> None:
    """Refuse a basis that the grid positions cannot determine.

    ``shifts`` may hold NaN rows (positions not measured); ``left_out`` is appended to the
    count in the message (e.g. `` (2 excluded, 4 not captured)``).

    Raises
    ------
    InvalidInputError
        Fewer positions than kernels, or a weight term that does not vary independently over
        the positions (e.g. all positions on one row).
    """
    shifts = np.asarray(shifts, dtype=np.float64).reshape(-1, 2)
    shifts = shifts[np.isfinite(shifts).all(axis=1)]     # gaps and excluded positions
    if len(shifts) < basis.n_kernels:
        raise InvalidInputError(f"{where}: basis {basis.name!r} needs at least "
                                f"{basis.n_kernels} positions ({basis.n_kernels} kernels) but "
                                f"only {len(shifts)} {'remain' if len(shifts) != 1 else 'remains'}"
                                f"{left_out}; use a smaller basis (--basis)")
    design = np.concatenate([position_weights(basis, sensor_shape, tuple(s), "source")[:, 0, 0][
        None] for s in shifts])
    for k, name in enumerate(basis.kernel_names[1:], start=1):
        column = design[:, k]
        if np.ptp(column) <= 1e-9 * (1.0 + np.abs(column).max()):
            raise InvalidInputError(
                f"{where}: singular design: the weight of kernel {name!r} of basis "
                f"{basis.name!r} does not vary over the grid positions, so the kernel is not "
                "determined (are all positions on one row or column?)")
    if np.linalg.matrix_rank(design, tol=1e-9 * np.abs(design).max()) < basis.n_kernels:
        raise InvalidInputError(
            f"{where}: singular design: the weights of the {basis.n_kernels} kernels of basis "
            f"{basis.name!r} are linearly dependent over the grid positions; use a grid that "
            "spans both directions or a smaller basis")


def relative_error(prediction: np.ndarray, data: np.ndarray, valid: np.ndarray) -> float:
    """``‖pred − data‖ / ‖data‖`` over the valid pixels of all channels."""
    diff = np.sum((prediction - data) ** 2, axis=0)[valid].sum()
    norm = np.sum(data**2, axis=0)[valid].sum()
    return float(math.sqrt(diff / norm)) if norm > 0 else float("nan")


def working_region(support: np.ndarray, reference: np.ndarray, working_size: int
                   ) -> tuple[tuple[slice, slice] | None, int, dict[str, Any]]:
    """Where and at what resolution the working copy holds the aligned PSFs, from the centre
    PSF's extent.

    The PSFs of the aligned grid all lie where the centre PSF lies. The working region is the
    bounding box of the centre PSF's support grown by its own size (and 8 px) on every side,
    room for PSFs that grow over the field, clipped to the sensor: defined by the PSF alone, so
    a cut-out that holds it gives the same working copy as the full frame; when that is the
    whole sensor (a caustic), the whole sensor as before issue 43. The binning is the smallest
    that brings the region to ``working_size`` px (the memory bound): a compact PSF stays at
    full resolution, several pixels wide. Its bandwidth is reported: the fraction of the
    centre PSF's power (on its support's box) above the binned grid's Nyquist frequency, which
    that binning folds.

    Parameters
    ----------
    support : numpy.ndarray
        ``(H, W)`` bool support of the centre PSF
        (:func:`psfkit.calibration.alignment.psf_support`).
    reference : numpy.ndarray
        ``(H, W)`` its luminance.
    working_size : int
        Longest side of the working copy, px.

    Returns
    -------
    region : (slice, slice) or None
        Rows and columns of the sensor (``None``: all of it).
    factor : int
        Binning factor.
    record : dict
        JSON-ready description (``kernel file`` provenance, ``fit.json``).
    """
    h, w = support.shape
    rows, cols = np.flatnonzero(support.any(axis=1)), np.flatnonzero(support.any(axis=0))
    if len(rows) == 0:
        rows, cols = np.arange(h), np.arange(w)
    box = (slice(int(rows[0]), int(rows[-1]) + 1), slice(int(cols[0]), int(cols[-1]) + 1))
    extent = [box[0].stop - box[0].start, box[1].stop - box[1].start]
    grown = tuple(slice(max(0, sl.start - size - 8), min(n, sl.stop + size + 8))
                  for sl, size, n in zip(box, extent, (h, w), strict=True))
    crop = (grown[0].stop - grown[0].start, grown[1].stop - grown[1].start)
    region = None if crop == (h, w) else (grown[0], grown[1])
    shape = (h, w) if region is None else crop
    factor = binning_factor(shape, working_size)
    record = {"chosen_from": "the whole sensor (the PSF fills it)" if region is None else
              "the centre PSF's support",
              "origin_px": [0, 0] if region is None else [region[0].start, region[1].start],
              "shape_px": list(shape), "binning": factor, "psf_extent_px": extent,
              "aliased_power": aliased_power(reference[box], factor)}
    return region, factor, record


def aliased_power(image: np.ndarray, factor: int) -> float:
    """Fraction of an image's (non-DC) power above the Nyquist frequency of a grid binned by
    ``factor`` (what that binning folds): 0 for ``factor`` 1."""
    import scipy.fft as sfft

    if factor <= 1 or min(image.shape) < 2:
        return 0.0
    power = np.abs(sfft.rfft2(image - image.mean(), workers=-1)) ** 2
    gy = np.abs(np.fft.fftfreq(image.shape[0]))[:, None]
    gx = np.fft.rfftfreq(image.shape[1])[None, :]
    total = float(power.sum())
    limit = 0.5 / factor
    return float(power[(gy > limit) | (gx > limit)].sum()) / total if total > 0 else 0.0


@dataclass
class WorkingStack:
    """The aligned grid, cropped to ``region`` and binned by ``factor`` (kept in memory for
    residuals, CV and PCA).

    ``images`` ``(P, C, h, w)``, ``valid`` ``(P, h, w)``, ``shifts`` ``(P, 2)`` in binned
    pixels, ``index`` ``(P, 2)`` grid rows/columns, ``overlap`` ``(P,)`` (the centre PSF's
    light in each one's registered overlap), ``light_in_region`` ``(P,)`` (each PSF's light
    inside ``region``): one entry per measured position (an excluded one is dropped by
    :meth:`subset`). ``region`` ``(rows, cols)`` of the sensor ``sensor_shape``, or ``None``:
    the whole sensor (a PSF that fills it).
    """

    factor: int
    images: np.ndarray
    valid: np.ndarray
    shifts: np.ndarray
    index: np.ndarray
    overlap: np.ndarray
    gains: np.ndarray
    region: tuple[slice, slice] | None = None
    sensor_shape: tuple[int, int] | None = None
    light_in_region: np.ndarray | None = None

    @classmethod
    def empty(cls, n: int, image_shape: tuple[int, int, int], factor: int,
              region: tuple[slice, slice] | None = None) -> WorkingStack:
        c, h, w = image_shape
        if region is not None:
            h, w = region[0].stop - region[0].start, region[1].stop - region[1].start
        shape = (h // factor, w // factor)
        return cls(factor=factor, images=np.zeros((n, c, *shape), np.float32),
                   valid=np.zeros((n, *shape), bool), shifts=np.zeros((n, 2)),
                   index=np.zeros((n, 2), int), overlap=np.zeros(n), gains=np.zeros(n),
                   region=region, sensor_shape=tuple(image_shape[1:]),   # type: ignore[arg-type]
                   light_in_region=np.ones(n))

    @property
    def frame(self) -> PixelFrame | None:
        """Where the working pixels lie on the sensor (``None``: the whole sensor binned,
        whose own grid is the frame, as before issue 43)."""
        if self.region is None or self.sensor_shape is None:
            return None
        return PixelFrame.crop(self.sensor_shape, (self.region[0].start, self.region[1].start),
                               self.factor, self.images.shape[-2:])

    def reduce(self, image: np.ndarray) -> np.ndarray:
        """A full-resolution ``(..., H, W)`` image (a kernel) as the working copy holds its
        PSFs: cropped to ``region``, block-averaged by ``factor``."""
        if self.region is not None:
            image = image[(..., *self.region)]
        return bin_image(image, self.factor) / self.factor**2

    def subset(self, members: np.ndarray) -> WorkingStack:
        """The stack of the ``members`` (bool ``(P,)``) only (the same arrays when all)."""
        if members.all():
            return self
        return WorkingStack(factor=self.factor, images=self.images[members],
                            valid=self.valid[members], shifts=self.shifts[members],
                            index=self.index[members], overlap=self.overlap[members],
                            gains=self.gains[members], region=self.region,
                            sensor_shape=self.sensor_shape,
                            light_in_region=None if self.light_in_region is None
                            else self.light_in_region[members])

    def row_of(self, index: tuple[int, int]) -> int:
        """The stack entry of grid index ``(row, col)``."""
        hits = np.flatnonzero((self.index == np.asarray(index)).all(axis=1))
        if len(hits) == 0:
            raise InvalidInputError(f"grid index {index} is not among the measured positions")
        return int(hits[0])

    def lattice(self, values: np.ndarray, grid_shape: tuple[int, int]) -> np.ndarray:
        """Per-entry ``values`` ``(P, ...)`` placed on the ``(N, M, ...)`` lattice (NaN
        elsewhere)."""
        out = np.full((*grid_shape, *np.shape(values)[1:]), np.nan)
        out[self.index[:, 0], self.index[:, 1]] = values
        return out

    def put(self, p: int, aligned: AlignedPsf, image: np.ndarray, gain: float) -> None:
        """Store position ``p`` cropped and binned (``image`` may be the gain-compensated
        version)."""
        f = self.factor
        valid = aligned.valid
        if self.region is not None:
            image, valid = image[(slice(None), *self.region)], valid[self.region]
            if self.light_in_region is not None and aligned.support is not None:
                light = np.where(aligned.support, np.maximum(aligned.luminance, 0.0), 0.0)
                total = float(light.sum(dtype=np.float64))
                self.light_in_region[p] = float(light[self.region].sum(dtype=np.float64)) \
                    / total if total > 0 else 1.0
        self.images[p] = bin_image(image, f)
        self.images[p] /= np.float32(f**2)
        rect = _rectangle(valid)
        if rect is None:
            self.valid[p] = bin_image(valid.astype(np.float32), f) > f**2 - 0.5
        else:   # the blocks that lie inside the rectangle
            h, w = self.valid.shape[1:]
            rows = (np.arange(h) * f >= rect[0].start) & ((np.arange(h) + 1) * f <= rect[0].stop)
            cols = (np.arange(w) * f >= rect[1].start) & ((np.arange(w) + 1) * f <= rect[1].stop)
            self.valid[p] = rows[:, None] & cols[None, :]
        self.shifts[p] = np.asarray(aligned.shift) / f
        self.index[p] = (aligned.position.row, aligned.position.col)
        self.overlap[p] = aligned.support_overlap if np.isfinite(aligned.support_overlap) \
            else aligned.overlap
        self.gains[p] = gain


def fit_stack(stack: WorkingStack, basis: WeightBasis, convention: str,
              members: np.ndarray | None = None, ridge: float = DEFAULT_RIDGE
              ) -> tuple[np.ndarray, np.ndarray]:
    """Kernels ``(K, C, h, w)`` fitted on the ``members`` (bool ``(P,)``) of a working stack,
    and the per-pixel conditioning of the design."""
    members = np.ones(len(stack.images), bool) if members is None else members
    equations = NormalEquations(basis, convention, stack.images.shape[1:], frame=stack.frame)
    for p in np.flatnonzero(members):
        equations.add(stack.images[p], stack.valid[p], tuple(stack.shifts[p]))
    kernels, conditioning = equations.solve(ridge)
    assert conditioning is not None
    return kernels, conditioning


def stack_residuals(stack: WorkingStack, kernels: np.ndarray, basis: WeightBasis,
                    convention: str) -> np.ndarray:
    """In-sample relative error ``(P,)`` of a model on every position of a working stack."""
    return np.array([relative_error(predict_aligned(kernels, basis, tuple(stack.shifts[p]),
                                                    convention, frame=stack.frame),
                                    stack.images[p], stack.valid[p])
                     for p in range(len(stack.images))])


def fold_groups(n: int, center_row: int, folds: int = 9, seed: int = 0) -> list[np.ndarray]:
    """The positions other than the centre (stack rows) in ``folds`` random groups (seeded:
    every cross-validation of a stack holds out the same groups)."""
    others = np.array([p for p in range(n) if p != center_row])
    if len(others) == 0:
        return []
    rng = np.random.default_rng(seed)
    return np.array_split(rng.permutation(others), min(folds, len(others)))


@dataclass
class CrossValidation:
    """Per-position held-out errors of cross-validated models (:func:`cross_validate_positions`).

    ``held_out`` has one entry per model (``"basis/convention"`` and ``"centre PSF only"``);
    ``kernel_differences[model]`` is ``(full, folds)``: the squared relative differences
    ``‖K_k − K_0‖² / ‖K_0‖²`` (k ≥ 1) of the kernels fitted on all positions ``(K − 1,)``
    and on each fold's training positions ``(G, K − 1)``, for a jackknife over the folds.
    """

    held_out: HeldOutErrors
    folds: int
    kernel_differences: dict[str, tuple[np.ndarray, np.ndarray]]

    def to_dict(self) -> dict[str, Any]:
        """The ``cross_validation`` record of a fit: pooled errors, their 1σ, the best."""
        names = list(self.held_out.squared)
        errors = {name: self.held_out.error(name) for name in names}
        best = min((k for k in errors if k != CENTRE_ONLY), key=errors.__getitem__,
                   default=None)
        return {"held_out_relative_error": errors,
                "held_out_sigma": {name: self.held_out.sigma(name) for name in names},
                "best": best, "folds": self.folds}


def squared_relative_differences(kernels: np.ndarray) -> np.ndarray:
    """``‖K_k − K_0‖² / ‖K_0‖²`` for k ≥ 1 of ``(K, C, h, w)`` kernels, ``(K − 1,)``."""
    base = float(np.sum(kernels[0].astype(np.float64) ** 2))
    return np.array([float(np.sum((kernels[k] - kernels[0]).astype(np.float64) ** 2))
                     / max(base, 1e-300) for k in range(1, len(kernels))])


def kernel_difference_estimates(full: np.ndarray, folds: np.ndarray, p_value: float
                                ) -> list[Estimate]:
    """Each eigen-kernel's relative difference from the base kernel, ``‖K_k − K_0‖/‖K_0‖``,
    as an :class:`~psfkit.numerics.significance.Estimate` from the delete-a-fold jackknife of its
    square: the jackknife removes the square's noise bias (of order 1/positions), its spread
    over the folds gives the 1σ; ``p_value`` is that of the held-out test of a field
    dependence (the differences matter only where the field model predicts better).

    ``full`` ``(K − 1,)`` and ``folds`` ``(G, K − 1)`` as in
    :attr:`CrossValidation.kernel_differences`.
    """
    g = len(folds)
    if g < 2:
        return [undetermined("fewer than two cross-validation folds") for _ in full]
    mean = folds.mean(axis=0)
    debiased = g * full - (g - 1) * mean
    spread = np.sqrt((g - 1) / g * np.sum((folds - mean) ** 2, axis=0))
    out = []
    for value2, se2 in zip(debiased, spread, strict=True):
        value = math.sqrt(max(float(value2), 0.0))
        # delta method on the square root, kept finite where the square is within its noise
        sigma = float(se2) / (2.0 * max(value, math.sqrt(float(se2)), 1e-300))
        out.append(checked(value, sigma, 0.0, p_value))
    return out


CENTRE_ONLY = "centre PSF only"


def cross_validate_positions(stack: WorkingStack, bases: list[str],
                             conventions: tuple[str, ...], center_row: int, folds: int = 9,
                             seed: int = 0) -> CrossValidation:
    """Leave-positions-out cross-validation of eigen-kernel models, per position.

    Positions other than the centre are split into ``folds`` random groups
    (:func:`fold_groups`); each model is fitted without one group (the centre is always kept:
    it defines the frame) and predicts it. The normal equations are accumulated once per
    group, so a fold's training system is the total minus its group. Also the centre PSF
    alone (every position predicted by the centre PSF, shifted) is scored.
    """
    n = len(stack.images)
    groups = fold_groups(n, center_row, folds, seed)
    held = np.concatenate(groups) if groups else np.zeros(0, int)
    training_size = n - max((len(g) for g in groups), default=0)
    norms = np.array([_squared_norm(stack, p) for p in held])
    centre = stack.images[center_row]
    squared = {CENTRE_ONLY: np.array([_squared_error(stack, p, centre) for p in held])}
    differences: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    shape = stack.images.shape[1:]
    for name in bases:
        basis = get_basis(name)
        if training_size < basis.n_kernels:
            continue                       # too few training positions for this basis
        for convention in conventions:
            per_group = []
            for group in groups:
                eq = NormalEquations(basis, convention, shape, frame=stack.frame)
                for p in group:
                    eq.add(stack.images[p], stack.valid[p], tuple(stack.shifts[p]))
                per_group.append(eq)
            total = NormalEquations(basis, convention, shape, frame=stack.frame)
            total.add(stack.images[center_row], stack.valid[center_row],
                      tuple(stack.shifts[center_row]))
            for eq in per_group:
                total += eq
            errors = {}
            fold_differences = []
            for group, eq in zip(groups, per_group, strict=True):
                kernels = total.minus(eq).solve(conditioning=False)[0]
                fold_differences.append(squared_relative_differences(kernels))
                for p in group:
                    errors[p] = _squared_error(stack, p, predict_aligned(
                        kernels, basis, tuple(stack.shifts[p]), convention, frame=stack.frame))
            key = f"{name}/{convention}"
            squared[key] = np.array([errors[p] for p in held])
            if basis.n_kernels > 1:
                full = squared_relative_differences(total.solve(conditioning=False)[0])
                differences[key] = (full, np.array(fold_differences))
    return CrossValidation(HeldOutErrors(squared, norms), len(groups), differences)


def _squared_norm(stack: WorkingStack, p: int) -> float:
    return float(np.sum(stack.images[p] ** 2, axis=0)[stack.valid[p]].sum())


def _squared_error(stack: WorkingStack, p: int, prediction: np.ndarray) -> float:
    return float(np.sum((prediction - stack.images[p]) ** 2, axis=0)[stack.valid[p]].sum())
