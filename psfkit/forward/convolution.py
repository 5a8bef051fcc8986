r"""Pure FFT kernels of the lensless forward model and its exact adjoint.

Conventions (``docs/architecture.md``)
----------------------------------
The scene ``x`` and the measurement ``y`` are both ``(B, C, H', W')`` (the sensor's size). The
convolution runs on a padded grid ``(P·H', P·W')`` (``P = scene_padding >= 2``):

.. math::

    y = \mathrm{crop}\big(K \circledast \mathrm{pad}(x)\big),

where :func:`pad` zero-fills ``x`` into the centre of the padded grid (rows
``[(P·H'−H')//2, (P·H'−H')//2 + H')``, likewise for columns), ``⊛`` is the circular
convolution computed with ``rfft2``/``irfft2`` on that grid, and :func:`crop` keeps the same
central block. :func:`crop` and :func:`pad` are exact adjoints of each other, so

.. math::

    A^\top y = \mathrm{crop}\big(K \star \mathrm{pad}(y)\big),

with ``⋆`` the circular cross-correlation (multiplication by the conjugate spectrum).

A kernel is an array of at most ``H' × W'`` whose origin is its centre pixel
``(Hk//2, Wk//2)``, the way a PSF image looks; :func:`embed_kernel` moves that origin to index
``(0, 0)`` of the padded grid. A point source at the scene's centre pixel ``(H'//2, W'//2)``
therefore images to the kernel itself (for an ``H' × W'`` kernel), and the linear convolution of
an ``H'``-row scene with an ``Hk <= H'``-row kernel has ``H' + Hk − 1 < P·H'`` rows, so the
circular convolution never wraps: the model is exactly the linear convolution
``scipy.signal.convolve(x, K, mode="full")`` shifted by the kernel origin and cropped.

Eigen-kernel models (Eq. 7 of the paper) sum ``K`` such convolutions with weight maps ``W_k``
``(K, H', W')``; see :func:`eigen_kernel_forward`. Every 2-D FFT goes through :func:`rfft2`
and every inverse through :func:`irfft2` (:mod:`psfkit.forward.fft`, wrappers of
:mod:`torch.fft`), which keeps the FFT count of every operator easy to audit
(:func:`~psfkit.forward.fft.count_ffts`). Every function here is differentiable and works for
float32 and float64 on any device. ekdun's operator classes (:mod:`ekdun.physics.operators`) are
thin :class:`torch.nn.Module` wrappers over :func:`eigen_kernel_forward` and
:func:`eigen_kernel_adjoint`; the same model with the scene on the whole padded grid is
:mod:`psfkit.forward.padded_scene`, the kernel-space form used to fit kernels from pairs
:mod:`psfkit.forward.kernel_space`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from psfkit.forward.fft import irfft2, rfft2, wrapped_slice
from psfkit.forward.geometry import centre_offset, kernel_origin


def pad(x: Tensor, grid_shape: tuple[int, int]) -> Tensor:
    """Zero-fill ``x`` ``(..., H', W')`` into the centre of a ``grid_shape`` array.

    The adjoint of :func:`crop`.

    Parameters
    ----------
    x : Tensor
        ``(..., H', W')``.
    grid_shape : (int, int)
        ``(PH, PW)`` with ``PH >= H'`` and ``PW >= W'``.

    Returns
    -------
    Tensor
        ``(..., PH, PW)``, zero outside rows ``[top, top + H')`` and columns
        ``[left, left + W')`` (:func:`centre_offset`).
    """
    h, w = x.shape[-2:]
    top, left = centre_offset((h, w), grid_shape)
    return F.pad(x, (left, grid_shape[1] - w - left, top, grid_shape[0] - h - top))


def crop(z: Tensor, sensor_shape: tuple[int, int]) -> Tensor:
    """The central ``sensor_shape`` block of ``z`` ``(..., PH, PW)`` (a view, no copy).

    The adjoint of :func:`pad`.
    """
    top, left = centre_offset(sensor_shape, tuple(z.shape[-2:]))
    return z[..., top:top + sensor_shape[0], left:left + sensor_shape[1]]


def embed_kernel(kernels: Tensor, grid_shape: tuple[int, int]) -> Tensor:
    """Place centred kernels on the padded grid with their origin at index ``(0, 0)``.

    Parameters
    ----------
    kernels : Tensor
        ``(..., Hk, Wk)`` with the origin at ``(Hk//2, Wk//2)``; ``Hk <= PH``, ``Wk <= PW``.
    grid_shape : (int, int)
        ``(PH, PW)``.

    Returns
    -------
    Tensor
        ``(..., PH, PW)``: ``out[(i − Hk//2) mod PH, (j − Wk//2) mod PW] = kernels[i, j]``.
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


def extract_kernel(full: Tensor, kernel_shape: tuple[int, int]) -> Tensor:
    """Adjoint of :func:`embed_kernel`: the centred ``(Hk, Wk)`` kernel window of a
    ``(..., PH, PW)`` array whose origin is at index ``(0, 0)``, ``(..., Hk, Wk)``."""
    row, col = kernel_origin(kernel_shape)
    # the window's wrapped rows, then columns (a roll of the whole grid copied all of it)
    rows = wrapped_slice(full, -row, kernel_shape[0], -2)
    return wrapped_slice(rows, -col, kernel_shape[1], -1)


def kernels_from_spectra(spectra: Tensor, grid_shape: tuple[int, int],
                         kernel_shape: tuple[int, int]) -> Tensor:
    """``extract_kernel(irfft2(spectra), kernel_shape)``: the centred ``(Hk, Wk)`` kernels of
    spectra on the grid, computing only the window's rows and columns (:func:`irfft2` with a
    wrapped block; on the 7 DLMD pairs' grid 0.64× the time of the whole inverse)."""
    row, col = kernel_origin(kernel_shape)
    return irfft2(spectra, grid_shape, kernel_shape, start=(-row, -col))


def kernel_spectra(kernels: Tensor, grid_shape: tuple[int, int]) -> Tensor:
    """Half spectra ``rfft2(embed_kernel(kernels))``, ``(..., PH, PW//2 + 1)`` complex.

    Computed once per network forward pass (trainable kernels) or cached (fixed kernels) and
    passed to :func:`eigen_kernel_forward` / :func:`eigen_kernel_adjoint`.
    """
    return rfft2(embed_kernel(kernels, grid_shape))


def _spectrum_of_corner(z: Tensor, grid_shape: tuple[int, int], workspace: Tensor | None,
                        weight: Tensor | None = None) -> Tensor:
    """``rfft2`` of ``z`` (times ``weight``) zero-padded at the end of the grid.

    With a ``workspace`` (a ``(..., PH, PW)`` array that is zero outside its top-left block,
    reused outside autograd) the input is written into that block and the whole array is
    transformed: cheaper than letting ``rfft2`` allocate and zero a padded copy on each call.
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
    r"""``Σ_k W_k ⊙ irfft2(X̂ · Ŝ_k)[:h, :w]``: K inverse FFTs of one input spectrum.

    The one place where a scene's spectrum meets the kernel spectra one kernel at a time
    (sensor-side forward, source-side adjoint, shift-invariant both). Only the top-left
    ``block`` ``(h, w)`` of each image is computed and weighted (``W_k`` ``(K, h, w)``).
    Outside autograd the spectrum products reuse one buffer (allocating large arrays costs more
    than multiplying them), and ``x_hat`` itself when ``overwrite`` allows.
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
    """``Σ_k Ŝ_k · spectrum_of(k)``: the kernel-by-input products of Eq. 7 summed in the
    Fourier domain (source-side forward, sensor-side adjoint, before the inverse FFT).

    ``spectrum_of(k)`` gives the spectrum of the ``k``-th (weighted) input ``(..., C, PH,
    PW//2+1)``; outside autograd (``graph`` false) the first is overwritten with the sum,
    unless it is not ``fresh`` (e.g. cached spectra): then the sum is a new array.
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
    r"""``irfft2(Σ_k Ŝ_k · spectrum_of(k))[:h, :w]``: K input spectra, 1 inverse FFT.

    The sum over kernels is taken in the Fourier domain so that one inverse FFT suffices
    (source-side forward, sensor-side adjoint); ``spectrum_of(k)`` is the spectrum of the
    ``k``-th weighted input (overwritten outside autograd if ``fresh``).
    """
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

    The sensor side takes 1 FFT and K inverse FFTs, the source side K FFTs and 1 inverse FFT
    (each call transforms all ``B × C`` planes at once). Implementation: ``x`` is zero-padded
    at the end of the grid (inside the FFT) and the top-left ``H' × W'`` block is kept. This is
    the centred ``crop ∘ (K ⊛ ·) ∘ pad`` exactly: centring is a circular shift by
    :func:`centre_offset`, which commutes with the circular convolution and cancels between
    ``pad`` and ``crop``.

    Parameters
    ----------
    x : Tensor
        Scene ``(B, C, H', W')``, real.
    spectra : Tensor
        ``(K, C, PH, PW//2 + 1)`` complex, from :func:`kernel_spectra`; its dtype matches ``x``.
    weights : Tensor or None
        ``(K, H', W')`` weight maps, or ``None`` for a single kernel with weight 1
        (the shift-invariant model).
    grid_shape : (int, int)
        ``(PH, PW)``.
    convention : {"sensor", "source"}
        Whether the weights multiply each kernel's image (sensor) or the scene (source).
    workspace : Tensor, optional
        ``(B, C, PH, PW)`` array, zero outside its top-left ``H' × W'`` block, reused for the
        zero-padded FFT inputs when autograd is not recording (see :func:`zero_workspace`).

    Returns
    -------
    Tensor
        Measurement ``(B, C, H', W')``.

    See Also
    --------
    psfkit.forward.padded_scene.padded_scene_forward : the same model with the scene on the
        whole padded grid.
    """
    sensor = (x.shape[-2], x.shape[-1])
    graph = records_model_graph(x, spectra, weights)
    ws = None if graph else workspace
    if convention == "sensor" or weights is None:
        return fan_out(_spectrum_of_corner(x, grid_shape, ws), spectra, weights, grid_shape,
                        sensor, graph)
    return fan_in(lambda k: _spectrum_of_corner(x, grid_shape, ws, weights[k]), spectra,
                   grid_shape, sensor, graph)


def eigen_kernel_adjoint(y: Tensor, conj_spectra: Tensor, weights: Tensor | None,
                         grid_shape: tuple[int, int], convention: str = "sensor",
                         workspace: Tensor | None = None) -> Tensor:
    r"""Apply the exact adjoint ``Aᵀ`` of :func:`eigen_kernel_forward`.

    .. math::

        \text{sensor:}\quad A^\top y = \mathrm{crop}\Big(\sum_k K_k \star
        \mathrm{pad}(W_k \odot y)\Big), \qquad
        \text{source:}\quad A^\top y = \sum_k W_k \odot \mathrm{crop}\big(K_k \star
        \mathrm{pad}(y)\big):

    weight, correlate, sum. The sensor side takes K FFTs and 1 inverse FFT, the source side
    1 FFT and K inverse FFTs. Shapes as in :func:`eigen_kernel_forward` (``y`` is the
    measurement, the result a scene), except that ``conj_spectra`` are the **conjugated**
    kernel spectra (``spectra.conj().resolve_conj()``: multiplying by a lazy conjugate view
    costs an extra copy in every call, so callers conjugate once per forward pass).
    """
    sensor = (y.shape[-2], y.shape[-1])
    graph = records_model_graph(y, conj_spectra, weights)
    ws = None if graph else workspace
    if convention == "sensor" and weights is not None:
        return fan_in(lambda k: _spectrum_of_corner(y, grid_shape, ws, weights[k]),
                       conj_spectra, grid_shape, sensor, graph)
    return fan_out(_spectrum_of_corner(y, grid_shape, ws), conj_spectra, weights,
                    grid_shape, sensor, graph)


def records_model_graph(t: Tensor, spectra: Tensor, weights: Tensor | None) -> bool:
    """Whether autograd records operations on a model's input ``t``, its kernel ``spectra`` or
    its ``weights`` (``None``: no weights)."""
    return records_graph(t, spectra) or (weights is not None and weights.requires_grad)


def zero_workspace(like: Tensor, grid_shape: tuple[int, int]) -> Tensor:
    """A zero ``(..., PH, PW)`` workspace for inputs shaped like ``like`` ``(..., H', W')``."""
    return like.new_zeros((*like.shape[:-2], *grid_shape))
