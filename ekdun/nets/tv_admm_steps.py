r"""The steps of ADMM with total-variation regularisation, written once (differentiable, float
or tensor ``μ``, ``τ``).

Used by the unrolled Le-ADMM-U; :mod:`ekdun.reconstruction.admm` shares the finite
differences, and its ``ShiftInvariantRule`` is this iteration in normalised units (tested).
The problem (DiffuserCam, Antipa et al. 2018), for ``x`` on the padded grid, ``H`` a circular
convolution, ``C`` the crop, ``Ψ`` circular forward differences:

.. math::

    \min_{x \ge 0}\ \tfrac12 \| y - C H x \|_2^2 + \tau \|\Psi x\|_1

split as ``v = Hx``, ``u = Ψx``, ``w = x``. One iteration (:func:`admm_tv_iteration`):

.. math::

    u &\leftarrow \mathcal{S}_{\tau/\mu_2}(\Psi x + \alpha_2/\mu_2) \\
    v &\leftarrow (C^\top C + \mu_1)^{-1}(\alpha_1 + \mu_1 H x + C^\top y) \\
    w &\leftarrow \max(x + \alpha_3/\mu_3, 0) \\
    x &\leftarrow (\mu_1 H^\top H + \mu_2 \Psi^\top\Psi + \mu_3)^{-1}
          \big[(\mu_3 w - \alpha_3) + \Psi^\top(\mu_2 u - \alpha_2)
                + H^\top(\mu_1 v - \alpha_1)\big] \\
    \alpha_1 &\mathrel{+}= \mu_1 (Hx - v), \quad
    \alpha_2 \mathrel{+}= \mu_2 (\Psi x - u), \quad
    \alpha_3 \mathrel{+}= \mu_3 (x - w)

The ``x`` update is exact in Fourier space. It lives in ``nets`` because the layers only go
down (``reconstruction`` sits above ``training``, above ``nets``).
"""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor

from psfkit.forward.convolution import pad
from psfkit.forward.fft import irfft2, rfft2
from psfkit.forward.padded_scene import kernel_images

#: State of an iteration: ``x``, ``hx`` (``Hx``), and the duals ``alpha1..3``.
AdmmState = dict[str, Tensor]


def finite_differences(x: Tensor) -> Tensor:
    """``Ψx``: circular forward differences along rows and columns, ``(2, *x.shape)``."""
    return torch.stack([torch.roll(x, -1, dims=-2) - x, torch.roll(x, -1, dims=-1) - x])


def finite_differences_adjoint(u: Tensor) -> Tensor:
    """``Ψᵀu`` for ``u`` ``(2, ...)``: the exact adjoint of :func:`finite_differences`."""
    return (torch.roll(u[0], 1, dims=-2) - u[0]) + (torch.roll(u[1], 1, dims=-1) - u[1])


def finite_difference_spectrum(grid_shape: tuple[int, int], dtype: torch.dtype) -> Tensor:
    """Eigenvalues of ``ΨᵀΨ`` on the ``rfft2`` grid, ``(PH, PW//2 + 1)``."""
    rows = 2.0 * torch.pi * torch.arange(grid_shape[0], dtype=torch.float64) / grid_shape[0]
    cols = (2.0 * torch.pi * torch.arange(grid_shape[1] // 2 + 1, dtype=torch.float64)
            / grid_shape[1])
    return ((2 - 2 * torch.cos(rows))[:, None] + (2 - 2 * torch.cos(cols))[None, :]).to(dtype)


def soft_threshold(z: Tensor, threshold: Tensor | float) -> Tensor:
    """``𝒮_t(z) = sign(z)·max(|z| − t, 0)``, elementwise."""
    return torch.sign(z) * torch.relu(z.abs() - threshold)


def admm_tv_context(y: Tensor, spectrum: Tensor, conj_spectrum: Tensor,
                    grid_shape: tuple[int, int]) -> dict[str, Any]:
    """What every iteration needs from the measurement ``y`` ``(..., C, H', W')`` and the PSF
    spectrum and its conjugate ``(C, PH, PW//2 + 1)`` on the grid ``(PH, PW)``: a dict of
    those, ``hth`` (``|Ĥ|²``), ``cty`` (``Cᵀy``), ``ctc`` (``CᵀC``, a 0/1 mask) and ``grid``.
    """
    ones = torch.ones_like(y[:1, :1] if y.ndim == 4 else y[:1])
    return {"spectrum": spectrum, "conj_spectrum": conj_spectrum,
            "hth": spectrum.real ** 2 + spectrum.imag ** 2,
            "cty": pad(y, grid_shape), "ctc": pad(ones, grid_shape), "grid": grid_shape}


def admm_tv_initial_state(context: dict[str, Any]) -> AdmmState:
    """Every variable at zero (``x``, ``Hx`` and the duals on the padded grid)."""
    zeros = torch.zeros_like(context["cty"])
    return {"x": zeros, "hx": zeros, "alpha1": zeros,
            "alpha2": torch.zeros((2, *zeros.shape), dtype=zeros.dtype, device=zeros.device),
            "alpha3": zeros}


def admm_tv_iteration(state: AdmmState, context: dict[str, Any], mu1: Tensor | float,
                      mu2: Tensor | float, mu3: Tensor | float, tau: Tensor | float,
                      tv_spectrum: Tensor) -> AdmmState:
    """One ADMM-TV iteration (the updates of the module docstring), a new state.

    ``tv_spectrum`` is :func:`finite_difference_spectrum` of the grid (in ``x``'s dtype).
    """
    x, hx = state["x"], state["hx"]
    alpha1, alpha2, alpha3 = state["alpha1"], state["alpha2"], state["alpha3"]
    u = soft_threshold(finite_differences(x) + alpha2 / mu2, tau / mu2)
    v = (alpha1 + mu1 * hx + context["cty"]) / (context["ctc"] + mu1)
    w = torch.relu(x + alpha3 / mu3)

    rhs = (mu3 * w - alpha3) + finite_differences_adjoint(mu2 * u - alpha2)
    # the x update's Fourier-diagonal solve (Hᵀ of the split variable, no crop: not Eq. 7)
    numerator = rfft2(rhs) + context["conj_spectrum"] * rfft2(mu1 * v - alpha1)
    x_hat = numerator / (mu1 * context["hth"] + mu2 * tv_spectrum + mu3)
    x = irfft2(x_hat, context["grid"])
    hx = kernel_images(x_hat, context["spectrum"], context["grid"])        # H x on the grid

    return {"x": x, "hx": hx,
            "alpha1": alpha1 + mu1 * (hx - v),
            "alpha2": alpha2 + mu2 * (finite_differences(x) - u),
            "alpha3": alpha3 + mu3 * (x - w)}
