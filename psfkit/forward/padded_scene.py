"""Eq. 7 with the scene on the whole padded grid: light from outside the sensor's view.

:func:`padded_scene_forward` and its exact adjoint (the classical solvers' operator), and the
pieces ADMM keeps apart (:func:`kernel_images`, :func:`padded_scene_adjoint_spectrum`).
Conventions as in :mod:`psfkit.forward.convolution`.
"""

from __future__ import annotations

import torch
from torch import Tensor

from psfkit.forward.convolution import (
    crop,
    fan_in,
    fan_out,
    pad,
    records_model_graph,
    sum_of_kernel_products,
)
from psfkit.forward.fft import irfft2, rfft2
from psfkit.forward.geometry import centre_offset


def _to_corner(z: Tensor, sensor_shape: tuple[int, int], back: bool = False) -> Tensor:
    """Circularly shift a padded-grid array so that its centred view block is top-left (with
    ``back``: the inverse and adjoint shift)."""
    top, left = centre_offset(sensor_shape, tuple(z.shape[-2:]))
    return torch.roll(z, shifts=(top, left) if back else (-top, -left), dims=(-2, -1))


def padded_scene_forward(x: Tensor, spectra: Tensor, weights: Tensor | None,
                         sensor_shape: tuple[int, int], convention: str = "sensor") -> Tensor:
    r"""Eq. 7 with the scene on the whole padded grid (light from outside the view).

    .. math::

        \text{sensor:}\quad y = \sum_k W_k \odot \mathrm{crop}(K_k \circledast x),
        \qquad
        \text{source:}\quad y = \mathrm{crop}\Big(\sum_k K_k \circledast
        (V_k \odot x)\Big),

    with ``V_k`` the scene weights, edge-continued outside the view (``KernelModel.weight_maps``
    with ``extent``). ``padded_scene_forward(pad(x)) == eigen_kernel_forward(x)``.

    Parameters
    ----------
    x : Tensor
        Scene ``(B, C, PH, PW)``.
    spectra : Tensor
        ``(K, C, PH, PW//2 + 1)`` kernel spectra.
    weights : Tensor or None
        Sensor side ``(K, H', W')``, source side ``(K, PH, PW)``; ``None``: one kernel, weight 1.
    sensor_shape : (int, int)
        ``(H', W')``.
    convention : {"sensor", "source"}

    Returns
    -------
    Tensor
        ``(B, C, H', W')``.
    """
    grid = (x.shape[-2], x.shape[-1])
    graph = records_model_graph(x, spectra, weights)
    # the crop is centred: shift the view to the top-left corner, where irfft2 crops cheaply
    shifted = _to_corner(x, sensor_shape)
    if convention == "sensor" or weights is None:
        return fan_out(rfft2(shifted), spectra, weights, grid, sensor_shape, graph)
    scene_weights = _to_corner(weights, sensor_shape)
    return fan_in(lambda k: rfft2(shifted * scene_weights[k]), spectra, grid, sensor_shape,
                   graph)


def padded_scene_adjoint(y: Tensor, conj_spectra: Tensor, weights: Tensor | None,
                         grid_shape: tuple[int, int], convention: str = "sensor") -> Tensor:
    r"""The exact adjoint of :func:`padded_scene_forward`.

    .. math::

        \text{sensor:}\quad A^\top y = \sum_k K_k \star \mathrm{pad}(W_k \odot y),
        \qquad
        \text{source:}\quad A^\top y = \sum_k V_k \odot \big(K_k \star
        \mathrm{pad}(y)\big).

    ``y`` ``(B, C, H', W')``, ``conj_spectra`` the conjugated spectra; returns ``(B, C, PH, PW)``.
    """
    sensor = (y.shape[-2], y.shape[-1])
    graph = records_model_graph(y, conj_spectra, weights)
    if convention == "sensor" and weights is not None:
        corner = fan_in(lambda k: rfft2(y * weights[k], grid_shape), conj_spectra,
                         grid_shape, grid_shape, graph)
    else:
        scene_weights = None if weights is None else _to_corner(weights, sensor)
        corner = fan_out(rfft2(y, grid_shape), conj_spectra, scene_weights, grid_shape,
                          grid_shape, graph)
    return _to_corner(corner, sensor, back=True)


def kernel_images(scene_spectrum: Tensor, spectra: Tensor, grid_shape: tuple[int, int],
                  sensor_shape: tuple[int, int] | None = None) -> Tensor:
    """``crop(K_k ⊛ x)`` for every kernel, from the spectrum of a padded-grid scene (ADMM's split
    ``u_k = H_k x``).

    Parameters
    ----------
    scene_spectrum : Tensor
        ``(..., C, PH, PW//2 + 1)``, ``rfft2`` of the scene.
    spectra : Tensor
        Kernel spectra broadcastable against it, e.g. ``(K, C, PH, PW//2 + 1)``.
    grid_shape : (int, int)
        ``(PH, PW)``.
    sensor_shape : (int, int), optional
        Keep the centred ``(H', W')`` view; ``None``: the whole grid.

    Returns
    -------
    Tensor
        ``(K, ..., H', W')`` (or the grid) real.
    """
    images = irfft2(spectra * scene_spectrum, grid_shape)
    return images if sensor_shape is None else crop(images, sensor_shape)


def padded_scene_adjoint_spectrum(y: Tensor, conj_spectra: Tensor, weights: Tensor | None,
                                  grid_shape: tuple[int, int]) -> Tensor:
    """``rfft2`` of the sensor-side :func:`padded_scene_adjoint`, ``Σ_k K̂_k^* · F(pad(W_k ⊙ y))``.

    For a Fourier-diagonal inverse applied before transforming back (ADMM's ``x`` update).
    ``y`` ``(..., C, H', W')``, ``conj_spectra`` ``(K, C, PH, PW//2 + 1)``, ``weights``
    ``(K, H', W')`` or ``None``; returns ``(..., C, PH, PW//2 + 1)`` complex.
    """
    graph = records_model_graph(y, conj_spectra, weights)
    return sum_of_kernel_products(
        lambda k: rfft2(pad(y if weights is None else y * weights[k], grid_shape)),
        conj_spectra, graph)
