r"""Dense shift-variant forward model: PSFs interpolated bilinearly over the field.

A grid of ``N × M`` field points ("nodes") has PSFs ``K_n`` (each re-centred on its chief ray,
origin at the array centre) at sensor positions ``(v_n, u_n)`` (where the chief ray lands).
The PSF of a scene point at pixel ``p`` is the piecewise-bilinear interpolation
``h_p = Σ_n w_n(p) K_n`` with hat functions ``w_n`` on the node grid (a partition of unity,
constant beyond the outermost nodes). Summing over scene points:

.. math::

    y = \sum_n \mathrm{crop}\big(K_n * \mathrm{pad}(w_n \odot x)\big)
    \quad\text{("source" convention, exact per-point interpolation)}

or ``y = Σ_n w_n ⊙ crop(K_n * pad(x))`` (``"sensor"``: the weights act on the sensor pixels).
Each term is one FFT convolution, so the cost is ``N·M`` convolutions per image (81 for a
9 × 9 grid) — a far richer model than the 3-kernel eigen-kernel model, which is why the
virtual bench uses it to simulate measurements. The convolutions are those of the one forward
model, :func:`psfkit.forward.convolution.eigen_kernel_forward`, with ``N·M`` kernels.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ekdun.errors import ConfigurationError, KernelShapeError, TensorShapeError
from psfkit.forward.convolution import eigen_kernel_forward, kernel_spectra
from psfkit.forward.geometry import CONVENTIONS, padded_shape


def hat_weights(nodes: np.ndarray, size: int) -> np.ndarray:
    """1-D piecewise-linear hat functions ``(len(nodes), size)`` at pixels ``0..size-1``.

    ``nodes`` must be increasing; pixels beyond the first (last) node get weight 1 on it.
    The rows sum to 1 at every pixel.
    """
    nodes = np.asarray(nodes, dtype=np.float64)
    if nodes.ndim != 1 or nodes.size < 1 or np.any(np.diff(nodes) <= 0):
        raise ConfigurationError("node coordinates must be a strictly increasing 1-D array")
    x = np.arange(size, dtype=np.float64)
    out = np.zeros((nodes.size, size))
    if nodes.size == 1:
        out[0] = 1.0
        return out
    xc = np.clip(x, nodes[0], nodes[-1])
    j = np.clip(np.searchsorted(nodes, xc, side="right") - 1, 0, nodes.size - 2)
    t = (xc - nodes[j]) / (nodes[j + 1] - nodes[j])
    out[j, np.arange(size)] = 1.0 - t
    out[j + 1, np.arange(size)] += t
    return out


class DenseShiftVariantModel:
    """``y = A x`` with per-pixel bilinear interpolation of a grid of PSFs.

    Parameters
    ----------
    kernels : array ``(N, M, C, Hk, Wk)``
        Node PSFs re-centred on their chief ray (origin at ``(Hk//2, Wk//2)``), in measurement
        units per unit scene radiance (gains kept).
    node_rows, node_cols : array
        Sensor row coordinates of the ``N`` node rows and column coordinates of the ``M`` node
        columns (increasing).
    sensor_shape : (int, int)
        ``(H', W')``.
    convention : {"source", "sensor"}
        Where the interpolation weights act (see the module docstring).
    scene_padding : int
        Convolution grid as a multiple of the sensor size.
    """

    def __init__(self, kernels: np.ndarray | Tensor, node_rows: np.ndarray,
                 node_cols: np.ndarray, sensor_shape: tuple[int, int],
                 convention: str = "source", scene_padding: int = 2) -> None:
        k = torch.tensor(np.array(kernels, dtype=np.float64))
        if k.ndim != 5 or k.shape[0] != len(node_rows) or k.shape[1] != len(node_cols):
            raise KernelShapeError(f"kernels must be (N, M, C, Hk, Wk) with N = {len(node_rows)}"
                                   f", M = {len(node_cols)}; got {tuple(k.shape)}")
        if convention not in CONVENTIONS:
            raise ConfigurationError(f"convention must be 'source' or 'sensor', got "
                                     f"{convention!r}")
        h, w = int(sensor_shape[0]), int(sensor_shape[1])
        if k.shape[-2] > h or k.shape[-1] > w:
            raise KernelShapeError(f"kernels {k.shape[-2]}x{k.shape[-1]} exceed the sensor "
                                   f"{h}x{w}")
        self.sensor_shape = (h, w)
        self.convention = convention
        self.grid_shape = padded_shape((h, w), scene_padding)
        n, m, c = k.shape[:3]
        self.channels = int(c)
        wy = hat_weights(node_rows, h)            # (N, H)
        wx = hat_weights(node_cols, w)            # (M, W)
        self.weights = torch.as_tensor(
            np.einsum("ih,jw->ijhw", wy, wx).reshape(n * m, h, w), dtype=torch.float64)
        flat = k.reshape(n * m, c, k.shape[-2], k.shape[-1])
        self.spectra = kernel_spectra(flat, self.grid_shape)     # (NM, C, PH, PW//2+1)

    @property
    def device(self) -> torch.device:
        """Where the model computes (its spectra and weights live)."""
        return self.spectra.device

    def to(self, device: str | torch.device) -> DenseShiftVariantModel:
        """Move the model to ``device`` (in place; returns ``self``). Still float64: a GPU
        gives the same measurements to rounding (~1e-16 relative), far below the noise."""
        self.spectra = self.spectra.to(device)
        self.weights = self.weights.to(device)
        return self

    def __call__(self, x: Tensor | np.ndarray) -> Tensor:
        """Forward model for scenes ``(B, C, H', W')`` (or one ``(C, H', W')``), float64, on
        the model's device."""
        t = torch.as_tensor(np.asarray(x) if not isinstance(x, Tensor) else x,
                            dtype=torch.float64).to(self.device)
        single = t.ndim == 3
        if single:
            t = t[None]
        if t.ndim != 4 or tuple(t.shape[-2:]) != self.sensor_shape or \
                t.shape[1] != self.channels:
            raise TensorShapeError(f"scene must be (B, {self.channels}, {self.sensor_shape[0]},"
                                   f" {self.sensor_shape[1]}), got {tuple(t.shape)}")
        out = eigen_kernel_forward(t, self.spectra, self.weights, self.grid_shape,
                                   self.convention)
        return out[0] if single else out
