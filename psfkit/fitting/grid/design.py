"""The design of an eigen-kernel model of a PSF grid: where a grid's pixels lie on the sensor
(:class:`PixelFrame`), each position's kernel weights in its aligned frame, the model's PSF at
a position, and the refusal of a basis the positions cannot determine.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psfkit.errors import ConfigurationError, InvalidInputError
from psfkit.forward.geometry import kernel_origin
from psfkit.forward.kernelfile import CONVENTIONS
from psfkit.forward.weights import WeightBasis


@dataclass(frozen=True)
class PixelFrame:
    """Where the pixels of an ``(h, w)`` grid lie in the sensor's normalized coordinates.

    The whole sensor (:meth:`of`) or a cropped, binned working copy (:meth:`crop`), whose weights
    must stay those of the pixels' places on the sensor. In the grid's own pixels: ``center``
    ``(v_c, u_c)`` the optical centre, ``half`` the sensor's half size, ``origin`` the kernel
    origin.
    """

    shape: tuple[int, int]
    center: tuple[float, float]
    half: tuple[float, float]
    origin: tuple[float, float]

    @classmethod
    def of(cls, sensor_shape: tuple[int, int]) -> PixelFrame:
        """The sensor's own pixel grid (optical centre: the middle)."""
        h, w = sensor_shape
        origin = kernel_origin(sensor_shape)
        return cls((h, w), ((h - 1) / 2, (w - 1) / 2), (h / 2.0, w / 2.0),
                   (float(origin[0]), float(origin[1])))

    @classmethod
    def crop(cls, sensor_shape: tuple[int, int], corner: tuple[int, int], factor: int,
             shape: tuple[int, int]) -> PixelFrame:
        """A ``shape`` grid of ``factor × factor`` blocks, the first block's corner at sensor pixel
        ``corner`` ``(row, col)``."""
        h, w = sensor_shape
        offset = (factor - 1) / 2.0          # a block's centre from its corner, sensor px

        def local(v: float, axis: int) -> float:
            return (v - corner[axis] - offset) / factor

        origin = kernel_origin(sensor_shape)
        return cls((int(shape[0]), int(shape[1])),
                   (local((h - 1) / 2, 0), local((w - 1) / 2, 1)),
                   (h / 2.0 / factor, w / 2.0 / factor),
                   (local(origin[0], 0), local(origin[1], 1)))

    def axes(self, shift: tuple[float, float]) -> tuple[np.ndarray, np.ndarray]:
        """Normalized ``u_n`` ``(1, w)`` and ``v_n`` ``(h, 1)`` of the pixels plus ``shift`` (grid
        px): the sensor-side weights of a displaced PSF in its aligned frame."""
        h, w = self.shape
        (v_c, u_c), (hh, hw) = self.center, self.half
        du, dv = shift
        return (((np.arange(w) - u_c) / hw)[None, :] + du / hw,
                ((np.arange(h) - v_c) / hh)[:, None] + dv / hh)

    def source(self, shift: tuple[float, float]) -> tuple[float, float]:
        """Normalized ``(u_n, v_n)`` of the source whose PSF origin lands at the kernel origin plus
        ``shift`` (grid px)."""
        (v_c, u_c), (hh, hw), (o_v, o_u) = self.center, self.half, self.origin
        du, dv = shift
        return (o_u + du - u_c) / hw, (o_v + dv - v_c) / hh


def position_weights(basis: WeightBasis, sensor_shape: tuple[int, int],
                     shift: tuple[float, float], convention: str,
                     frame: PixelFrame | None = None) -> np.ndarray:
    """Weights of the K kernels for the PSF displaced by ``shift``, in its aligned frame.

    Returns ``(K, H, W)`` (sensor-side: :math:`W_k(v + s)`) or ``(K, 1, 1)`` (source-side:
    :math:`W_k(s)`); ``frame`` places a cropped or binned grid on the sensor.
    """
    frame = frame if frame is not None else PixelFrame.of(sensor_shape)
    if convention == "sensor":
        u_n, v_n = frame.axes(shift)
        return basis.evaluate(u_n, v_n)
    if convention == "source":
        u_s, v_s = frame.source(shift)
        return basis.evaluate(np.array([[u_s]]), np.array([[v_s]]))
    raise ConfigurationError(f"convention must be one of {CONVENTIONS}, got {convention!r}")


def predict_aligned(kernels: np.ndarray, basis: WeightBasis, shift: tuple[float, float],
                    convention: str, frame: PixelFrame | None = None) -> np.ndarray:
    """The model's ``(C, H, W)`` PSF for a source displaced by ``shift``, in the aligned frame."""
    weights = position_weights(basis, kernels.shape[-2:], shift, convention, frame)
    return np.einsum("khw,kchw->chw", np.broadcast_to(weights, (len(kernels), *kernels.shape[-2:])),
                     kernels)


def source_weights(basis: WeightBasis, shifts: np.ndarray, sensor_shape: tuple[int, int]
                   ) -> np.ndarray:
    """``(P, K)`` source-side weights of the kernels at each of ``(P, 2)`` shifts (px)."""
    return np.array([position_weights(basis, sensor_shape, tuple(s), "source")[:, 0, 0]
                     for s in shifts])


def check_design(basis: WeightBasis, shifts: np.ndarray, sensor_shape: tuple[int, int],
                 where: str, left_out: str = "") -> None:
    """Refuse a basis that the grid positions cannot determine.

    ``shifts`` may hold NaN rows (not measured); ``left_out`` is appended to the count in the
    message.

    Raises
    ------
    InvalidInputError
        Fewer positions than kernels, or a weight term not varying independently over them.
    """
    shifts = np.asarray(shifts, dtype=np.float64).reshape(-1, 2)
    shifts = shifts[np.isfinite(shifts).all(axis=1)]     # gaps and excluded positions
    if len(shifts) < basis.n_kernels:
        raise InvalidInputError(f"{where}: basis {basis.name!r} needs at least "
                                f"{basis.n_kernels} positions ({basis.n_kernels} kernels) but "
                                f"only {len(shifts)} {'remain' if len(shifts) != 1 else 'remains'}"
                                f"{left_out}; use a smaller basis (--basis)")
    design = source_weights(basis, shifts, sensor_shape)
    for k, name in enumerate(basis.kernel_names[1:], start=1):
        column = design[:, k]
        if np.ptp(column) <= 1e-9 * (1.0 + np.abs(column).max()):
            raise InvalidInputError(
                f"{where}: singular design: the weight of kernel {name!r} of basis "
                f"{basis.name!r} does not vary over the grid positions, so the kernel is not "
                "determined (are all positions on one row or column?)")
    if np.linalg.matrix_rank(design, tol=1e-9 * np.abs(design).max()) < basis.n_kernels:
        raise InvalidInputError(
            f"{where}: singular design: the weights of the {basis.n_kernels} kernels of basis "
            f"{basis.name!r} are linearly dependent over the grid positions; use a grid that "
            "spans both directions or a smaller basis")
