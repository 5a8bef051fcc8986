r"""The eigen-kernel operator of Eq. 7 bound to precomputed kernel spectra.

:class:`SpectralOperator` applies ``A`` and ``Aᵀ`` of
:func:`~psfkit.forward.convolution.eigen_kernel_forward` /
:func:`~psfkit.forward.convolution.eigen_kernel_adjoint` with the kernel spectra taken once
(no kernel FFT per call) and the zero-padded FFT input reused outside autograd
(:class:`PaddingWorkspace`). ekdun's :class:`~ekdun.physics.operators.PreparedOperator` adds
its input checks on top.
"""

from __future__ import annotations

import torch
from torch import Tensor

from psfkit.forward.convolution import (
    eigen_kernel_adjoint,
    eigen_kernel_forward,
    records_graph,
    zero_workspace,
)

_REAL_DTYPE = {torch.complex64: torch.float32, torch.complex128: torch.float64}


class PaddingWorkspace:
    """A zero-padded FFT input array reused across calls made outside autograd.

    :func:`eigen_kernel_forward` / :func:`eigen_kernel_adjoint` write each input into the
    top-left block of this ``(..., PH, PW)`` array (which stays zero elsewhere) instead of
    letting every FFT allocate a padded copy. Under autograd a fresh input is needed, so
    :meth:`for_input` then returns ``None``.

    Parameters
    ----------
    grid_shape : (int, int)
        ``(PH, PW)``.
    """

    def __init__(self, grid_shape: tuple[int, int]) -> None:
        self.grid_shape = (int(grid_shape[0]), int(grid_shape[1]))
        self._array: Tensor | None = None

    def for_input(self, t: Tensor, spectra: Tensor) -> Tensor | None:
        """The workspace for inputs shaped like ``t`` ``(..., H', W')`` (reallocated when
        the leading shape, dtype or device changes), or ``None`` when autograd records
        ``t`` or ``spectra``."""
        if records_graph(t, spectra):
            return None
        ws = self._array
        if ws is None or ws.shape[:-2] != t.shape[:-2] or ws.dtype != t.dtype \
                or ws.device != t.device:
            ws = self._array = zero_workspace(t, self.grid_shape)
        return ws


class SpectralOperator:
    """An eigen-kernel operator (Eq. 7, either convention) bound to kernel spectra.

    Cheap to build (no copies), so unrolled networks build one per forward pass, or several
    sharing spectra (EK-DUN's base-kernel model uses the first kernel's spectrum of its
    eigen-kernel model).

    Parameters
    ----------
    spectra : Tensor
        ``(K, C, PH, PW//2 + 1)`` complex kernel spectra
        (:func:`~psfkit.forward.convolution.kernel_spectra`).
    weights : Tensor or None
        ``(K, H', W')`` weight maps (real, same precision as ``spectra``), or ``None`` for one
        kernel with weight 1.
    sensor_shape : (int, int)
        ``(H', W')``.
    grid_shape : (int, int)
        ``(PH, PW)``, the padded grid of the spectra.
    convention : {"sensor", "source"}
        Where the weights act.
    conj_spectra : Tensor, optional
        ``spectra.conj()`` materialised (taken lazily, once, when not given).
    """

    def __init__(self, spectra: Tensor, weights: Tensor | None, sensor_shape: tuple[int, int],
                 grid_shape: tuple[int, int], convention: str = "sensor",
                 conj_spectra: Tensor | None = None) -> None:
        self.spectra = spectra
        self._conj_spectra = conj_spectra
        self.weights = weights
        self.sensor_shape = (int(sensor_shape[0]), int(sensor_shape[1]))
        self.grid_shape = (int(grid_shape[0]), int(grid_shape[1]))
        self.convention = convention
        self.channels = int(spectra.shape[1])
        self.dtype = _REAL_DTYPE[spectra.dtype]
        self._workspace = PaddingWorkspace(self.grid_shape)

    @property
    def device(self) -> torch.device:
        """Where the spectra (and so the inputs) live."""
        return self.spectra.device

    @property
    def n_kernels(self) -> int:
        """Number of kernels ``K`` (1 for the shift-invariant model)."""
        return int(self.spectra.shape[0])

    @property
    def conj_spectra(self) -> Tensor:
        """Conjugate spectra for the adjoint, materialised once (a lazy ``conj()`` view would
        cost a copy in every product)."""
        if self._conj_spectra is None:
            self._conj_spectra = self.spectra.conj().resolve_conj()
        return self._conj_spectra

    def forward(self, x: Tensor) -> Tensor:
        """``y = A x``, scene ``(B, C, H', W')`` → measurement ``(B, C, H', W')``."""
        return eigen_kernel_forward(x, self.spectra, self.weights, self.grid_shape,
                                    self.convention, self._workspace.for_input(x, self.spectra))

    def adjoint(self, y: Tensor) -> Tensor:
        """``x = Aᵀ y``, measurement ``(B, C, H', W')`` → scene ``(B, C, H', W')``."""
        return eigen_kernel_adjoint(y, self.conj_spectra, self.weights, self.grid_shape,
                                    self.convention, self._workspace.for_input(y, self.spectra))
