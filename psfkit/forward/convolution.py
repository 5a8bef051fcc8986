r"""Pure FFT kernels of the lensless forward model and its exact adjoint.

Scene ``x`` and measurement ``y`` are both ``(B, C, H', W')``; the convolution runs on a padded
grid ``(P·H', P·W')`` (``P = scene_padding >= 2``, ``docs/architecture.md``):

.. math::

    y = \mathrm{crop}\big(K \circledast \mathrm{pad}(x)\big), \qquad
    A^\top y = \mathrm{crop}\big(K \star \mathrm{pad}(y)\big),

with :func:`pad` / :func:`crop` (exact adjoints) the centred zero-fill and block, ``⊛`` the
circular convolution and ``⋆`` the circular cross-correlation. A kernel (at most ``H' × W'``)
has its origin at its centre pixel ``(Hk//2, Wk//2)``; since ``H' + Hk − 1 < P·H'`` the
circular convolution never wraps, so the model is exactly the linear convolution. Eigen-kernel
models (Eq. 7) sum ``K`` such convolutions with weight maps ``W_k`` (:func:`eigen_kernel_forward`).
All FFTs go through :mod:`psfkit.forward.fft`; every function is differentiable.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from psfkit.forward.fft import irfft2, rfft2
from psfkit.forward.geometry import centre_offset, kernel_origin


def pad(x: Tensor, grid_shape: tuple[int, int]) -> Tensor:
    """Zero-fill ``x`` ``(..., H', W')`` into the centre of a ``grid_shape`` ``(PH, PW)`` array.

    The adjoint of :func:`crop`; returns ``(..., PH, PW)``.
    """
    h, w = x.shape[-2:]
    top, left = centre_offset((h, w), grid_shape)
    return F.pad(x, (left, grid_shape[1] - w - left, top, grid_shape[0] - h - top))


def crop(z: Tensor, sensor_shape: tuple[int, int]) -> Tensor:
    """The central ``sensor_shape`` block of ``z`` ``(..., PH, PW)`` (a view), adjoint of pad."""
    top, left = centre_offset(sensor_shape, tuple(z.shape[-2:]))
    return z[..., top:top + sensor_shape[0], left:left + sensor_shape[1]]


def embed_kernel(kernels: Tensor, grid_shape: tuple[int, int]) -> Tensor:
    """Place centred kernels ``(..., Hk, Wk)`` on the ``(PH, PW)`` grid, origin at ``(0, 0)``.

    Returns ``(..., PH, PW)``: ``out[(i − Hk//2) mod PH, (j − Wk//2) mod PW] = kernels[i, j]``.
    """
    hk, wk = kernels.shape[-2:]
    row, col = kernel_origin((hk, wk))
    if records_graph(kernels):
        grown = F.pad(kernels, (0, grid_shape[1] - wk, 0, grid_shape[0] - hk))
        return torch.roll(grown, shifts=(-row, -col), dims=(-2, -1))
    # outside autograd the four quadrants are written in place: the pad and the roll each
    # copied the whole grid (a fit-pairs profile: a quarter of its time)
    ph, pw = grid_shape
    out = kernels.new_zeros((*kernels.shape[:-2], ph, pw))
    out[..., :hk - row, :wk - col] = kernels[..., row:, col:]
    out[..., :hk - row, pw - col:] = kernels[..., row:, :col]
    out[..., ph - row:, :wk - col] = kernels[..., :row, col:]
    out[..., ph - row:, pw - col:] = kernels[..., :row, :col]
    return out


def kernels_from_spectra(spectra: Tensor, grid_shape: tuple[int, int],
                         kernel_shape: tuple[int, int]) -> Tensor:
    """The centred ``(..., Hk, Wk)`` window of ``irfft2(spectra)``, inverting only its rows and
    columns (:func:`irfft2` with a wrapped block)."""
    row, col = kernel_origin(kernel_shape)
    return irfft2(spectra, grid_shape, kernel_shape, start=(-row, -col))


def kernel_spectra(kernels: Tensor, grid_shape: tuple[int, int]) -> Tensor:
    """Half spectra ``rfft2(embed_kernel(kernels))``, ``(..., PH, PW//2 + 1)`` complex."""
    return rfft2(embed_kernel(kernels, grid_shape))


def _spectrum_of_corner(z: Tensor, grid_shape: tuple[int, int], workspace: Tensor | None,
                        weight: Tensor | None = None) -> Tensor:
    """``rfft2`` of ``z`` (times ``weight``) zero-padded at the end of the grid.

    A ``workspace`` (zero outside its top-left block) is filled in place and transformed whole,
    cheaper than letting ``rfft2`` allocate a padded copy on each call.
    """
    if workspace is None:
        return rfft2(z if weight is None else z * weight, grid_shape)
    corner = workspace[..., :z.shape[-2], :z.shape[-1]]
    if weight is None:
        corner.copy_(z)
    else:
        torch.mul(z, weight, out=corner)
    return rfft2(workspace)


def records_graph(*tensors: Tensor) -> bool:
    """Whether autograd records operations on ``tensors`` (else buffers may be reused)."""
    return torch.is_grad_enabled() and any(t.requires_grad for t in tensors)


def fan_out(x_hat: Tensor, spectra: Tensor, weights: Tensor | None,
             grid_shape: tuple[int, int], block: tuple[int, int], graph: bool,
             overwrite: bool = True) -> Tensor:
    """``Σ_k W_k ⊙ irfft2(X̂ · Ŝ_k)[:h, :w]``: K inverse FFTs of one input spectrum.

    Only the top-left ``block`` ``(h, w)`` is computed and weighted (``W_k`` ``(K, h, w)``).
    Outside autograd the products reuse one buffer, and ``x_hat`` itself when ``overwrite``.
    """
    n_kernels = spectra.shape[0]
    product: Tensor | None = None
    out: Tensor | None = None
    for k in range(n_kernels):
        if graph:
            product = x_hat * spectra[k]
        elif n_kernels == 1 and overwrite:
            product = x_hat.mul_(spectra[k])           # x_hat is not needed any more
        else:
            product = torch.mul(x_hat, spectra[k], out=product)
        image = irfft2(product, grid_shape, block)
        if weights is None:
            out = image if out is None else out + image
        elif out is None:
            out = image * weights[k]
        elif graph:
            out = torch.addcmul(out, image, weights[k])
        else:
            out.addcmul_(image, weights[k])
    assert out is not None  # at least one kernel (checked by the operators)
    return out


def sum_of_kernel_products(spectrum_of: Callable[[int], Tensor], spectra: Tensor,
                           graph: bool, fresh: bool = True) -> Tensor:
    """``Σ_k Ŝ_k · spectrum_of(k)``: Eq. 7's kernel-by-input products summed in the Fourier domain.

    Outside autograd the first ``spectrum_of(0)`` is overwritten with the sum unless it is not
    ``fresh`` (e.g. cached spectra).
    """
    acc: Tensor | None = None
    for k in range(spectra.shape[0]):
        term = spectrum_of(k)
        if graph:
            term = term * spectra[k]
            acc = term if acc is None else acc + term
        elif acc is None:
            acc = term.mul_(spectra[k]) if fresh else torch.mul(term, spectra[k])
        else:
            acc.addcmul_(term, spectra[k])
    assert acc is not None
    return acc


def fan_in(spectrum_of: Callable[[int], Tensor], spectra: Tensor,
            grid_shape: tuple[int, int], block: tuple[int, int], graph: bool,
            fresh: bool = True) -> Tensor:
    """``irfft2(Σ_k Ŝ_k · spectrum_of(k))[:h, :w]``: K input spectra, 1 inverse FFT."""
    return irfft2(sum_of_kernel_products(spectrum_of, spectra, graph, fresh), grid_shape,
                  block)


def eigen_kernel_forward(x: Tensor, spectra: Tensor, weights: Tensor | None,
                         grid_shape: tuple[int, int], convention: str = "sensor",
                         workspace: Tensor | None = None) -> Tensor:
    r"""Apply the eigen-kernel forward model ``A`` (Eq. 7) to a sensor-sized scene.

    .. math::

        \text{sensor:}\quad y = \sum_k W_k \odot \mathrm{crop}\big(K_k \circledast
        \mathrm{pad}(x)\big), \qquad
        \text{source:}\quad y = \mathrm{crop}\Big(\sum_k K_k \circledast
        \mathrm{pad}(W_k \odot x)\Big).

    Sensor side: 1 FFT and K inverse FFTs; source side: K FFTs and 1 inverse (the centring
    shift cancels between ``pad`` and ``crop``, so the top-left block is kept).

    Parameters
    ----------
    x : Tensor
        Scene ``(B, C, H', W')``, real.
    spectra : Tensor
        ``(K, C, PH, PW//2 + 1)`` complex (:func:`kernel_spectra`), ``x``'s precision.
    weights : Tensor or None
        ``(K, H', W')`` weight maps; ``None``: one kernel of weight 1.
    grid_shape : (int, int)
        ``(PH, PW)``.
    convention : {"sensor", "source"}
    workspace : Tensor, optional
        ``(B, C, PH, PW)``, reused outside autograd (:func:`zero_workspace`).

    Returns
    -------
    Tensor
        Measurement ``(B, C, H', W')``.
    """
    return _eigen_kernels(x, spectra, weights, grid_shape, workspace,
                          weighted_input=convention != "sensor")


def eigen_kernel_adjoint(y: Tensor, conj_spectra: Tensor, weights: Tensor | None,
                         grid_shape: tuple[int, int], convention: str = "sensor",
                         workspace: Tensor | None = None) -> Tensor:
    r"""Apply the exact adjoint ``Aᵀ`` of :func:`eigen_kernel_forward`.

    .. math::

        \text{sensor:}\quad A^\top y = \mathrm{crop}\Big(\sum_k K_k \star
        \mathrm{pad}(W_k \odot y)\Big), \qquad
        \text{source:}\quad A^\top y = \sum_k W_k \odot \mathrm{crop}\big(K_k \star
        \mathrm{pad}(y)\big).

    Shapes as in :func:`eigen_kernel_forward`, but ``conj_spectra`` are the conjugated spectra,
    materialised (``spectra.conj().resolve_conj()``, once per forward pass).
    """
    return _eigen_kernels(y, conj_spectra, weights, grid_shape, workspace,
                          weighted_input=convention == "sensor")


def _eigen_kernels(t: Tensor, spectra: Tensor, weights: Tensor | None,
                   grid_shape: tuple[int, int], workspace: Tensor | None,
                   weighted_input: bool) -> Tensor:
    """``A`` or ``Aᵀ``: K weighted inputs and 1 inverse FFT, or 1 input and K inverse FFTs."""
    sensor = (t.shape[-2], t.shape[-1])
    graph = records_model_graph(t, spectra, weights)
    ws = None if graph else workspace
    if weighted_input and weights is not None:
        return fan_in(lambda k: _spectrum_of_corner(t, grid_shape, ws, weights[k]), spectra,
                      grid_shape, sensor, graph)
    return fan_out(_spectrum_of_corner(t, grid_shape, ws), spectra, weights, grid_shape,
                   sensor, graph)


def records_model_graph(t: Tensor, spectra: Tensor, weights: Tensor | None) -> bool:
    """Whether autograd records operations on ``t``, ``spectra`` or ``weights`` (or ``None``)."""
    return records_graph(t, spectra) or (weights is not None and weights.requires_grad)


def zero_workspace(like: Tensor, grid_shape: tuple[int, int]) -> Tensor:
    """A zero ``(..., PH, PW)`` workspace for inputs shaped like ``like`` ``(..., H', W')``."""
    return like.new_zeros((*like.shape[:-2], *grid_shape))
