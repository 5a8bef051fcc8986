"""The scenes of a pairs fit visited in batches (:class:`PairBatches`): the streaming passes
over the pairs (forward model, exact normal operator, right-hand side, Gram blocks, residuals)
with bounded memory, their batch size and the cache of their scene spectra.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from contextlib import contextmanager

import numpy as np
import torch
from torch import Tensor

from psfkit.errors import InvalidInputError
from psfkit.fitting.pairs.gram import FrequencyGram
from psfkit.forward.kernel_space import KernelSpaceOperator, linear_convolution_grid
from psfkit.forward.weights import get_basis

#: Default bytes of scene spectra kept between passes (beyond it, they are recomputed per
#: batch in every pass: bounded memory, a few more FFTs).
DEFAULT_CACHE_BYTES = 3 * 2**29
#: Most pairs per batch of the streaming passes.
DEFAULT_BATCH = 16
#: On the CPU a batch's largest temporary (its scene spectra times a residual's) is kept under
#: glibc's largest reuse threshold (:mod:`psfkit.cli.allocator`): a larger one is served with fresh
#: ``mmap`` pages and page-faulted in on every pass (at 128² this halves a pass;
#: research/notes/changelog-measurements.md).
BATCH_BYTES = 24 * 2**20

MeasurementSource = Callable[[int, int], np.ndarray | Tensor]


def auto_batch_size(bytes_per_pair: int, device: str = "cpu") -> int:
    """Pairs per batch: on the CPU as many as keep a batch's spectra under ``BATCH_BYTES``
    (at least 1, at most ``DEFAULT_BATCH``); elsewhere ``DEFAULT_BATCH``."""
    if str(device).split(":")[0] != "cpu":
        return DEFAULT_BATCH
    return int(min(DEFAULT_BATCH, max(1, BATCH_BYTES // max(1, bytes_per_pair))))


class PairBatches:
    """The scenes of a pairs fit, visited in batches, with their kernel-space operators.

    Parameters
    ----------
    scenes : numpy.ndarray or Tensor
        ``(N, C, H', W')``.
    basis, convention : str
        The eigen-kernel model (``"si"`` for one kernel).
    kernel_shape : (int, int)
        ``(Hk, Wk)`` (at most the sensor size).
    scene_padding : int
        Padding factor of the model.
    batch_size : int, optional
        Pairs per batch; default :func:`auto_batch_size`.
    cache_bytes : int
        Bytes of the first batches' operators (scene spectra) kept between passes (``0``:
        never); :meth:`astype`'s twin has its own budget.
    dtype, device
        Working precision and device of the operators.
    """

    def __init__(self, scenes: np.ndarray | Tensor, basis: str, convention: str,
                 kernel_shape: tuple[int, int], scene_padding: int = 2,
                 batch_size: int | None = None, cache_bytes: int = DEFAULT_CACHE_BYTES,
                 dtype: torch.dtype = torch.float64, device: str = "cpu") -> None:
        if scenes.ndim != 4 or len(scenes) == 0:
            raise InvalidInputError(f"scenes must be (N, C, H, W) with N >= 1, got "
                                    f"{tuple(scenes.shape)}")
        self.scenes = scenes
        self.n, self.channels, h, w = (int(s) for s in scenes.shape)
        self.sensor = (h, w)
        self.basis, self.convention = basis, convention
        self.kernel_shape = (int(kernel_shape[0]), int(kernel_shape[1]))
        self.scene_padding = scene_padding
        self.n_kernels = get_basis(basis).n_kernels
        self.grid = linear_convolution_grid(self.sensor, self.kernel_shape, scene_padding)
        self.dtype, self.device = dtype, device
        self.cache_bytes = cache_bytes
        self.scales = torch.ones(self.n, dtype=dtype, device=device)
        per_pair = (self.n_kernels if basis != "si" and convention == "source" else 1) \
            * self.channels * self.grid[0] * (self.grid[1] // 2 + 1) \
            * (16 if dtype == torch.float64 else 8)
        self.batch_size = max(1, int(batch_size)) if batch_size is not None \
            else auto_batch_size(per_pair, device)
        # as many batches as fit in ``cache_bytes`` are kept (the first ones): with more pairs
        # than fit, the rest are recomputed in every pass, and the kept ones still save their
        # FFTs (384 pairs of 128²: 1.8 GB of float64 spectra against a 1.5 GiB budget)
        self._per_pair = per_pair
        self._cache: dict[int, KernelSpaceOperator] = {}
        self._cached_pairs = 0
        self.passes = 0
        #: Pairs that the passes visit (a cross-validation fold's, :meth:`only`); None: all.
        self.active: Tensor | None = None

    def astype(self, dtype: torch.dtype) -> PairBatches:
        """The same pairs, batches and scales in another precision, with a cache of its own
        (e.g. float32 Hessian products for :func:`projected_newton`)."""
        twin = PairBatches(self.scenes, self.basis, self.convention, self.kernel_shape,
                           self.scene_padding, None, self.cache_bytes, dtype, self.device)
        twin.scales = self.scales.to(dtype)
        return twin

    def ranges(self) -> Iterator[tuple[int, int]]:
        """``(start, stop)`` of every batch."""
        for start in range(0, self.n, self.batch_size):
            yield start, min(start + self.batch_size, self.n)

    def operator(self, start: int, stop: int) -> KernelSpaceOperator:
        """The (unscaled) kernel-space operator of pairs ``start:stop`` (cached if allowed)."""
        if start in self._cache:
            return self._cache[start]
        x = torch.as_tensor(self.scenes[start:stop], dtype=self.dtype, device=self.device)
        op = KernelSpaceOperator(x, self.basis, self.convention, self.kernel_shape,
                                 self.scene_padding)
        if op.grid != self.grid:                       # one grid for every batch
            raise AssertionError("batch grid differs")  # pragma: no cover
        if (self._cached_pairs + stop - start) * self._per_pair <= self.cache_bytes:
            self._cache[start] = op
            self._cached_pairs += stop - start
        return op

    @contextmanager
    def only(self, active: Tensor | np.ndarray) -> Iterator[PairBatches]:
        """Within the ``with`` block every pass visits only the pairs where ``active`` (``(N,)``
        bool) is true (a fold's training or held-out pairs), from the same cached scene spectra."""
        previous = self.active
        self.active = torch.as_tensor(np.asarray(active, dtype=bool), device=self.device)
        try:
            yield self
        finally:
            self.active = previous

    def batches(self) -> Iterator[tuple[int, int, KernelSpaceOperator, Tensor]]:
        """One pass: ``(start, stop, operator, scales)`` per batch, or with :attr:`active` per run
        of consecutive active pairs (a view of the batch's spectra)."""
        self.passes += 1
        for start, stop in self.ranges():
            if self.active is None or bool(self.active[start:stop].all()):
                yield start, stop, self.operator(start, stop), self.scales[start:stop]
                continue
            for a, b in _runs(self.active[start:stop].tolist()):
                yield (start + a, start + b, self.operator(start, stop).subset(slice(a, b)),
                       self.scales[start + a:start + b])

    def measurement(self, source: np.ndarray | Tensor | MeasurementSource, start: int,
                    stop: int) -> Tensor:
        """The measurements of pairs ``start:stop`` (a batch, or a run of one)."""
        y = source(start, stop) if callable(source) else source[start:stop]
        return torch.as_tensor(y, dtype=self.dtype, device=self.device)

    # -------------------------------------------------------------------- operators
    def predictions(self, kernels: Tensor
                    ) -> Iterator[tuple[int, int, KernelSpaceOperator, Tensor, Tensor]]:
        """``(start, stop, operator, scales, B_i K)`` per batch (one pass; unscaled), the kernels'
        FFTs taken once per pass."""
        spectra = None
        for start, stop, op, s in self.batches():
            if spectra is None:
                spectra = op.spectra_of(kernels)
            yield start, stop, op, s, op.forward_spectra(spectra)

    def normal(self, kernels: Tensor) -> Tensor:
        r""":math:`\sum_i s_i^2 B_i^\top B_i K` (one exact pass over the pairs)."""
        total = op = None
        for _start, _stop, op, s, p in self.predictions(kernels):
            term = op.adjoint_spectra(p * (s * s)[:, None, None, None])
            total = term if total is None else total.add_(term)
        return torch.zeros_like(kernels) if op is None else op.kernels_of(total)

    def rhs(self, measurements: np.ndarray | Tensor | MeasurementSource) -> Tensor:
        r""":math:`\sum_i s_i B_i^\top y_i`; ``measurements`` an array or a callable
        ``(start, stop) → (stop − start, C, H', W')``."""
        total = op = None
        for start, stop, op, s in self.batches():
            y = self.measurement(measurements, start, stop)
            term = op.adjoint_spectra(y * s[:, None, None, None])
            total = term if total is None else total.add_(term)
        assert op is not None
        return op.kernels_of(total)

    def gram(self) -> FrequencyGram:
        """The per-frequency ``K × K`` blocks of the scaled scenes (one pass)."""
        gram = FrequencyGram(self)
        for _start, _stop, op, s in self.batches():
            gram.add(op, s)
        return gram

    def residual_norms(self, kernels: Tensor,
                       measurements: np.ndarray | Tensor | MeasurementSource
                       ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """Per pair ``‖s_i B_i K − y_i‖``, ``‖y_i‖``, and the per-pair products
        ``⟨B_i K, y_i⟩`` and ``‖B_i K‖²`` of the unscaled prediction (for the scales)."""
        err = torch.zeros(self.n, dtype=self.dtype, device=self.device)
        norm, num, den = err.clone(), err.clone(), err.clone()
        for start, stop, _op, s, p in self.predictions(kernels):
            y = self.measurement(measurements, start, stop)
            err[start:stop] = (p * s[:, None, None, None] - y).pow(2).sum(dim=(1, 2, 3)).sqrt()
            norm[start:stop] = y.pow(2).sum(dim=(1, 2, 3)).sqrt()
            num[start:stop] = (p * y).sum(dim=(1, 2, 3))
            den[start:stop] = p.pow(2).sum(dim=(1, 2, 3))
        return err, norm, num, den


def _runs(active: list[bool]) -> list[tuple[int, int]]:
    """``(start, stop)`` of every run of consecutive ``True``."""
    edges = np.flatnonzero(np.diff(np.concatenate([[0], np.asarray(active, int), [0]])))
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]
