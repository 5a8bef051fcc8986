"""Figures of a grid characterization: Fig. 2 of the paper, heat maps, montage, warp plots.

Each function takes a :class:`~psfkit.characterization.characterize.GridCharacterization` and
returns a
matplotlib ``Figure`` (nothing is shown or saved; see :func:`psfkit.report.figures.save_figure`).
They follow the conventions of :mod:`psfkit.report.figures.style`: PSFs are cropped to their support
(the reference's support box, moved by each position's shift), colour bars are labelled with
their unit, compared panels share a scale.

Gaps are visible on every map: a cell of the lattice that was never captured is hatched grey,
an excluded position (a failed quality check) is hatched red with a red ×. An irregular scan
is drawn as a scatter of its positions in the field, coloured by value (excluded: red ×).
"""

from __future__ import annotations

import matplotlib
import matplotlib.patches
import numpy as np
from matplotlib import colors
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from psfkit.calibration.alignment import RELIABLE_OVERLAP
from psfkit.calibration.preprocess import luminance
from psfkit.calibration.support import crop_window
from psfkit.calibration.warp import geometric_anisotropy
from psfkit.characterization.results import QUIVER_CELLS, GridCharacterization
from psfkit.numerics.resample import binning_factor
from psfkit.report.figures.style import (
    COLUMN_IN,
    PAGE_IN,
    fitted,
    new_figure,
    psf_cmap,
    psf_norm,
    publication_style,
)

MISSING_STYLE = {"fill": True, "fc": "0.93", "ec": "0.6", "hatch": "////", "lw": 0.0}
EXCLUDED_STYLE = {"fill": True, "fc": "#fde0e0", "ec": "#c00000", "hatch": "xx", "lw": 0.8}
GAP_NOTE = "hatched grey: not captured; red ×: excluded (see the table of excluded positions)"
#: a lattice map prints its values in the cells up to this many cells a side (7-pt text fits)
ANNOTATE_MAX_CELLS = 5
#: the montage of an irregular scan shows at most this many positions, spread over the field
MONTAGE_MAX = 48


def _box(result: GridCharacterization) -> tuple[slice, slice]:
    """The reference PSF's support box (the whole frame for results without one)."""
    if result.psf_box is not None:
        return result.psf_box
    _, h, w = result.image_shape
    return slice(0, h), slice(0, w)


def _field_label(result: GridCharacterization, row: int, col: int) -> str:
    pos = next(p for p in result.captured if (p.row, p.col) == (row, col))
    if pos.field_deg is not None:
        return f"({pos.field_deg[0]:+.1f}°, {pos.field_deg[1]:+.1f}°)"
    if pos.monitor_px is not None:
        return f"({pos.monitor_px[0]:+.0f}, {pos.monitor_px[1]:+.0f}) px"
    if result.layout == "irregular":
        return f"#{col}"
    return f"[{row}, {col}]"


def _mark_gaps(ax: Axes, result: GridCharacterization) -> None:
    """Hatch the cells of a lattice map that were not captured or were excluded."""
    from matplotlib.patches import Rectangle

    status = result.status()
    for (r, c), state in np.ndenumerate(status):
        if state == "ok":
            continue
        style = MISSING_STYLE if state == "missing" else EXCLUDED_STYLE
        ax.add_patch(Rectangle((c - 0.5, r - 0.5), 1, 1, **style))
        if state == "excluded":
            ax.plot([c], [r], marker="x", color="#c00000", ms=5, mew=1.2)


def _scatter_coordinates(result: GridCharacterization) -> tuple[np.ndarray, str]:
    """``(P, 2)`` field positions of an irregular scan for scatter maps, and their unit."""
    coords = result.field_coordinates()[0]
    if result.field_units == "tan(field angle)":
        return np.rad2deg(np.arctan(coords)), "°"
    return coords, result.field_units


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
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"y ({unit})")
    ax.xaxis.set_major_locator(MaxNLocator(3))
    ax.yaxis.set_major_locator(MaxNLocator(4))


