"""The forward model of the lensless camera, written once (``docs/architecture.md``).

``y = crop(K * pad(x))`` on a padded grid, the eigen-kernel operator of Eq. 7 in both
conventions with its exact adjoint, and its kernel-space form ``K ↦ A_K x`` used to fit kernels
from (scene, measurement) pairs. Everything above it calls these functions: psfkit's
``fit-pairs`` (:mod:`psfkit.fitting.pairs.fit`), ekdun's operator classes, the dense virtual-bench
model, ADMM-TV and Le-ADMM-U.

Modules
-------
:mod:`psfkit.forward.geometry`
    ``CONVENTIONS``, :func:`padded_shape`, :func:`centre_offset`, :func:`kernel_origin`
    (no torch).
:mod:`psfkit.forward.fft`
    :func:`rfft2` / :func:`irfft2`, the only FFT entry points, and :func:`count_ffts`.
:mod:`psfkit.forward.convolution`
    ``pad``/``crop``, kernel embedding and spectra, :func:`eigen_kernel_forward` /
    :func:`eigen_kernel_adjoint` (sensor-sized scene): Eq. 7, written once (its fan-out /
    fan-in core).
:mod:`psfkit.forward.padded_scene`
    :func:`padded_scene_forward` / :func:`padded_scene_adjoint` (scene on the whole padded
    grid) and the pieces ADMM keeps apart (:func:`kernel_images`,
    :func:`padded_scene_adjoint_spectrum`).
:mod:`psfkit.forward.base`
    :class:`LinearOperator`, the base of every operator: ``A``/``A_adjoint``, ``norm()`` and
    ``adjointness_error()`` (the dot-product test every operator's tests run).
:mod:`psfkit.forward.operator`
    The operator of a kernel file, built in one place (``from_kernel_model``;
    :func:`kernel_model_tensors`): :class:`SpectralOperator` (sensor-sized scene, bound to
    precomputed kernel spectra; what ekdun's operator modules hand to the unrolled networks and
    what ``fit-pairs`` predicts with) and :class:`PaddedSceneOperator` (scene on the whole
    padded grid; the classical solvers).
:mod:`psfkit.forward.kernel_space`
    :class:`KernelSpaceOperator` (``B: K ↦ (A_K x_i)_i`` and ``Bᵀ``), the fit-pairs form.
:mod:`psfkit.forward.norm`
    :func:`operator_norm` (``‖A‖`` by power iteration on the actual operator, cached per
    operator) and :func:`largest_eigenvalue`: the one estimator, used by ADMM, PDHG and the
    constrained kernel fit; :func:`spectral_bound`, the bound from above that the unrolled
    networks' initial step sizes use.

Importing this package loads only the geometry; the torch parts load on first use of one of
their names (``psfkit --help`` and the kernel file stay free of torch).
"""

from __future__ import annotations

import importlib
from typing import Any

from psfkit.forward.geometry import CONVENTIONS, centre_offset, kernel_origin, padded_shape

_LAZY = {
    "FFTCount": "fft", "count_ffts": "fft", "rfft2": "fft", "irfft2": "fft",
    "pad": "convolution", "crop": "convolution", "embed_kernel": "convolution",
    "extract_kernel": "convolution", "kernel_spectra": "convolution",
    "eigen_kernel_forward": "convolution", "eigen_kernel_adjoint": "convolution",
    "padded_scene_forward": "padded_scene", "padded_scene_adjoint": "padded_scene",
    "padded_scene_adjoint_spectrum": "padded_scene", "kernel_images": "padded_scene",
    "sum_of_kernel_products": "convolution",
    "zero_workspace": "convolution", "PaddingWorkspace": "operator",
    "SpectralOperator": "operator", "PaddedSceneOperator": "operator",
    "kernel_model_tensors": "operator", "LinearOperator": "base",
    "records_graph": "convolution",
    "KernelSpaceOperator": "kernel_space", "linear_convolution_grid": "kernel_space",
    "operator_norm": "norm", "largest_eigenvalue": "norm", "spectral_bound": "norm",
}

__all__ = ["CONVENTIONS", "centre_offset", "kernel_origin", "padded_shape", *_LAZY]


def __getattr__(name: str) -> Any:
    # PEP 562: import the torch modules only when one of their names is used.
    if name in _LAZY:
        module = importlib.import_module(f"psfkit.forward.{_LAZY[name]}")
        return getattr(module, name)
    raise AttributeError(f"module 'psfkit.forward' has no attribute {name!r}")
