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
:func:`eigen_kernel_adjoint`; the kernel-space form used to fit kernels from pairs is
:mod:`psfkit.forward.kernel_space`.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import Tensor

from psfkit.forward.fft import irfft2, rfft2
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
    hk, wk = kernel_shape
    row, col = kernel_origin((hk, wk))
    ph, pw = full.shape[-2:]
    # the window's wrapped rows, then columns (a roll of the whole grid copied all of it)
    rows = torch.cat([full[..., ph - row:, :], full[..., :hk - row, :]], dim=-2)
    return torch.cat([rows[..., pw - col:], rows[..., :wk - col]], dim=-1)


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


def _fan_out(x_hat: Tensor, spectra: Tensor, weights: Tensor | None,
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
                           graph: bool) -> Tensor:
    """``Σ_k Ŝ_k · spectrum_of(k)``: the kernel-by-input products of Eq. 7 summed in the
    Fourier domain (source-side forward, sensor-side adjoint, before the inverse FFT).

    ``spectrum_of(k)`` gives the spectrum of the ``k``-th (weighted) input ``(..., C, PH,
    PW//2+1)``; outside autograd (``graph`` false) the first is overwritten with the sum.
    """
    acc: Tensor | None = None
    for k in range(spectra.shape[0]):
        term = spectrum_of(k)
        if graph:
            term = term * spectra[k]
            acc = term if acc is None else acc + term
        elif acc is None:
            acc = term.mul_(spectra[k])
        else:
            acc.addcmul_(term, spectra[k])
    assert acc is not None
    return acc