def _scatter_map(fig: Figure, ax: Axes, result: GridCharacterization, values: np.ndarray,
                 title: str, label: str, cmap: str, norm: colors.Normalize | None = None
                 ) -> None:
    """A per-position quantity of an irregular scan as coloured points in the field (the
    colour bar gives the values: numbers beside the points would run into each other)."""
    coords, unit = _scatter_coordinates(result)
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


def _no_ticks(ax: Axes) -> None:
    ax.set_xticks([])
    ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_visible(False)


def figure_shift_variance(result: GridCharacterization) -> Figure:
    """Fig. 2 of the paper: centre PSF (A), two off-axis PSFs along the vertical (B, C; one
    on a 3-row grid), their differences from A after shift compensation, and the MAE against
    position. PSFs cropped to A's support; all on A's scale."""
    box = _box(result)
    ref = crop_window(luminance(result.reference), box)
    peak = float(np.nanmax(ref)) or 1.0
    # nearest to the centre first: B halfway to the edge, C at the edge
    radius = np.hypot(*np.moveaxis(result.field_coordinates(), -1, 0))
    keys = sorted(result.examples, key=lambda k: radius[k])
    n_off = len(keys)       # 0 or 1 where B or C was not captured or was excluded
    letters = "BC"[2 - n_off:]
    # B and C aligned to A: where they were not measured (off the sensor) NaN, drawn pale
    # blue, and their differences from A grey
    valid = [crop_window(result.examples[k][1].astype(np.float32), box, fill=0) > 0
             for k in keys]
    panels = [(ref, f"A\n{_field_label(result, *result.center)}")]
    panels += [(np.where(ok, crop_window(luminance(result.examples[k][0]), box), np.nan),
                f"{letter}\n{_field_label(result, *k)}")
               for letter, k, ok in zip(letters, keys, valid, strict=True)]
    diffs = [(ref - image) / peak for image, _ in panels[1:]]
    with publication_style():
        fig = new_figure(PAGE_IN, 2.7)
        axes = fig.subplots(1, 2 + 2 * n_off, width_ratios=[1] * (1 + 2 * n_off) + [1.7])
        for ax, (img, title) in zip(axes[:1 + n_off], panels, strict=True):
            im = ax.imshow(img / peak, cmap=psf_cmap(), norm=psf_norm())
            ax.set_title(title)
            _no_ticks(ax)
        fig.colorbar(im, ax=list(axes[:1 + n_off]), location="bottom", shrink=0.8,
                     label="PSF (fraction of A's peak)")
        if diffs:
            limit = float(np.nanpercentile(np.abs(np.concatenate([d.ravel() for d in diffs])),
                                           99.9)) or 1.0
            cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="0.85")
            diff_axes = axes[1 + n_off:1 + 2 * n_off]
            for ax, diff, letter in zip(diff_axes, diffs, letters, strict=True):
                im = ax.imshow(diff, cmap=cmap, vmin=-limit, vmax=limit)
                ax.set_title(f"Diff(A−{letter})")
                _no_ticks(ax)
            fig.colorbar(im, ax=list(diff_axes), location="bottom", shrink=0.8,
                         label="difference (fraction of A's peak)")
        _mae_panel(axes[-1], result)
    return fig


