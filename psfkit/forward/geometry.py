"""Geometry of the forward model's padded grid (no torch: the kernel file and CLIs use it).

The scene ``x`` and the measurement ``y`` are both ``H' × W'`` (the sensor's size); the
convolutions run on a padded grid ``(P·H', P·W')`` (``P = scene_padding >= 2``) in whose centre
the sensor-sized block sits (``docs/architecture.md``).
"""

from __future__ import annotations

#: Where the weight maps of an eigen-kernel model act: on each kernel's image on the sensor
#: (``"sensor"``, Eq. 7) or on the scene before each convolution (``"source"``).
CONVENTIONS = ("sensor", "source")


def padded_shape(sensor_shape: tuple[int, int], scene_padding: int = 2) -> tuple[int, int]:
    """Size ``(P·H', P·W')`` of the grid on which the convolutions run.

    Parameters
    ----------
    sensor_shape : (int, int)
        ``(H', W')`` in pixels.
    scene_padding : int
        ``P``, the grid as a multiple of the sensor size.
    """
    return (scene_padding * int(sensor_shape[0]), scene_padding * int(sensor_shape[1]))


def kernel_origin(kernel_shape: tuple[int, int]) -> tuple[int, int]:
    """``(row, column)`` of a kernel's origin in its array: the centre pixel ``(Hk//2, Wk//2)``,
    the way a PSF image looks (the one definition; the kernel file records it as
    :data:`psfkit.forward.kernel_checks.KERNEL_ORIGIN`)."""
    return (int(kernel_shape[0]) // 2, int(kernel_shape[1]) // 2)


def centre_offset(sensor_shape: tuple[int, int],
                  grid_shape: tuple[int, int]) -> tuple[int, int]:
    """``(top, left)`` index of the sensor-sized block in the centre of ``grid_shape``."""
    return ((grid_shape[0] - sensor_shape[0]) // 2, (grid_shape[1] - sensor_shape[1]) // 2)
