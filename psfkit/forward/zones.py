"""Field zones: where on the sensor a model or a reconstruction is scored.

One definition for ``psfkit eval-model`` and ``ekdun eval``: three **equal-area radial zones**
around the optical centre, ``"centre"`` (nearest the axis), ``"middle"`` and ``"edge"``, each a
third of the pixels (counts differ by at most one). Pixels are ranked by the distance of their
centre from the optical centre; ties at a boundary radius are split in raster order. The
optical centre ``(v_c, u_c)`` is the weight maps' one (a kernel file's ``optical_center``, else
``((H-1)/2, (W-1)/2)``). NumPy only, so both packages can use it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from psfkit.errors import InvalidInputError

__all__ = ["ZONE_NAMES", "FieldZones", "field_zones"]

#: The zones, from the optical axis outwards.
ZONE_NAMES: tuple[str, ...] = ("centre", "middle", "edge")


@dataclass(eq=False)
class FieldZones:
    """The three equal-area radial zones of a sensor (:func:`field_zones`).

    Attributes
    ----------
    labels : numpy.ndarray
        ``(H, W)`` int8: 0 = centre, 1 = middle, 2 = edge (indices into :data:`ZONE_NAMES`).
    radii : tuple of float
        ``(r1, r2)`` in pixels: the largest distance in the centre and in the middle zone.
    optical_center : tuple of float
        ``(v_c, u_c)`` in pixels.
    """

    labels: np.ndarray
    radii: tuple[float, float]
    optical_center: tuple[float, float]

    @property
    def shape(self) -> tuple[int, int]:
        return int(self.labels.shape[0]), int(self.labels.shape[1])

    def masks(self) -> dict[str, np.ndarray]:
        """``{name: (H, W) bool}``, one mask per zone, in :data:`ZONE_NAMES` order."""
        return {name: self.labels == i for i, name in enumerate(ZONE_NAMES)}

    def cropped(self, margin: int) -> FieldZones:
        """The zones of pixels ``margin`` or more from the border (SSIM valid region)."""
        if margin == 0:
            return self
        return FieldZones(self.labels[margin:-margin, margin:-margin], self.radii,
                          (self.optical_center[0] - margin, self.optical_center[1] - margin))

    def describe(self) -> dict[str, object]:
        """JSON-able summary: names, optical centre, radii and pixel counts."""
        return {"names": list(ZONE_NAMES),
                "definition": "equal-area radial zones around the optical centre",
                "optical_center": [float(c) for c in self.optical_center],
                "radii_px": [float(r) for r in self.radii],
                "pixels": [int(np.count_nonzero(self.labels == i))
                           for i in range(len(ZONE_NAMES))]}


def field_zones(shape: tuple[int, int],
                optical_center: tuple[float, float] | None = None) -> FieldZones:
    """Split an ``(H, W)`` sensor into three equal-area radial zones (module docstring).

    Parameters
    ----------
    shape : (int, int)
        ``(H, W)``, in the pixels the zones are used on (binned ones included).
    optical_center : (float, float), optional
        ``(v_c, u_c)`` in pixels; default the sensor centre.

    Returns
    -------
    FieldZones

    Raises
    ------
    InvalidInputError
        Fewer than 3 pixels or a non-finite centre.
    """
    h, w = int(shape[0]), int(shape[1])
    if h < 1 or w < 1 or h * w < len(ZONE_NAMES):
        raise InvalidInputError(f"field zones need at least 3 pixels, got a {h}x{w} sensor")
    v_c, u_c = optical_center if optical_center is not None else ((h - 1) / 2, (w - 1) / 2)
    if not (np.isfinite(v_c) and np.isfinite(u_c)):
        raise InvalidInputError(f"optical centre must be finite, got {(v_c, u_c)}")
    v = np.arange(h, dtype=np.float64)[:, None] - float(v_c)
    u = np.arange(w, dtype=np.float64)[None, :] - float(u_c)
    # squared distances: exact in float64 for a centre on the pixel or half-pixel grid, so
    # pixels symmetric about the centre tie exactly (and a stable sort keeps raster order)
    d2 = (v * v + u * u).ravel()
    order = np.argsort(d2, kind="stable")
    n = d2.size
    bounds = [(k * n) // 3 for k in (1, 2)]          # first index of the middle, of the edge
    flat = np.empty(n, dtype=np.int8)
    flat[order[:bounds[0]]] = 0
    flat[order[bounds[0]:bounds[1]]] = 1
    flat[order[bounds[1]:]] = 2
    labels = flat.reshape(h, w)
    radii = (float(np.sqrt(d2[order[bounds[0] - 1]])), float(np.sqrt(d2[order[bounds[1] - 1]])))
    return FieldZones(labels, radii, (float(v_c), float(u_c)))