def _mae_panel(ax: Axes, result: GridCharacterization) -> None:
    """Fig. 2's last panel: MAE along the centre column (row of a one-row grid) against field
    position, or against the distance from the centre for an irregular scan."""
    if result.layout == "irregular":
        coords, unit = _scatter_coordinates(result)
        x = np.hypot(*(coords - coords[result.center[1]]).T)
        mae, mae_gain = result.table("mae")[0], result.table("mae_gain_compensated")[0]
        xlabel, style = f"distance from the centre ({unit})", ""
    else:
        column = result.center[1] if result.grid_shape[0] > 1 else None
        picks = [p for p in result.positions
                 if (p.col == column if column is not None else p.row == result.center[0])]
        axis = 1 if column is not None else 0
        x = np.array([p.field_deg[axis] if p.field_deg is not None else
                      (p.row if column is not None else p.col) for p in picks])
        order = np.argsort(x)
        x = x[order]
        mae = np.array([p.mae for p in picks])[order]
        mae_gain = np.array([p.mae_gain_compensated for p in picks])[order]
        xlabel = (("field angle θy (°)" if column is not None else "field angle θx (°)")
                  if picks and picks[0].field_deg is not None else "grid index")
        style = "-"
    # percent of the centre PSF's light, as `psfkit report` records it
    ax.plot(x, mae * 100, "o" + style, label="shift compensated")
    ax.plot(x, mae_gain * 100, "s" + ("--" if style else ""), mfc="none",
            label="+ gain compensated")
    ax.set_xlabel(xlabel)
    ax.set_ylabel("MAE vs A (% of A's light)")
    ax.set_title("MAE vs position")
    ax.legend(frameon=False)


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
    ax.xaxis.set_major_locator(MaxNLocator(6, integer=True))
    ax.yaxis.set_major_locator(MaxNLocator(6, integer=True))
    if center is not None:
        ax.add_patch(_centre_box(center))
    ax.set_title(title)
    ax.set_xlabel("column")
    ax.set_ylabel("row")
    fig.colorbar(im, ax=ax, shrink=0.8, label=label)


def _centre_box(center: tuple[int, int]):  # type: ignore[no-untyped-def]
    from matplotlib.patches import Rectangle

    return Rectangle((center[1] - 0.5, center[0] - 0.5), 1, 1, fill=False, ec="red", lw=1)


def _maps(result: GridCharacterization) -> list[tuple[np.ndarray, str, str, str, str,
                                                      colors.Normalize | None]]:
    """``(values, title, colour-bar label, cell format, colour map, norm)`` of each map; the
    two MAE maps share one scale (they are compared)."""
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
    """Heat maps: MAE, gain, registration quality and overlap, plus the residual distortion
    of the shift map as arrows; gaps and excluded positions marked (module docstring). An
    irregular scan gives scatter maps over the field."""
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
    coords, _ = _scatter_coordinates(result)
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
        coords, unit = _scatter_coordinates(result)
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
        ax.xaxis.set_major_locator(MaxNLocator(6, integer=True))
        ax.yaxis.set_major_locator(MaxNLocator(6, integer=True))
        ax.set_xlabel("column")
        ax.set_ylabel("row")
        _mark_gaps(ax, result)
    ax.quiverkey(q, 0.08, 0.92, scale, f"{scale:.2f} px", labelpos="E", coordinates="axes")
    ax.set_title(f"shift-map residual (rms {result.shift_fit.rms_residual:.3f} px)")


def _montage_cells(result: GridCharacterization) -> tuple[list[tuple[int, int]], int, int]:
    """The cells the montage shows and its ``(rows, cols)``: the lattice as it is; an irregular
    scan's positions (at most :data:`MONTAGE_MAX`, spread over the field) in reading order
    of their field positions."""
    n, m = result.grid_shape
    if result.layout != "irregular":
        return [(r, c) for r in range(n) for c in range(m)], n, m
    coords, _ = _scatter_coordinates(result)
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
    """Column and row headings of a lattice montage: the field angle (or monitor position)
    of each column and row, or its index."""
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
    """The grid of PSFs: each PSF's window (the centre PSF's support moved by the PSF's
    shift), luminance on a common square-root scale, with the field position of every column
    and row (of every PSF for an irregular scan)."""
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
            _no_ticks(ax)
            if i >= len(cells):
                ax.set_visible(False)
                continue
            r, c = cells[i]
            im = ax.imshow(thumbs[r, c] / peak, cmap=psf_cmap(), norm=psf_norm())
            if irregular:
                ax.set_title(_field_label(result, r, c).strip("()"), fontsize=7, pad=2)
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


