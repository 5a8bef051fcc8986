"""The residual maps of ``psfkit eval-model``: one panel per model on one colour scale, with
the field zones (:mod:`psfkit.forward.zones`)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from matplotlib.figure import Figure

from psfkit.forward.zones import ZONE_NAMES, FieldZones
from psfkit.report.figures.style import COLUMN_IN, PAGE_IN, new_figure, publication_style

#: What the maps show (the colour bar's label); see
# :func:`psfkit.fitting.pairs.model_errors.residual_map`.
RESIDUAL_LABEL = "RMS residual / RMS measurement"


def _zone_boundaries(ax, zones: FieldZones) -> None:  # type: ignore[no-untyped-def]
    """Contours between the zones, and their names along the optical centre's row."""
    ax.contour(zones.labels.astype(float), levels=[0.5, 1.5], colors="white",
               linewidths=0.6, linestyles=["-", "--"])
    v_c, u_c = zones.optical_center
    h, w = zones.shape
    r1, r2 = zones.radii
    # the label of each zone at the middle of its radial extent to the right of the centre
    spots = (u_c, u_c + 0.5 * (r1 + r2), u_c + 0.5 * (r2 + (w - 1 - u_c)))
    for name, u in zip(ZONE_NAMES, spots, strict=True):
        if 0 <= u <= w - 1 and 0 <= v_c <= h - 1:
            ax.text(u, v_c, name, color="white", fontsize=6, ha="center", va="center")


def figure_residual_maps(maps: Sequence[np.ndarray], titles: Sequence[str],
                         zones: FieldZones | None = None) -> Figure:
    """``(H, W)`` residual maps of one sensor side by side, one title each, optionally with
    the ``zones``; one colour bar (:data:`RESIDUAL_LABEL`) from 0 to the largest 99.5th
    percentile (pointed when pixels exceed it)."""
    if not maps or len(maps) != len(titles):
        raise ValueError("one title per map, and at least one map")
    h, w = maps[0].shape
    n = len(maps)
    with publication_style():
        panel_w = min((PAGE_IN - 0.9) / n, 3.2)
        fig = new_figure(max(COLUMN_IN, panel_w * n + 0.9), panel_w * h / w + 0.8)
        axes = fig.subplots(1, n, squeeze=False)[0]
        top = max(float(np.percentile(m, 99.5)) for m in maps) or 1.0
        clipped = any(float(m.max()) > top for m in maps)
        image = None
        for ax, m, title in zip(axes, maps, titles, strict=True):
            image = ax.imshow(m, cmap="magma", vmin=0.0, vmax=top)
            if zones is not None:
                _zone_boundaries(ax, zones)
            ax.set_title(title)
            ax.set_xticks([])
            ax.set_yticks([])
        bar = fig.colorbar(image, ax=list(axes), shrink=0.9, extend="max" if clipped
                           else "neither")
        bar.set_label(RESIDUAL_LABEL)
    return fig
