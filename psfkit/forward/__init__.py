"""The forward model of the lensless camera, written once (``docs/architecture.md``).

``y = crop(K * pad(x))`` on a padded grid, the eigen-kernel operator of Eq. 7 in both
conventions with its exact adjoint, and its kernel-space form ``K ↦ A_K x``. Everything above
calls these: ``fit-pairs``, ekdun's operators, the virtual bench, ADMM-TV and Le-ADMM-U.

Modules: :mod:`~psfkit.forward.geometry` (grid geometry, no torch), :mod:`~psfkit.forward.fft`
(the only FFT entry points), :mod:`~psfkit.forward.convolution` (pad/crop, kernel spectra,
Eq. 7), :mod:`~psfkit.forward.padded_scene` (scene on the whole padded grid),
:mod:`~psfkit.forward.base` (:class:`LinearOperator`), :mod:`~psfkit.forward.operator` (the
operator of a kernel file), :mod:`~psfkit.forward.kernel_space` (the fit-pairs form) and
:mod:`~psfkit.forward.norm` (``‖A‖`` by power iteration).

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
    "kernel_spectra": "convolution",
    "eigen_kernel_forward": "convolution", "eigen_kernel_adjoint": "convolution",
    "padded_scene_forward": "padded_scene", "padded_scene_adjoint": "padded_scene",
    "padded_scene_adjoint_spectrum": "padded_scene", "kernel_images": "padded_scene",
    "sum_of_kernel_products": "convolution",
    "zero_workspace": "convolution",
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