def _flow_positions(result: GridCharacterization, flow: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Full-resolution ``(u, v)`` pixel centres of a stored coarse flow's cells."""
    factor = binning_factor(result.image_shape[1:], QUIVER_CELLS)
    vv, uu = np.mgrid[0:flow.shape[1], 0:flow.shape[2]]
    return (uu + 0.5) * factor - 0.5, (vv + 0.5) * factor - 0.5


def figure_warp(result: GridCharacterization, max_panels: int = 6) -> Figure:
    """Residual displacement fields (after the affine part) at the outermost reliable
    positions, as arrows over the centre PSF (cropped to its support)."""
    candidates = [p for p in result.positions
                  if (p.row, p.col) in result.flows and p.support_overlap >= RELIABLE_OVERLAP]
    if not candidates:
        candidates = [p for p in result.positions if (p.row, p.col) in result.flows]
    candidates.sort(key=lambda p: -np.hypot(*p.shift))
    picks = candidates[:max_panels]
    cols = min(3, max(1, len(picks)))
    rows = int(np.ceil(len(picks) / cols)) or 1
    box = _box(result)
    (r0, r1), (c0, c1) = (box[0].start, box[0].stop), (box[1].start, box[1].stop)
    ref = crop_window(luminance(result.reference), box)
    peak = float(np.nanmax(ref)) or 1.0
    panel_h = min(2.3, (PAGE_IN / cols - 0.1) * (r1 - r0) / (c1 - c0))
    with publication_style():
        fig = new_figure(PAGE_IN, (panel_h + 0.45) * rows + 0.35)
        axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False).ravel())
        scale = max([float(np.nanmax(np.hypot(*result.flows[(p.row, p.col)][:2])))
                     for p in picks] + [1e-6])
        arrow = 0.12 * max(r1 - r0, c1 - c0)      # drawn length of the largest residual, px
        q = None
        for ax, p in zip(axes, picks, strict=False):
            flow = result.flows[(p.row, p.col)]
            # the flow lives in the centre PSF's frame (the off-axis PSF is aligned to it)
            ax.imshow(ref / peak, cmap=psf_cmap(), norm=psf_norm(),
                      extent=(c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5))
            uu, vv = _flow_positions(result, flow)
            keep = (flow[2] > 0.2) & (uu >= c0) & (uu < c1) & (vv >= r0) & (vv < r1)
            quiver = ax.quiver(uu[keep], vv[keep], flow[0][keep], -flow[1][keep], color="C1",
                               angles="xy", scale_units="xy", scale=scale / arrow, width=0.006)
            q = q or quiver
            t = np.deg2rad(p.warp["azimuth_deg"]) if p.warp else 0.0
            start = (c0 + 0.15 * (c1 - c0), r0 + 0.15 * (r1 - r0))
            ax.annotate("", xy=(start[0] + arrow * np.cos(t), start[1] + arrow * np.sin(t)),
                        xytext=start, arrowprops={"arrowstyle": "->", "color": "C0"})
            ax.set_xlim(c0 - 0.5, c1 - 0.5)
            ax.set_ylim(r1 - 0.5, r0 - 0.5)
            ax.set_title(f"{_field_label(result, p.row, p.col)}\n{_warp_numbers(p.warp)}")
            _no_ticks(ax)
        for ax in axes[len(picks):]:
            ax.set_visible(False)
        if q is not None:
            key = axes[0].quiverkey(q, 0.86, 0.06, scale, f"{scale:.2f} px", labelpos="W",
                                    coordinates="axes", color="C1")
            key.text.set_color("white")
        fig.suptitle("residual displacement after the affine part, on the centre PSF "
                     "(orange; blue: tangential direction)")
    return fig


