"""The montage of a grid characterization: every PSF's window on one √ scale, labelled with
its field position, gaps hatched."""

from __future__ import annotations

import matplotlib.patches
import numpy as np
from matplotlib.figure import Figure

from psfkit.characterization.results import GridCharacterization
from psfkit.report.figures.grid_layout import (
    EXCLUDED_STYLE,
    MISSING_STYLE,
    field_label,
    scatter_coordinates,
)
from psfkit.report.figures.style import (
    PAGE_IN,
    new_figure,
    no_ticks,
    psf_image,
    publication_style,
)

#: the montage of an irregular scan shows at most this many positions, spread over the field
MONTAGE_MAX = 48


def _montage_cells(result: GridCharacterization) -> tuple[list[tuple[int, int]], int, int]:
    """The cells shown and ``(rows, cols)``: the lattice, or an irregular scan's positions (at
    most :data:`MONTAGE_MAX`, spread over the field) in reading order."""
    n, m = result.grid_shape
    if result.layout != "irregular":
        return [(r, c) for r in range(n) for c in range(m)], n, m
    coords, _ = scatter_coordinates(result)
    captured = [c for c in range(m) if result.status()[0, c] != "missing"]
    pick = [result.center[1]]
    if len(captured) > MONTAGE_MAX:     # farthest-point sampling from the centre
        distance = np.full(m, np.inf)
        for _ in range(MONTAGE_MAX - 1):
            distance = np.minimum(distance, np.hypot(*(coords - coords[pick[-1]]).T))
            pick.append(max(captured, key=lambda c: distance[c]))
    else:
        pick = captured
    cols = int(np.ceil(np.sqrt(len(pick))))
    rows = int(np.ceil(len(pick) / cols))
    by_y = sorted(pick, key=lambda c: coords[c, 1])
    ordered = []
    for r in range(rows):           # rows of the field top to bottom, each left to right
        ordered += sorted(by_y[r * cols:(r + 1) * cols], key=lambda c: coords[c, 0])
    return [(0, c) for c in ordered], rows, cols


def _lattice_labels(result: GridCharacterization) -> tuple[list[str], list[str]]:
    """Column and row headings: field angle, monitor position or index."""
    n, m = result.grid_shape
    cols, rows = [f"col {c}" for c in range(m)], [f"row {r}" for r in range(n)]
    for p in result.captured:
        if p.field_deg is not None:
            cols[p.col] = f"θx {p.field_deg[0]:+.1f}°"
            rows[p.row] = f"θy {p.field_deg[1]:+.1f}°"
        elif p.monitor_px is not None:
            cols[p.col] = f"x {p.monitor_px[0]:+.0f} px"
            rows[p.row] = f"y {p.monitor_px[1]:+.0f} px"
    return cols, rows


def figure_montage(result: GridCharacterization) -> Figure:
    """The grid of PSF windows (the centre PSF's support moved by each shift)."""
    thumbs = result.thumbnails
    peak = float(np.nanmax(thumbs[result.center])) or 1.0
    status = result.status()
    reasons = {(e.row, e.col): e.reason for e in result.excluded}
    cells, n, m = _montage_cells(result)
    irregular = result.layout == "irregular"
    col_labels, row_labels = ([], []) if irregular else _lattice_labels(result)
    step = max(1, int(np.ceil(max(n, m) / 12)))    # headings every step-th column and row
    h, w = thumbs.shape[2:]
    panel = (PAGE_IN - 1.3) / m
    with publication_style():
        fig = new_figure(PAGE_IN, n * (panel * h / w + (0.17 if irregular else 0.0)) + 0.6)
        axes = np.atleast_2d(fig.subplots(n, m, squeeze=False))
        im = None
        for i, ax in enumerate(axes.ravel()):
            no_ticks(ax)
            if i >= len(cells):
                ax.set_visible(False)
                continue
            r, c = cells[i]
            im = psf_image(ax, thumbs[r, c] / peak)
            if irregular:
                ax.set_title(field_label(result, r, c).strip("()"), fontsize=7, pad=2)
            else:
                if r == 0 and c % step == 0:
                    ax.set_title(col_labels[c], fontsize=7, pad=2)
                if c == 0 and r % step == 0:
                    ax.set_ylabel(row_labels[r], fontsize=7)
            if status[r, c] != "ok":
                style = MISSING_STYLE if status[r, c] == "missing" else EXCLUDED_STYLE
                ax.add_patch(matplotlib.patches.Rectangle(
                    (0, 0), 1, 1, transform=ax.transAxes, **style))
                ax.text(0.5, 0.5, reasons.get((r, c), "not\ncaptured"), ha="center",
                        va="center", transform=ax.transAxes, fontsize=7, wrap=True,
                        color="#c00000" if status[r, c] == "excluded" else "0.3")
            if (r, c) == result.center:
                for spine in ax.spines.values():
                    spine.set_visible(True)
                    spine.set_color("red")
        fig.colorbar(im, ax=axes, shrink=0.6,
                     label="PSF (fraction of the centre PSF's peak)")
        shown = (f"{len(cells)} of {len(result.captured)} positions, spread over the field; "
                 if len(cells) < len(result.captured) else "")
        note = "; hatched: not captured or excluded" if result.missing or result.excluded \
            else ""
        fig.suptitle(f"PSF grid: {shown}each PSF's window on the sensor, √ scale "
                     f"(red frame: centre; pale blue: off the sensor{note})")
    return fig
