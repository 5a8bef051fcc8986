r"""Physical constraints on kernels fitted from pairs: the footprint, the step size of the
non-negative solve, and what the kernel file records.

A measured PSF is non-negative and lives on the caustic's footprint. The pairs fit imposes both
with one solver, projected Newton-CG on the normal equations of the conjugate-gradient fit
(:func:`psfkit.pairs_solver.projected_newton`); a support without non-negativity is a linear
constraint, solved exactly by the same conjugate gradients restricted to it
(:func:`psfkit.pairs_fit.fit_pairs`). This module gives the footprint (:func:`auto_support`),
the step ``1/L`` of the KKT residual (:func:`lipschitz`) and the physics record
(:func:`kernel_summary`).

Until issue 44 a second solver lived here: FISTA with adaptive restart, for a fixed per-kernel
energy (``--energy fit|base``, the projection onto the scaled simplex) or a support without
non-negativity. Projected Newton reaches the non-negative least squares to a KKT residual
orders of magnitude smaller in less time, with a held-out error as low or lower (measured in
docs/forward-models.md), and the energy constraint changed the held-out DLMD error by 3e-4
(research/notes/forward-model-studies.md): both left.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np
from torch import Tensor

from psfkit.forward.norm import largest_eigenvalue

Normal = Callable[[Tensor], Tensor]


def auto_support(base: np.ndarray, threshold: float = 0.1, smoothing: float = 1.0,
                 dilation: int = 2) -> np.ndarray:
    """The caustic footprint of a fitted (unconstrained) PSF ``(C, Hk, Wk)``.

    ``|K|`` is averaged over channels, smoothed with a Gaussian of ``smoothing`` pixels (the
    negative lobes of an unconstrained fit sit next to the caustic lines: their magnitude marks
    the footprint too), thresholded at ``threshold`` × its maximum, and dilated by ``dilation``
    pixels so that the edge of the caustic is not cut.

    Returns
    -------
    numpy.ndarray
        ``(Hk, Wk)`` bool.
    """
    from scipy.ndimage import binary_dilation, gaussian_filter

    magnitude = np.abs(np.asarray(base, dtype=np.float64)).mean(axis=0)
    smooth = gaussian_filter(magnitude, smoothing) if smoothing > 0 else magnitude
    mask = smooth >= threshold * smooth.max() if smooth.max() > 0 else np.ones_like(smooth,
                                                                                     bool)
    if dilation > 0:
        mask = binary_dilation(mask, iterations=dilation)
    return mask


#: Relative accuracy of the step-size eigenvalue (a step size needs no more).
LIPSCHITZ_TOLERANCE = 1e-2


def lipschitz(normal: Normal, like: Tensor, seed: int = 0) -> Tensor:
    """Largest eigenvalue of the (per-channel block-diagonal, positive semi-definite) normal
    operator, per channel ``(C,)``, times 1.05: :func:`psfkit.forward.norm.largest_eigenvalue`
    (the one estimator; to ``LIPSCHITZ_TOLERANCE``) approaches it from below, and a step of
    ``1/L`` needs ``L`` at least the eigenvalue."""
    value = largest_eigenvalue(normal, tuple(like.shape), like.dtype, like.device, block_dim=1,
                               tol=LIPSCHITZ_TOLERANCE, seed=seed)
    return 1.05 * value.to(dtype=like.dtype, device=like.device)


def kernel_summary(kernels: np.ndarray) -> dict[str, Any]:
    """What the kernel file records about a fitted model's physics: per-kernel, per-channel
    energies (sums) ``[K][C]``, the support fraction (pixels non-zero in some kernel or
    channel), and the count of negative and non-finite pixels."""
    k = np.asarray(kernels, dtype=np.float64)
    return {"energy": [[float(e) for e in row] for row in k.sum(axis=(-2, -1))],
            "support_fraction": float(np.any(k != 0, axis=(0, 1)).mean()),
            "negative_pixels": int((k < 0).sum()),
            "nonfinite_pixels": int((~np.isfinite(k)).sum())}