def _warp_numbers(warp: dict | None) -> str:
    """``rms 0.34 px, t/s 2.4``: the anisotropy only where it was measured."""
    if not warp:
        return "no warp measured"
    text = f"rms {warp['residual_rms']:.2f} px"
    anisotropy = warp.get("anisotropy")
    if anisotropy is not None and np.isfinite(anisotropy):
        text += f", t/s {anisotropy:.1f}"
    return text


def figure_warp_summary(result: GridCharacterization) -> Figure:
    """Residual displacement vs field angle with its growth fit (±1σ; grey and "not
    detected" when not significant), and the tangential/sagittal anisotropy against the
    geometric-optics prediction where it was measured. Without field angles, the residual
    against the distance from the centre in field units."""
    theta = result.field_angle_deg()
    reliable = result.table("support_overlap") >= RELIABLE_OVERLAP
    anis = result.warp_table("anisotropy")
    show_anisotropy = theta is not None and bool(np.isfinite(anis[reliable]).any())
    with publication_style():
        fig = new_figure(PAGE_IN if show_anisotropy else COLUMN_IN + 0.6, 2.6)
        axes = np.atleast_1d(fig.subplots(1, 2 if show_anisotropy else 1))
        _growth_panel(axes[0], result, theta, reliable)
        if show_anisotropy:
            _anisotropy_panel(axes[1], result, theta, anis, reliable)
    return fig


def _growth_panel(ax: Axes, result: GridCharacterization, theta: np.ndarray | None,
                  reliable: np.ndarray) -> None:
    if theta is None:
        coords = result.field_coordinates()
        x = np.hypot(*np.moveaxis(coords - coords[result.center], -1, 0))
        xlabel = f"distance from the centre ({result.field_units})"
    else:
        x, xlabel = theta, "field angle θ (°)"
    rms = result.warp_table("residual_rms")
    rt, rs = result.warp_table("rms_tangential"), result.warp_table("rms_sagittal")
    for sel, marker, label in [(reliable, "o", "≥ 50% of A's light in overlap"),
                               (~reliable, "x", "< 50% of A's light in overlap")]:
        if np.isfinite(rms[sel]).any():
            ax.plot(x[sel], rms[sel], marker, color="C0", ls="", label=f"total, {label}")
    if np.isfinite(rt[reliable]).any():
        ax.plot(x[reliable], rt[reliable], "^", color="C1", ls="", label="tangential")
        ax.plot(x[reliable], rs[reliable], "v", color="C2", ls="", label="sagittal")
    growth = result.warp_growth
    if growth is not None and theta is not None:
        exponent = fitted(growth, "exponent")
        t = np.linspace(0, np.nanmax(theta), 100)
        curve = np.sqrt(growth.floor**2 + (growth.scale_10deg * (t / 10) ** growth.exponent)**2)
        label = (f"fit: rms ∝ θ^n, n = {exponent.value_text()}" if exponent.detected else
                 f"no growth detected (fit n = {exponent.value_text()})")
        ax.plot(t, curve, "-" if exponent.detected else "--", color=exponent.colour, lw=0.8,
                label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("residual displacement rms (px)")
    ax.legend(frameon=False)


def _anisotropy_panel(ax: Axes, result: GridCharacterization, theta: np.ndarray,
                      anis: np.ndarray, reliable: np.ndarray) -> None:
    ok = reliable & np.isfinite(anis)
    ax.plot(theta[ok], anis[ok], "o", label="measured (transport spectrum)")
    t = np.linspace(max(0.2, float(np.nanmin(theta[theta > 0]))), float(np.nanmax(theta)), 100)
    ax.plot(t, geometric_anisotropy(t), "k-", lw=0.8,
            label="geometric optics (1/cos³θ−1)/(1/cosθ−1)")
    ax.set_xlabel("field angle θ (°)")
    ax.set_ylabel("tangential / sagittal")
    ax.set_ylim(0, max(4.0, float(np.nanmax(anis[ok])) * 1.1))
    ax.legend(frameon=False, loc="upper right")
