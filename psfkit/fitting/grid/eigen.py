r"""Eigen-kernel fits of a registered PSF grid (paper, Eq. 7), in closed form.

The PSF at grid position ``p``, displaced by ``s_p`` from the centre PSF, is
:math:`h_p(u) = \sum_k W_k(u)\,K_k(u - s_p)` (sensor-side weights) or
:math:`\sum_k W_k(s_p)\,K_k(u - s_p)` (source-side). In the centre PSF's frame
(``v = u − s_p``) both are, at every kernel pixel ``v``, linear in the K kernel values with
design :math:`w_p(v) = W(v + s_p)` or :math:`W(s_p)`, so the least-squares kernels solve per
pixel

.. math::

    \Big(\sum_p m_p w_p w_p^\top + \lambda R\Big) K(v) = \sum_p m_p w_p a_p(v),
    \qquad R = \sum_{k\ge1}(e_k - e_0)(e_k - e_0)^\top,

(``m_p`` the valid mask), accumulated one PSF at a time (:class:`NormalEquations`); the ridge
pulls unconstrained correction kernels towards the base kernel.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import numpy as np

from psfkit.errors import ConfigurationError
from psfkit.fitting.grid.design import PixelFrame, position_weights
from psfkit.forward.kernelfile import CONVENTIONS
from psfkit.forward.weights import WeightBasis

BLOCK_ELEMENTS = 16384      # pixels per block of rows in NormalEquations.add (cache-sized)
SOLVE_BLOCK = 65536         # pixels per block of NormalEquations.solve
#: Default ridge ``λ`` (relative to the mean diagonal of each pixel's normalised Gram matrix).
#: Where the data do not constrain a pixel (the edges, seen by one or two PSFs) the ridge alone
#: sets its correction kernels, so it must lie well above the rounding of the sums (at 1e-9 a
#: one-ulp change of the PSFs moved the demo's kernels there by 15 % of their peak; at 1e-4 by
#: 1.5e-6, at a cost of 3e-5 in the fit's in-sample error;
#: research/notes/changelog-measurements.md).
DEFAULT_RIDGE = 1e-4


def difference_matrix(n_kernels: int) -> np.ndarray:
    r"""``D`` of :math:`\tfrac12\sum_{k\ge1}\lVert K_k - K_0\rVert^2 = \tfrac12 K^\top D K`,
    ``(K, K)`` (the ridge ``R`` above; fit-pairs' difference prior too)."""
    r = np.zeros((n_kernels, n_kernels))
    for k in range(1, n_kernels):
        e = np.zeros(n_kernels)
        e[0], e[k] = -1.0, 1.0
        r += np.outer(e, e)
    return r


class NormalEquations:
    """Per-pixel normal equations of an eigen-kernel fit, accumulated one PSF at a time.

    Two paths give the same sums (to rounding): a PSF whose valid mask is a rectangle keeps only
    its weighted image in the rectangle and, since every weight is a sum of ``f(u)·g(v)``
    products, the row and column factors of its Gram terms, summed for all PSFs as matrix products
    when read (the base kernel's right-hand side is formed then, the weights summing to 1); any
    other mask goes through per-pixel products (:meth:`_add_masked`).

    Parameters
    ----------
    basis : WeightBasis
    convention : {"sensor", "source"}
    image_shape : (int, int, int)
        ``(C, H, W)`` of the PSFs.
    frame : PixelFrame, optional
        Where the ``(H, W)`` pixels lie on the sensor; default: they are the sensor.
    """

    def __init__(self, basis: WeightBasis, convention: str, image_shape: tuple[int, int, int],
                 frame: PixelFrame | None = None) -> None:
        if convention not in CONVENTIONS:
            raise ConfigurationError(f"convention must be one of {CONVENTIONS}, "
                                     f"got {convention!r}")
        self.basis, self.convention = basis, convention
        self.channels, self.h, self.w = image_shape
        self.frame = frame if frame is not None else PixelFrame.of((self.h, self.w))
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

        Accumulated in the image's precision (float32 grid data: rounding far below any sensor's
        noise; float64 input stays float64); the rectangle path's Gram sums are float64.
        """
        dtype = np.dtype(image.dtype if np.issubdtype(image.dtype, np.floating)
                         else np.float64)
        rect = mask_rectangle(valid)
        if rect is None:
            self._add_masked(image, valid, shift, dtype)
        else:
            self._add_rectangle(image, rect, shift, dtype)
        self.count += 1

    def _axis_weights(self, shift: tuple[float, float]
                      ) -> list[list[tuple[np.ndarray | float | None, np.ndarray | None]]]:
        """The weights of the PSF displaced by ``shift`` as sums of ``row(v) ⊗ col(u)`` products,
        per kernel (``None``: a factor of 1)."""
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
        """Per-pixel products over cache-sized blocks of rows."""
        if self._gram is None:
            self._gram = np.zeros((len(self._iu[0]), self.h, self.w), dtype)
            self._rhs = np.zeros((self.channels, self.basis.n_kernels, self.h, self.w), dtype)
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
            self._rhs = sums if self._rhs is None else self._rhs + sums
            self._rect_rhs = None
        if self._gram is None:      # nothing added
            self._gram = np.zeros((len(self._iu[0]), self.h, self.w))
            self._rhs = np.zeros((self.channels, self.basis.n_kernels, self.h, self.w))

    def minus(self, other: NormalEquations) -> NormalEquations:
        """The equations of this set of PSFs without those of ``other`` (a subset)."""
        out = NormalEquations(self.basis, self.convention, (self.channels, self.h, self.w),
                              self.frame)
        out._gram, out._rhs = self.gram - other.gram, self.rhs - other.rhs
        out.count = self.count - other.count
        return out

    def __iadd__(self, other: NormalEquations) -> NormalEquations:
        self._gram = self.gram + other.gram     # may change precision: not in place
        self._rhs = self.rhs + other.rhs
        self.count += other.count
        return self

    def solve(self, ridge: float = DEFAULT_RIDGE, conditioning: bool = True
              ) -> tuple[np.ndarray, np.ndarray | None]:
        """Kernels ``(K, C, H, W)`` and (if ``conditioning``) the per-pixel smallest eigenvalue of
        the normalized Gram matrix ``(H, W)`` (0 where the data do not constrain a pixel)."""
        k = self.basis.n_kernels
        n = self.h * self.w
        gram = self.gram.reshape(len(self._iu[0]), n)
        rhs = self.rhs.reshape(self.channels, k, n)
        prior = (ridge * difference_matrix(k) + 1e-12 * np.eye(k))[:, :, None]
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
    ``(K, C, N)``. A Cholesky factorization vectorized over the pixels (per-pixel LAPACK calls
    cost ten times the arithmetic); pixels whose pivot loses more than 10 digits are re-solved by
    LAPACK with partial pivoting.
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


def mask_rectangle(valid: np.ndarray) -> tuple[slice, slice] | None:
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
