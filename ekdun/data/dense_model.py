r"""Dense shift-variant forward model: PSFs interpolated bilinearly over the field.

Node PSFs ``K_n`` (centred on their chief rays) at sensor positions ``(v_n, u_n)`` are
interpolated with hat functions ``w_n`` on the node grid (a partition of unity, constant beyond
the outermost nodes):

.. math::

    y = \sum_n \mathrm{crop}\big(K_n * \mathrm{pad}(w_n \odot x)\big)
    \quad\text{("source" convention, exact per-point interpolation)}

or ``y = Σ_n w_n ⊙ crop(K_n * pad(x))`` (``"sensor"``): ``N·M`` FFT convolutions of
:func:`psfkit.forward.convolution.eigen_kernel_forward` per image, a far richer model than
the eigen-kernel one, which is why the virtual bench simulates with it.
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from ekdun.errors import ConfigurationError, KernelShapeError, TensorShapeError
from psfkit.forward.convolution import eigen_kernel_forward, kernel_spectra
from psfkit.forward.geometry import CONVENTIONS, padded_shape


def hat_weights(nodes: np.ndarray, size: int) -> np.ndarray:
    """1-D piecewise-linear hat functions ``(len(nodes), size)`` at pixels ``0..size-1`` of
    increasing ``nodes`` (weight 1 on the end node beyond it; columns sum to 1)."""
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
        Node PSFs centred on their chief ray (origin at ``(Hk//2, Wk//2)``), gains kept.
    node_rows, node_cols : array
        Increasing sensor coordinates of the ``N`` node rows and ``M`` node columns.
    sensor_shape : (int, int)
    convention : {"source", "sensor"}
        Where the interpolation weights act.
    scene_padding : int
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
        """Move the model to ``device`` (in place, still float64; returns ``self``)."""
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
