"""``admm_tv(measurement, psf)``: ADMM-TV with a PSF, a thin alias of the one solver.

Kept for callers of the DiffuserCam tutorial's function. It builds the shift-invariant kernel
model of the PSF (:func:`~ekdun.reconstruction.classical.psf_model`) and runs
:class:`~ekdun.reconstruction.classical.ModelReconstructor`, the solver of
``ekdun admm --kernels`` and ``ekdun admm PSF RAW`` (:func:`~ekdun.reconstruction.ek_admm.
ek_admm_tv`; the scene on the padded grid, ``tau`` relative to the measurement's peak and
``‖A‖``).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ekdun.reconstruction.classical import ClassicalOptions, ModelReconstructor, psf_model

_DTYPE_NAMES = {torch.float32: "float32", torch.float64: "float64"}


def admm_tv(measurement: np.ndarray | Tensor, psf: np.ndarray | Tensor, iterations: int = 100,
            tau: float = 1e-3, scene_padding: int = 2, normalize_psf: bool = True,
            dtype: torch.dtype = torch.float64) -> Tensor:
    """Reconstruct a scene from one measurement with ADMM-TV and a shift-invariant PSF.

    Parameters
    ----------
    measurement : array ``(C, H', W')`` or ``(H', W')``
        Background-subtracted measurement.
    psf : array ``(C, Hk, Wk)`` or ``(Hk, Wk)``
        PSF (origin at its centre), ``Hk <= H'``, ``Wk <= W'``; a mono PSF is used for every
        channel.
    iterations : int
        ADMM iterations.
    tau : float
        TV weight relative to the measurement's peak and ``‖A‖`` (``--tv``).
    scene_padding : int
        Padded-grid factor.
    normalize_psf : bool
        Scale each PSF channel to unit sum first (reconstruction in measurement units).
    dtype : torch.float32 or torch.float64

    Returns
    -------
    Tensor
        ``(C, H', W')`` in ``dtype``.
    """
    y = np.asarray(measurement, dtype=np.float64)
    y = y[None] if y.ndim == 2 else y
    h = np.asarray(psf, dtype=np.float64)
    if normalize_psf:
        h = h / np.maximum(h.sum(axis=(-2, -1), keepdims=True), 1e-12)
    model = psf_model(h, y.shape[-2:], y.shape[0], scene_padding)
    options = ClassicalOptions(solver="admm", tv=tau, iterations=iterations,
                               dtype=_DTYPE_NAMES[dtype])
    image = ModelReconstructor(model, options)(y).image
    return torch.as_tensor(image, dtype=dtype)
