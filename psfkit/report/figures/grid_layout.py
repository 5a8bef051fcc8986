"""What the grid characterization's figures share: the reference's support box, a position's
field label, an irregular scan's coordinates, bare image axes, and the gap hatching (never
captured: grey; excluded: red with a red ×).
"""

from __future__ import annotations

import numpy as np

from psfkit.characterization.results import GridCharacterization

MISSING_STYLE = {"fill": True, "fc": "0.93", "ec": "0.6", "hatch": "////", "lw": 0.0}
EXCLUDED_STYLE = {"fill": True, "fc": "#fde0e0", "ec": "#c00000", "hatch": "xx", "lw": 0.8}


def support_box(result: GridCharacterization) -> tuple[slice, slice]:
    """The reference PSF's support box (the whole frame for results without one)."""
    if result.psf_box is not None:
        return result.psf_box
    _, h, w = result.image_shape
    return slice(0, h), slice(0, w)


def field_label(result: GridCharacterization, row: int, col: int) -> str:
    """The field position of a PSF as a panel label: field angles, monitor pixels or index."""
    pos = next(p for p in result.captured if (p.row, p.col) == (row, col))
    if pos.field_deg is not None:
        return f"({pos.field_deg[0]:+.1f}°, {pos.field_deg[1]:+.1f}°)"
    if pos.monitor_px is not None:
        return f"({pos.monitor_px[0]:+.0f}, {pos.monitor_px[1]:+.0f}) px"
    if result.layout == "irregular":
        return f"#{col}"
    return f"[{row}, {col}]"


def scatter_coordinates(result: GridCharacterization) -> tuple[np.ndarray, str]:
    """``(P, 2)`` field positions of an irregular scan for scatter maps, and their unit."""
    coords = result.field_coordinates()[0]
    if result.field_units == "tan(field angle)":
        return np.rad2deg(np.arctan(coords)), "°"
    return coords, result.field_units
