"""Heat maps of a grid characterization (MAE, gain, registration quality, overlap) and the
shift map's residual as arrows, gaps hatched; an irregular scan as a coloured scatter.
"""

from __future__ import annotations

import numpy as np
from matplotlib import colors
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from psfkit.characterization.results import GridCharacterization
from psfkit.report.figures.grid_layout import EXCLUDED_STYLE, MISSING_STYLE, scatter_coordinates
from psfkit.report.figures.style import PAGE_IN, axis_labels, new_figure, publication_style

GAP_NOTE = "hatched grey: not captured; red ×: excluded (see the table of excluded positions)"
#: a lattice map prints its values in the cells up to this many cells a side (7-pt text fits)
ANNOTATE_MAX_CELLS = 5


def _mark_gaps(ax: Axes, result: GridCharacterization) -> None:
    """Hatch the cells of a lattice map that were not captured or were excluded."""
    status = result.status()
    for (r, c), state in np.ndenumerate(status):
        if state == "ok":
            continue
        style = MISSING_STYLE if state == "missing" else EXCLUDED_STYLE
        ax.add_patch(Rectangle((c - 0.5, r - 0.5), 1, 1, **style))
        if state == "excluded":
            ax.plot([c], [r], marker="x", color="#c00000", ms=5, mew=1.2)


def _field_axes(ax: Axes, coords: np.ndarray, unit: str, key_band: float = 0.0) -> None:
    """Equal-aspect field axes around ``coords`` (y down, as the field's rows), with an empty
    band of ``key_band`` × the extent at the top (for a quiver key)."""
    ok = np.isfinite(coords).all(axis=1)
    lo, hi = coords[ok].min(axis=0), coords[ok].max(axis=0)
    extent = float(max(hi - lo)) or 1.0
    pad = 0.08 * extent
    ax.set_xlim(lo[0] - pad, hi[0] + pad)
    ax.set_ylim(hi[1] + pad, lo[1] - pad - key_band * extent)
    ax.set_aspect("equal", adjustable="box")
    axis_labels(ax, f"x ({unit})", f"y ({unit})", (3, 4))


def _scatter_map(fig: Figure, ax: Axes, result: GridCharacterization, values: np.ndarray,
                 title: str, label: str, cmap: str, norm: colors.Normalize | None = None
                 ) -> None:
    """A per-position quantity of an irregular scan as coloured points in the field."""
    coords, unit = scatter_coordinates(result)
    v = values.reshape(-1)
    ok = np.isfinite(v)
    sc = ax.scatter(coords[ok, 0], coords[ok, 1], c=v[ok], cmap=cmap, norm=norm, s=22, ec="k",
                    lw=0.3)
    bad = result.status().reshape(-1) == "excluded"
    if bad.any():
        ax.scatter(coords[bad, 0], coords[bad, 1], marker="x", color="#c00000", s=30, lw=1.2)
    centre = result.center[1]
    ax.scatter([coords[centre, 0]], [coords[centre, 1]], marker="s", s=60, fc="none",
               ec="red", lw=1)
    _field_axes(ax, coords, unit)
    ax.set_title(title)
    fig.colorbar(sc, ax=ax, shrink=0.8, pad=0.1, label=label)   # pad: room for the title


def _heatmap(fig: Figure, ax: Axes, values: np.ndarray, title: str, label: str, fmt: str,
             cmap: str = "viridis", center: tuple[int, int] | None = None,
             norm: colors.Normalize | None = None) -> None:
    im = ax.imshow(values, cmap=cmap, norm=norm)
    n, m = values.shape
    if max(n, m) <= ANNOTATE_MAX_CELLS:     # larger grids: the colour bar gives the values
        for (r, c), value in np.ndenumerate(values):
            if np.isfinite(value):
                shade = im.cmap(im.norm(value))
                ax.text(c, r, format(value, fmt), ha="center", va="center", fontsize=7,
                        color="white" if sum(shade[:3]) < 1.5 else "black")
    axis_labels(ax, "column", "row", (6, 6), integer=True)
    if center is not None:
        ax.add_patch(Rectangle((center[1] - 0.5, center[0] - 0.5), 1, 1, fill=False, ec="red",
                               lw=1))
    ax.set_title(title)
    fig.colorbar(im, ax=ax, shrink=0.8, label=label)