def _fan_in(spectrum_of: Callable[[int], Tensor], spectra: Tensor,
            grid_shape: tuple[int, int], block: tuple[int, int], graph: bool) -> Tensor:
    r"""``irfft2(Σ_k Ŝ_k · spectrum_of(k))[:h, :w]``: K input spectra, 1 inverse FFT.

    The sum over kernels is taken in the Fourier domain so that one inverse FFT suffices
    (source-side forward, sensor-side adjoint); ``spectrum_of(k)`` is the spectrum of the
    ``k``-th weighted input (a fresh array: it is overwritten outside autograd).
    """
    return irfft2(sum_of_kernel_products(spectrum_of, spectra, graph), grid_shape, block)


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
    padded_scene_forward : the same model with the scene on the whole padded grid.
    """
    sensor = (x.shape[-2], x.shape[-1])
    graph = _records(x, spectra, weights)
    ws = None if graph else workspace
    if convention == "sensor" or weights is None:
        return _fan_out(_spectrum_of_corner(x, grid_shape, ws), spectra, weights, grid_shape,
                        sensor, graph)
    return _fan_in(lambda k: _spectrum_of_corner(x, grid_shape, ws, weights[k]), spectra,
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
    graph = _records(y, conj_spectra, weights)
    ws = None if graph else workspace
    if convention == "sensor" and weights is not None:
        return _fan_in(lambda k: _spectrum_of_corner(y, grid_shape, ws, weights[k]),
                       conj_spectra, grid_shape, sensor, graph)
    return _fan_out(_spectrum_of_corner(y, grid_shape, ws), conj_spectra, weights,
                    grid_shape, sensor, graph)


def _to_corner(z: Tensor, sensor_shape: tuple[int, int]) -> Tensor:
    """Circularly shift a padded-grid array so that its centred view block is top-left."""
    top, left = centre_offset(sensor_shape, tuple(z.shape[-2:]))
    return torch.roll(z, shifts=(-top, -left), dims=(-2, -1))


def _from_corner(z: Tensor, sensor_shape: tuple[int, int]) -> Tensor:
    """Inverse of :func:`_to_corner` (its adjoint too: a circular shift is orthogonal)."""
    top, left = centre_offset(sensor_shape, tuple(z.shape[-2:]))
    return torch.roll(z, shifts=(top, left), dims=(-2, -1))


def padded_scene_forward(x: Tensor, spectra: Tensor, weights: Tensor | None,
                         sensor_shape: tuple[int, int], convention: str = "sensor") -> Tensor:
    r"""Eq. 7 with the scene on the whole padded grid (light from outside the view).

    .. math::

        \text{sensor:}\quad y = \sum_k W_k \odot \mathrm{crop}(K_k \circledast x),
        \qquad
        \text{source:}\quad y = \mathrm{crop}\Big(\sum_k K_k \circledast
        (V_k \odot x)\Big),

    with ``W_k`` ``(K, H', W')`` the sensor weights and ``V_k`` ``(K, PH, PW)`` the scene
    weights on the whole grid (edge-continued outside the view:
    :meth:`psfkit.forward.kernelfile.KernelModel.weight_maps` with ``extent``). For a scene zero
    outside
    the view, ``padded_scene_forward(pad(x)) == eigen_kernel_forward(x)``. Sensor side: 1 FFT
    and K inverse FFTs; source side: K FFTs and 1 inverse FFT.

    Parameters
    ----------
    x : Tensor
        Scene ``(B, C, PH, PW)``.
    spectra : Tensor
        ``(K, C, PH, PW//2 + 1)`` kernel spectra (:func:`kernel_spectra`).
    weights : Tensor or None
        Sensor side ``(K, H', W')``, source side ``(K, PH, PW)``; ``None`` for one kernel with
        weight 1.
    sensor_shape : (int, int)
        ``(H', W')``.
    convention : {"sensor", "source"}

    Returns
    -------
    Tensor
        Measurement ``(B, C, H', W')``.
    """
    grid = (x.shape[-2], x.shape[-1])
    graph = _records(x, spectra, weights)
    # the crop is centred: shift the view to the top-left corner, where irfft2 crops cheaply
    shifted = _to_corner(x, sensor_shape)
    if convention == "sensor" or weights is None:
        return _fan_out(rfft2(shifted), spectra, weights, grid, sensor_shape, graph)
    scene_weights = _to_corner(weights, sensor_shape)
    return _fan_in(lambda k: rfft2(shifted * scene_weights[k]), spectra, grid, sensor_shape,
                   graph)


def padded_scene_adjoint(y: Tensor, conj_spectra: Tensor, weights: Tensor | None,
                         grid_shape: tuple[int, int], convention: str = "sensor") -> Tensor:
    r"""The exact adjoint of :func:`padded_scene_forward`.

    .. math::

        \text{sensor:}\quad A^\top y = \sum_k K_k \star \mathrm{pad}(W_k \odot y),
        \qquad
        \text{source:}\quad A^\top y = \sum_k V_k \odot \big(K_k \star
        \mathrm{pad}(y)\big).

    ``y`` is ``(B, C, H', W')``, ``conj_spectra`` the conjugated kernel spectra, ``weights``
    as in :func:`padded_scene_forward`; returns the ``(B, C, PH, PW)`` scene. Sensor side:
    K FFTs and 1 inverse FFT; source side: 1 FFT and K inverse FFTs.
    """
    sensor = (y.shape[-2], y.shape[-1])
    graph = _records(y, conj_spectra, weights)
    if convention == "sensor" and weights is not None:
        corner = _fan_in(lambda k: rfft2(y * weights[k], grid_shape), conj_spectra,
                         grid_shape, grid_shape, graph)
    else:
        scene_weights = None if weights is None else _to_corner(weights, sensor)
        corner = _fan_out(rfft2(y, grid_shape), conj_spectra, scene_weights, grid_shape,
                          grid_shape, graph)
    return _from_corner(corner, sensor)


def kernel_images(scene_spectrum: Tensor, spectra: Tensor, grid_shape: tuple[int, int],
                  sensor_shape: tuple[int, int] | None = None) -> Tensor:
    r"""``crop(K_k ⊛ x)`` for every kernel, from the spectrum of a padded-grid scene.

    The images that sensor-side weights multiply in Eq. 7 (:func:`padded_scene_forward` sums
    them weighted), for solvers that keep them apart (ADMM's split ``u_k = H_k x``) and that
    already hold ``x̂`` (after a Fourier-diagonal update).

    Parameters
    ----------
    scene_spectrum : Tensor
        ``(..., C, PH, PW//2 + 1)``, ``rfft2`` of the ``(..., C, PH, PW)`` scene.
    spectra : Tensor
        Kernel spectra broadcastable against it, e.g. ``(K, C, PH, PW//2 + 1)``.
    grid_shape : (int, int)
        ``(PH, PW)``.
    sensor_shape : (int, int), optional
        Keep the centred ``(H', W')`` view (the crop); ``None``: the whole grid (``H_k x``).

    Returns
    -------
    Tensor
        ``(K, ..., H', W')`` (or the grid) real.
    """
    images = irfft2(spectra * scene_spectrum, grid_shape)
    return images if sensor_shape is None else crop(images, sensor_shape)


def padded_scene_adjoint_spectrum(y: Tensor, conj_spectra: Tensor, weights: Tensor | None,
                                  grid_shape: tuple[int, int]) -> Tensor:
    r"""``rfft2`` of the sensor-side :func:`padded_scene_adjoint`:
    ``Σ_k K̂_k^* · F(pad(W_k ⊙ y))`` (K FFTs, no inverse).

    For solvers that apply a Fourier-diagonal inverse to ``Aᵀy`` before transforming back
    (ADMM's ``x`` update), which saves the inverse FFT.

    Parameters
    ----------
    y : Tensor
        ``(..., C, H', W')``.
    conj_spectra : Tensor
        ``(K, C, PH, PW//2 + 1)`` conjugated kernel spectra.
    weights : Tensor or None
        ``(K, H', W')`` sensor weights, or ``None`` (one kernel, weight 1).
    grid_shape : (int, int)

    Returns
    -------
    Tensor
        ``(..., C, PH, PW//2 + 1)`` complex.
    """
    graph = _records(y, conj_spectra, weights)
    return sum_of_kernel_products(
        lambda k: rfft2(pad(y if weights is None else y * weights[k], grid_shape)),
        conj_spectra, graph)


def _records(t: Tensor, spectra: Tensor, weights: Tensor | None) -> bool:
    return records_graph(t, spectra) or (weights is not None and weights.requires_grad)


def zero_workspace(like: Tensor, grid_shape: tuple[int, int]) -> Tensor:
    """A zero ``(..., PH, PW)`` workspace for inputs shaped like ``like`` ``(..., H', W')``."""
    return like.new_zeros((*like.shape[:-2], *grid_shape))

