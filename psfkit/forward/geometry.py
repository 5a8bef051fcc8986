"""Geometry of the forward model's padded grid (no torch: the kernel file and CLIs use it).

The sensor-sized ``H' × W'`` block sits in the centre of the ``(P·H', P·W')`` grid
(``docs/architecture.md``).
"""

from __future__ import annotations

#: Where the weight maps of an eigen-kernel model act: on each kernel's image on the sensor
#: (``"sensor"``, Eq. 7) or on the scene before each convolution (``"source"``).
CONVENTIONS = ("sensor", "source")


def padded_shape(sensor_shape: tuple[int, int], scene_padding: int = 2) -> tuple[int, int]:
    """Size ``(P·H', P·W')`` of the convolution grid (``P = scene_padding``)."""
    return (scene_padding * int(sensor_shape[0]), scene_padding * int(sensor_shape[1]))


def kernel_origin(kernel_shape: tuple[int, int]) -> tuple[int, int]:
    """``(row, column)`` of a kernel's origin: the centre pixel ``(Hk//2, Wk//2)``."""
    return (int(kernel_shape[0]) // 2, int(kernel_shape[1]) // 2)


def centre_offset(sensor_shape: tuple[int, int],
                  grid_shape: tuple[int, int]) -> tuple[int, int]:
    """``(top, left)`` index of the sensor-sized block in the centre of ``grid_shape``."""
    return ((grid_shape[0] - sensor_shape[0]) // 2, (grid_shape[1] - sensor_shape[1]) // 2)
