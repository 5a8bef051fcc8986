"""The per-frequency ``K × K`` Gram blocks of the scenes of a pairs fit (:class:`FrequencyGram`),
and the preconditioner of :mod:`psfkit.fitting.pairs.solver`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

import numpy as np
import torch
from torch import Tensor

from psfkit.fitting.grid.eigen import difference_matrix
from psfkit.forward.convolution import kernel_spectra, kernels_from_spectra
from psfkit.forward.kernel_space import KernelSpaceOperator
from psfkit.forward.weights import get_basis


class PairLayout(Protocol):
    """What the Gram blocks read of the pairs
    (:class:`~psfkit.fitting.pairs.batches.PairBatches`)."""

    grid: tuple[int, int]
    sensor: tuple[int, int]
    kernel_shape: tuple[int, int]
    n_kernels: int
    basis: str
    channels: int
    device: str


class FrequencyGram:
    r"""Per-frequency ``K × K`` Gram blocks of the weighted scenes, accumulated batch by batch.

    ``blocks`` is ``(C, PH, PW//2 + 1, K, K)`` complex128. Source side (and SI):
    :math:`\sum_i s_i^2\,\overline{\hat S_{ik}}\hat S_{il}`; sensor side :math:`m_{kl}\sum_i
    s_i^2|\hat x_i|^2`, :math:`m_{kl}` the mean of :math:`W_kW_l` (an approximation).
    """

    def __init__(self, batches: PairLayout) -> None:
        self.grid, self.kernel_shape = batches.grid, batches.kernel_shape
        self.n_kernels, self.device = batches.n_kernels, batches.device
        freq = (self.grid[0], self.grid[1] // 2 + 1)
        k = self.n_kernels
        self.blocks = torch.zeros((batches.channels, *freq, k, k), dtype=torch.complex128,
                                  device=self.device)
        self._power: Tensor | None = None
        self.mean_products = np.ones((1, 1))
        if batches.basis != "si":
            w = get_basis(batches.basis).maps(batches.sensor).astype(np.float64)  # (K, H, W)
            self.mean_products = np.einsum("khw,lhw->kl", w, w) / (w.shape[1] * w.shape[2])

    def add(self, op: KernelSpaceOperator, scales: Tensor) -> None:
        """Add one batch (its operator's scene spectra, times the scales)."""
        spectra = op.scene_spectra.to(torch.complex128)              # (b, K or 1, C, F...)
        s2 = (scales.to(torch.float64) ** 2)[:, None, None, None, None]
        if spectra.shape[1] == 1:
            power = (spectra[:, 0].abs() ** 2 * s2[:, 0]).sum(dim=0)         # (C, F...)
            self._power = power if self._power is None else self._power + power
            return
        weighted = spectra * s2
        self.blocks += torch.einsum("bkcuv,blcuv->cuvkl", spectra.conj(), weighted)

    def matrix(self) -> Tensor:
        """The blocks ``(C, PH, PW//2+1, K, K)`` (sensor side and SI: from the summed power)."""
        if self._power is not None:
            m = torch.as_tensor(self.mean_products, dtype=torch.complex128, device=self.device)
            return self._power[..., None, None].to(torch.complex128) * m
        return self.blocks

    def reference_power(self) -> float:
        """Mean over frequencies and channels of the summed power of the scene spectra the kernels
        see: the unit of ``--tikhonov`` and ``--difference``."""
        if self._power is not None:
            return float(self._power.mean())
        return float(torch.diagonal(self.blocks, dim1=-2, dim2=-1).real.sum(-1).mean())

    def inverse(self, tikhonov: float, difference: float, floor: float = 1e-12,
                coupled: bool = True) -> Tensor:
        """``[G(ω) + λ I + μ D + ε]^{-1}`` per frequency and channel (``ε``: ``floor`` times the
        mean trace); ``coupled=False`` inverts only the diagonal, kernel by kernel (block Jacobi).
        """
        k = self.n_kernels
        if self._power is not None and k == 1:           # one kernel: a division
            eps = floor * max(float(self._power.mean()), 1e-300)
            return (1.0 / (self._power + (tikhonov + eps))).to(torch.complex128)[..., None,
                                                                                  None]
        g = self.matrix()
        eye = torch.eye(k, dtype=torch.complex128, device=self.device)
        reg = tikhonov * eye + difference * torch.as_tensor(
            difference_matrix(k), dtype=torch.complex128, device=self.device)
        scale = float(torch.diagonal(g, dim1=-2, dim2=-1).real.mean())
        eps = floor * max(scale, 1e-300)
        if not coupled:
            return torch.diag_embed(1.0 / torch.diagonal(g + reg + eps * eye, dim1=-2, dim2=-1))
        return torch.linalg.inv(g + reg + eps * eye)

    def preconditioner(self, tikhonov: float, difference: float, coupled: bool = True,
                       dtype: torch.dtype | None = None) -> Callable[[Tensor], Tensor]:
        """``P`` of :mod:`psfkit.fitting.pairs.solver` on ``(K, C, Hk, Wk)`` residuals, applied in
        ``dtype`` (default the residual's) and returned in the residual's; ``coupled`` as in
        :meth:`inverse`."""
        # (K, K, C, PH, PW//2+1): one multiply-add per block entry beats a batched matmul of
        # 3 x 3 matrices over the frequencies
        inverses = {torch.float64: self.inverse(tikhonov, difference, coupled=coupled)
                    .permute(3, 4, 0, 1, 2).contiguous()}

        def apply(r: Tensor) -> Tensor:
            work = r.dtype if dtype is None else dtype
            if work not in inverses:
                inverses[work] = inverses[torch.float64].to(
                    torch.complex64 if work == torch.float32 else torch.complex128)
            inv = inverses[work]
            spectra = kernel_spectra(r.to(work), self.grid)
            if coupled:
                solved = torch.stack([sum(inv[k, j] * spectra[j] for j in range(len(inv)))
                                      for k in range(len(inv))])
            else:
                solved = torch.stack([inv[k, k] * spectra[k] for k in range(len(inv))])
            return kernels_from_spectra(solved, self.grid, self.kernel_shape).to(r.dtype)

        return apply
