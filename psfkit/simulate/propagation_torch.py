r"""The virtual camera's optics in PyTorch: all channels of one PSF in float32, in place.

The physics of the NumPy path of :meth:`psfkit.simulate.camera.VirtualCamera.psf_patch`, on
CUDA if present, else the CPU (elementwise work in torch, FFTs in scipy's pocketfft on the same
memory). Formulas that cancel in float32 are rewritten, keeping the phases within ~1e-5 rad of
float64 where the light is:

- spherical wavefront, with :math:`L = x x_s + y y_s`, :math:`\rho^2 = x^2+y^2`:
  :math:`R - R_0 - \alpha x - \beta y = \rho^2/(R+R_0) + L\,(R-R_0)/(R_0(R+R_0))`,
  :math:`R - R_0 = (\rho^2 - 2L)/(R+R_0)`;
- transfer function, with :math:`q = 2 f_0\cdot g + |g|^2` and
  :math:`W = w + w_0 = \sqrt{w_0^2 - q} + w_0`:
  :math:`w - w_0 + f_0\cdot g/w_0 = -\big(f_0\cdot g\; q/(w_0 W) + |g|^2\big)/W`.

torch is imported here only, so that importing :mod:`psfkit` does not load it.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any

import numpy as np

from psfkit.errors import ConfigurationError

if TYPE_CHECKING:
    import torch


def resolve_backend(backend: str) -> str:
    """``"torch"`` or ``"numpy"`` for a backend name (``"auto"``: torch if importable)."""
    if backend not in ("auto", "torch", "numpy"):
        raise ConfigurationError(f"backend must be 'auto', 'torch' or 'numpy', got {backend!r}")
    if backend == "auto":
        import importlib.util

        return "torch" if importlib.util.find_spec("torch") is not None else "numpy"
    return backend


@contextmanager
def cpu_threads(n: int) -> Iterator[None]:
    """Run torch's CPU operators on ``n`` threads, then restore the previous count (set once per
    run: a change re-creates the thread pool)."""
    import torch

    previous = torch.get_num_threads()
    torch.set_num_threads(max(1, n))
    try:
        yield
    finally:
        torch.set_num_threads(previous)


class TorchOptics:
    """Optics of a :class:`~psfkit.simulate.camera.VirtualCamera` on a torch device.

    Parameters
    ----------
    x_um, y_um : numpy.ndarray
        ``(nx,)`` and ``(ny,)`` optical-grid coordinates (µm) relative to the axis.
    surface_opl_um : numpy.ndarray
        ``(ny, nx)`` optical path of the diffuser, ``(n−1)·h`` (µm).
    aperture : numpy.ndarray
        ``(ny, nx)`` aperture transmission.
    wavelengths_um : tuple of float
        One per channel.
    gap_um, z_um, pitch_um : float
        Diffuser–sensor gap, monitor distance, optical sample spacing (µm).
    oversample : int
        Optical samples per pixel and axis.
    spherical : bool
        Spherical (True) or plane (False) incident wave.
    device : str, optional
        Default CUDA where available, else the CPU.
    """

    def __init__(self, x_um: np.ndarray, y_um: np.ndarray, surface_opl_um: np.ndarray,
                 aperture: np.ndarray, wavelengths_um: tuple[float, ...], gap_um: float,
                 z_um: float, pitch_um: float, oversample: int, spherical: bool,
                 device: str | None = None) -> None:
        import torch

        self.torch = torch
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        self.gap_um, self.z_um, self.pitch_um = gap_um, z_um, pitch_um
        self.oversample, self.spherical = oversample, spherical
        self.wavelengths_um = tuple(wavelengths_um)
        self.shape = (len(y_um), len(x_um))
        # the envelope is zero outside the aperture: work on its bounding box only
        rows = np.flatnonzero(aperture.any(axis=1))
        cols = np.flatnonzero(aperture.any(axis=0))
        self.box = (slice(rows[0], rows[-1] + 1), slice(cols[0], cols[-1] + 1))
        dev = self.device

        def tensor(a: np.ndarray, dtype: Any = torch.float32) -> torch.Tensor:
            return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype, device=dev)

        self.x = tensor(x_um[self.box[1]])[None, :]
        self.y = tensor(y_um[self.box[0]])[:, None]
        self.rho2 = self.x**2 + self.y**2
        self.surface_opl = tensor(surface_opl_um[self.box])
        self.aperture = tensor(aperture[self.box])
        self.k = tuple(2.0 * np.pi / lam for lam in self.wavelengths_um)
        self.gx = np.fft.fftfreq(self.shape[1], d=pitch_um)
        self.gy = np.fft.fftfreq(self.shape[0], d=pitch_um)
        # work buffers, reused for every PSF: a fresh 20-120 MB array per step costs as much
        # in page faults as the arithmetic on it
        self.field = torch.zeros((len(self.k), *self.shape), dtype=torch.complex64, device=dev)
        self.work = torch.empty((3, *self.shape), dtype=torch.float32, device=dev)
        self.box_work = torch.empty((2, *self.aperture.shape), dtype=torch.float32, device=dev)
        self._plane_spectrum: torch.Tensor | None = None

    # ----------------------------------------------------------------- FFTs

    def _fft2_(self, x: torch.Tensor, inverse: bool = False) -> None:
        """In-place 2-D FFT of a contiguous complex64 ``(ny, nx)`` tensor: scipy's pocketfft on the
        tensor's memory on the CPU (2-3x faster than torch's here), cuFFT on CUDA."""
        if x.device.type == "cpu":
            import scipy.fft as sfft

            a = x.numpy()
            fn = sfft.ifft2 if inverse else sfft.fft2
            out = fn(a, workers=-1, overwrite_x=True)        # all cores, as the NumPy path
            if not np.shares_memory(out, a):
                a[...] = out
        else:
            x.copy_(self.torch.fft.ifft2(x) if inverse else self.torch.fft.fft2(x))

    # ----------------------------------------------------------------- envelope

    def optical_path(self, source_um: tuple[float, float]) -> torch.Tensor:
        """Optical path (µm) over the aperture box for a source at ``(xs, ys)`` (µm)."""
        if not self.spherical:
            return self.surface_opl
        torch = self.torch
        xs, ys = source_um
        r0 = math.sqrt(xs**2 + ys**2 + self.z_um**2)
        lin = torch.add(self.x * xs, self.y * ys, out=self.box_work[0])          # L
        r = torch.add((self.x - xs) ** 2, (self.y - ys) ** 2, out=self.box_work[1])
        r.add_(self.z_um**2).sqrt_().add_(r0)                                     # R + R0
        # (ρ² − 2L)/(R+R0) = R − R0, times L/R0, plus ρ², over R + R0
        delta = lin.mul_(lin.mul(-2.0).add_(self.rho2).div_(r)).div_(r0)
        return delta.add_(self.rho2).div_(r).add_(self.surface_opl)

    def spectra(self, source_um: tuple[float, float]) -> torch.Tensor:
        """``(C, ny, nx)`` complex64 spectra of the envelopes behind the diffuser (a work buffer,
        overwritten by the next call)."""
        if not self.spherical and self._plane_spectrum is not None:
            return self.field.copy_(self._plane_spectrum)
        torch = self.torch
        opl = self.optical_path(source_um)
        rows, cols = self.box
        field = self.field
        # outside the aperture box the envelope is zero
        field[:, :rows.start].zero_()
        field[:, rows.stop:].zero_()
        field[:, rows, :cols.start].zero_()
        field[:, rows, cols.stop:].zero_()
        phase = self.box_work[1] if opl.data_ptr() != self.box_work[1].data_ptr() \
            else self.box_work[0]
        for c, k in enumerate(self.k):
            parts = torch.view_as_real(field[c, rows, cols])
            torch.mul(opl, k, out=phase)
            torch.cos(phase, out=parts[..., 0])
            parts[..., 0].mul_(self.aperture)
            torch.sin(phase, out=parts[..., 1])
            parts[..., 1].mul_(self.aperture)
            self._fft2_(field[c])
        if not self.spherical:
            self._plane_spectrum = field.clone()
        return field

    # ----------------------------------------------------------------- propagation

    def _row(self, a: np.ndarray) -> torch.Tensor:
        return self.torch.as_tensor(a, dtype=self.torch.float32, device=self.device)[None, :]

    def _col(self, a: np.ndarray) -> torch.Tensor:
        return self.torch.as_tensor(a, dtype=self.torch.float32, device=self.device)[:, None]

    def transfer_phase(self, channel: int, alpha: float, beta: float,
                       residual_shift_um: tuple[float, float]
                       ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Phase (rad) of :func:`~psfkit.simulate.propagation.oblique_transfer_function` for one
        channel, ``(ny, nx)`` float32 (a work buffer), and the mask of propagating components (None:
        all)."""
        torch = self.torch
        lam = self.wavelengths_um[channel]
        f0x, f0y = alpha / lam, beta / lam
        w0 = math.sqrt(1.0 / lam**2 - f0x**2 - f0y**2)
        gx, gy = self.gx, self.gy
        row, col = self._row, self._col
        # separable pieces are computed in float64 on 1-D arrays, combined in float32
        q, big_w, tmp = self.work
        qx, qy = 2 * f0x * gx + gx**2, 2 * f0y * gy + gy**2
        torch.add(row(qx), col(qy), out=q)                             # |g+f0|² − |f0|²
        propagating = q < w0**2 if qx.max() + qy.max() >= w0**2 else None
        torch.mul(q, -1.0, out=big_w).add_(w0**2).clamp_(min=0.0).sqrt_().add_(w0)  # w + w0
        torch.add(row(f0x * gx), col(f0y * gy), out=tmp)               # f0·g
        phase = q.mul_(tmp).div_(big_w).mul_(1.0 / w0)
        phase.add_(torch.add(row(gx**2), col(gy**2), out=tmp)).div_(big_w)
        phase.mul_(-2.0 * np.pi * self.gap_um)
        rx, ry = residual_shift_um
        phase.sub_(torch.add(row(2.0 * np.pi * rx * gx), col(2.0 * np.pi * ry * gy), out=tmp))
        return phase, propagating

    def intensity(self, source_um: tuple[float, float], alpha: float, beta: float,
                  residual_shift_um: tuple[float, float]) -> torch.Tensor:
        """``(C, ny/q, nx/q)`` float32 intensity on the block's sensor pixels, unnormalized."""
        torch = self.torch
        field = self.spectra(source_um)
        q = self.oversample
        c_n, ny, nx = field.shape
        out = torch.empty((c_n, ny // q, nx // q), dtype=torch.float32, device=self.device)
        for c in range(c_n):
            phase, propagating = self.transfer_phase(c, alpha, beta, residual_shift_um)
            # the transfer function as complex64 in the memory of work[1:3] (free now)
            transfer = torch.view_as_complex(self.work[1:].view(ny, nx, 2))
            parts = torch.view_as_real(transfer)
            torch.cos(phase, out=parts[..., 0])
            torch.sin(phase, out=parts[..., 1])
            if propagating is not None:                                # evanescent: zero
                transfer.mul_(propagating)
            field[c].mul_(transfer)
            self._fft2_(field[c], inverse=True)
            parts = torch.view_as_real(field[c]).square_()             # (ny, nx, 2)
            torch.sum(parts.reshape(ny // q, q, nx // q, 2 * q), dim=(1, 3), out=out[c])
        return out

    def box_blur(self, image: torch.Tensor, width_px: float) -> torch.Tensor:
        """:func:`psfkit.simulate.propagation.box_blur` of a ``(C, h, w)`` tensor."""
        torch = self.torch
        if image.device.type == "cpu":
            from psfkit.simulate.propagation import box_blur

            return torch.from_numpy(box_blur(image.numpy(), width_px))
        h, w = image.shape[-2:]
        spec = torch.fft.rfft2(image)
        spec *= (self._col(np.sinc(np.fft.fftfreq(h) * width_px))
                 * self._row(np.sinc(np.fft.rfftfreq(w) * width_px)))
        return torch.fft.irfft2(spec, s=(h, w))


def to_numpy(tensor: torch.Tensor) -> np.ndarray:
    """A tensor's values as a float64 NumPy array (copied from the device)."""
    import torch

    return tensor.detach().to("cpu", torch.float64).numpy()