def _maps(result: GridCharacterization) -> list[tuple[np.ndarray, str, str, str, str,
                                                      colors.Normalize | None]]:
    """``(values, title, colour-bar label, cell format, colour map, norm)`` of each map (the
    two MAE maps share one scale)."""
    mae, mae_gain = result.table("mae"), result.table("mae_gain_compensated")
    scale = 100.0                   # percent of the centre PSF's light, as the report prints it
    top = float(np.nanmax(np.concatenate([mae.ravel(), mae_gain.ravel()]), initial=0.0)) * scale
    shared = colors.Normalize(0.0, top or 1.0)
    unit = "MAE (% of the centre PSF's light)"
    return [(mae * scale, "MAE (shift comp.)", unit, ".2g", "magma", shared),
            (mae_gain * scale, "MAE (+ gain comp.)", unit, ".2g", "magma", shared),
            (result.table("gain"), "relative gain", "gain (rel. to centre)", ".2f", "cividis",
             None),
            (result.table("quality"), "registration NCC", "NCC (1 = identical)", ".2f",
             "viridis", None),
            (result.table("support_overlap"), "overlap with centre",
             "overlap (fraction of A's light)", ".2f", "Greys_r", None)]


def figure_maps(result: GridCharacterization) -> Figure:
    """The maps of the module docstring."""
    irregular = result.layout == "irregular"
    with publication_style():
        # panels of the map's own aspect: colour bars as tall as the maps
        fig = new_figure(PAGE_IN, 2 * (1.45 * _map_aspect(result) + 0.85)
                         + (0.2 if result.missing or result.excluded else 0.0))
        axes = fig.subplots(2, 3)
        for ax, (values, title, label, fmt, cmap, norm) in zip(axes.ravel(), _maps(result),
                                                               strict=False):
            if irregular:
                _scatter_map(fig, ax, result, values, title, label, cmap, norm)
            else:
                _heatmap(fig, ax, values, title, label, fmt, cmap, result.center, norm)
                _mark_gaps(ax, result)
        if result.shift_fit is not None:
            _residual_quiver(axes[1, 2], result)
        else:
            axes[1, 2].set_visible(False)
        if result.missing or result.excluded:
            fig.text(0.5, 0.005, GAP_NOTE, ha="center", va="bottom", fontsize=7)
    return fig


def _map_aspect(result: GridCharacterization) -> float:
    """Height / width of a map panel: of the lattice, or of the scan's field (0.4 to 1.6)."""
    if result.layout != "irregular":
        n, m = result.grid_shape
        return float(np.clip(n / m, 0.4, 1.6))
    coords, _ = scatter_coordinates(result)
    span = np.nanmax(coords, axis=0) - np.nanmin(coords, axis=0)
    return float(np.clip((span[1] + 1e-9) / (span[0] + 1e-9), 0.4, 1.6))


def _residual_quiver(ax: Axes, result: GridCharacterization) -> None:
    """The shift map's residual (distortion the affine map does not explain) as arrows, with
    a key in an empty band at the top of the panel."""
    assert result.shift_fit is not None
    res = result.shift_fit.residuals
    length = np.hypot(res[..., 0], res[..., 1])
    scale = max(float(np.nanmax(length, initial=0.0)), 1e-9)
    if result.layout == "irregular":
        coords, unit = scatter_coordinates(result)
        res = res[0]
        extent = float(np.nanmax(np.ptp(coords, axis=0))) or 1.0
        # arrows a tenth of the field's extent at the largest residual
        q = ax.quiver(coords[:, 0], coords[:, 1], np.ma.masked_invalid(res[..., 0]),
                      np.ma.masked_invalid(res[..., 1]), angles="xy",
                      scale=scale * 10 / extent, scale_units="xy", color="C3")
        _field_axes(ax, coords, unit, key_band=0.2)
    else:
        n, m = result.grid_shape
        rows, cols = np.mgrid[0:n, 0:m]
        q = ax.quiver(cols.astype(float), rows.astype(float), np.ma.masked_invalid(res[..., 0]),
                      np.ma.masked_invalid(-res[..., 1]), angles="xy",
                      scale=2.5 * scale, scale_units="xy", color="C3")
        ax.set_xlim(-0.7, m - 0.3)
        ax.set_ylim(n - 0.3, -0.7 - max(1.0, 0.25 * n))     # the key's band on top
        ax.set_aspect("equal")
        axis_labels(ax, "column", "row", (6, 6), integer=True)
        _mark_gaps(ax, result)
    ax.quiverkey(q, 0.08, 0.92, scale, f"{scale:.2f} px", labelpos="E", coordinates="axes")
    ax.set_title(f"shift-map residual (rms {result.shift_fit.rms_residual:.3f} px)")
