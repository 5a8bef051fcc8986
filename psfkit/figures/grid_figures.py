"""Figures of a grid characterization: Fig. 2 of the paper, heat maps, montage, warp plots.

Each function takes a :class:`~psfkit.characterize.GridCharacterization` and returns a
matplotlib ``Figure`` (nothing is shown or saved; see :func:`psfkit.figures.save_figure`).

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

from psfkit.characterize import RELIABLE_OVERLAP, GridCharacterization
from psfkit.figures.style import PAGE_IN, new_figure, publication_style
from psfkit.preprocess import luminance
from psfkit.warp import geometric_anisotropy


def _display(image: np.ndarray) -> np.ndarray:
    """RGB (H, W, 3) or mono (H, W) for imshow, square-root scaled to [0, 1] (caustics span a
    large dynamic range)."""
    img = np.clip(image, 0, None)
    peak = float(img.max()) or 1.0
    img = np.sqrt(img / peak)
    return np.moveaxis(img, 0, -1) if img.shape[0] == 3 else img[0]


MISSING_STYLE = {"fill": True, "fc": "0.93", "ec": "0.6", "hatch": "////", "lw": 0.0}
EXCLUDED_STYLE = {"fill": True, "fc": "#fde0e0", "ec": "#c00000", "hatch": "xx", "lw": 0.8}
GAP_NOTE = "hatched grey: not captured; red ×: excluded (see the table of excluded positions)"


def _field_label(result: GridCharacterization, row: int, col: int) -> str:
    pos = next(p for p in result.captured if (p.row, p.col) == (row, col))
    if pos.field_deg is not None:
        return f"({pos.field_deg[0]:+.1f}°, {pos.field_deg[1]:+.1f}°)"
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
    """``(P, 2)`` field positions of an irregular scan for scatter maps, and the axis unit."""
    coords = result.field_coordinates()[0]
    unit = result.field_units
    if result.field_units == "tan(field angle)":
        coords, unit = np.rad2deg(np.arctan(coords)), "field angle (°)"
    return coords, unit


def _scatter_map(fig: Figure, ax: Axes, result: GridCharacterization, values: np.ndarray,
                 title: str, label: str, fmt: str, cmap: str) -> None:
    """A per-position quantity of an irregular scan as coloured points in the field."""
    coords, unit = _scatter_coordinates(result)
    v = values.reshape(-1)
    ok = np.isfinite(v)
    sc = ax.scatter(coords[ok, 0], coords[ok, 1], c=v[ok], cmap=cmap, s=28, ec="k", lw=0.3)
    status = result.status().reshape(-1)
    bad = status == "excluded"
    if bad.any():
        ax.scatter(coords[bad, 0], coords[bad, 1], marker="x", color="#c00000", s=30, lw=1.2)
    centre = result.center[1]
    ax.scatter([coords[centre, 0]], [coords[centre, 1]], marker="s", s=70, fc="none",
               ec="red", lw=1)
    if ok.sum() <= 30:
        for (x, y), value in zip(coords[ok], v[ok], strict=True):
            ax.annotate(format(value, fmt), (x, y), xytext=(0, 5), textcoords="offset points",
                        ha="center", fontsize=5)
    ax.set_aspect("equal", adjustable="datalim")
    ax.invert_yaxis()       # y down, as the field's rows
    ax.set_title(title)
    ax.set_xlabel(f"x ({unit})")
    ax.set_ylabel(f"y ({unit})")
    fig.colorbar(sc, ax=ax, shrink=0.8, label=label)


def _no_ticks(ax: Axes) -> None:
    ax.set_xticks([])
    ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_visible(False)


def figure_shift_variance(result: GridCharacterization) -> Figure:
    """Fig. 2 of the paper: centre PSF (A), two off-axis PSFs along the vertical (B, C; one
    on a 3-row grid), their differences from A after shift compensation, and the MAE against
    position."""
    with publication_style():
        ref = result.reference
        # nearest to the centre first: B halfway to the edge, C at the edge
        radius = np.hypot(*np.moveaxis(result.field_coordinates(), -1, 0))
        keys = sorted(result.examples, key=lambda k: radius[k])
        n_off = len(keys)       # 0 or 1 where B or C was not captured or was excluded
        fig = new_figure(PAGE_IN, 2.3)
        axes = fig.subplots(1, 2 + 2 * n_off, width_ratios=[1] * (1 + 2 * n_off) + [1.5])
        letters = "BC"[2 - n_off:]
        panels = [(ref, f"A\n{_field_label(result, *result.center)}")]
        panels += [(result.examples[k][0], f"{letter}\n{_field_label(result, *k)}")
                   for letter, k in zip(letters, keys, strict=True)]
        for ax, (img, title) in zip(axes[:1 + n_off], panels, strict=True):
            ax.imshow(_display(img), cmap="gray")
            ax.set_title(title)
            _no_ticks(ax)
        # differences only where both PSFs were measured (grey elsewhere)
        diffs = [np.where(result.examples[k][1],
                          luminance(ref) - luminance(result.examples[k][0]), np.nan)
                 for k in keys]
        if diffs:
            limit = float(np.nanpercentile(np.abs(np.concatenate([d.ravel() for d in diffs])),
                                           99.9)) or 1.0
            cmap = matplotlib.colormaps["RdBu_r"].with_extremes(bad="0.85")
            diff_axes = axes[1 + n_off:1 + 2 * n_off]
            for ax, diff, letter in zip(diff_axes, diffs, letters, strict=True):
                im = ax.imshow(diff, cmap=cmap, vmin=-limit, vmax=limit)
                ax.set_title(f"Diff(A−{letter})")
                _no_ticks(ax)
            fig.colorbar(im, ax=list(diff_axes), shrink=0.7, label="A − aligned PSF (norm.)")
        ax = axes[-1]
        if result.layout == "irregular":
            _mae_vs_radius(ax, result)
            return fig
        column = result.center[1] if result.grid_shape[0] > 1 else None
        picks = [p for p in result.positions
                 if (p.col == column if column is not None else p.row == result.center[0])]
        axis = 1 if column is not None else 0
        x = [p.field_deg[axis] if p.field_deg is not None else (p.row if column is not None
                                                                 else p.col) for p in picks]
        order = np.argsort(x)
        ax.plot(np.array(x)[order], np.array([p.mae for p in picks])[order], "o-",
                label="shift compensated")
        ax.plot(np.array(x)[order], np.array([p.mae_gain_compensated for p in picks])[order],
                "s--", label="+ gain compensated")
        ax.set_xlabel(("field angle θy (°)" if column is not None else "field angle θx (°)")
                      if picks[0].field_deg is not None else "grid index")
        ax.set_ylabel("MAE vs centre A (norm.)")
        ax.set_title("MAE vs position")
        ax.legend(frameon=False)
    return fig


def _mae_vs_radius(ax: Axes, result: GridCharacterization) -> None:
    """Fig. 2's last panel for an irregular scan: MAE against the distance from the centre."""
    coords, unit = _scatter_coordinates(result)
    radius = np.hypot(*(coords - coords[result.center[1]]).T)
    ax.plot(radius, result.table("mae")[0], "o", label="shift compensated")
    ax.plot(radius, result.table("mae_gain_compensated")[0], "s", mfc="none",
            label="+ gain compensated")
    ax.set_xlabel(f"distance from the centre ({unit})")
    ax.set_ylabel("MAE vs centre A (norm.)")
    ax.set_title("MAE vs position")
    ax.legend(frameon=False)


def _heatmap(fig: Figure, ax: Axes, values: np.ndarray, title: str, label: str, fmt: str,
             cmap: str = "viridis", center: tuple[int, int] | None = None,
             norm: colors.Normalize | None = None) -> None:
    im = ax.imshow(values, cmap=cmap, norm=norm)
    n, m = values.shape
    size = min(6.0, 44.0 / max(n, m))  # points: the text fits its cell up to ~15 × 15 grids
    for r in range(n):
        for c in range(m):
            if np.isfinite(values[r, c]) and max(n, m) <= 15:
                value = values[r, c]
                shade = im.cmap(im.norm(value))
                ax.text(c, r, format(value, fmt), ha="center", va="center", fontsize=size,
                        color="white" if sum(shade[:3]) < 1.5 else "black")
    ax.set_xticks(range(0, m, max(1, m // 9)))
    ax.set_yticks(range(0, n, max(1, n // 9)))
    if center is not None:
        ax.add_patch(_box(center))
    ax.set_title(title)
    ax.set_xlabel("column")
    ax.set_ylabel("row")
    fig.colorbar(im, ax=ax, shrink=0.8, label=label)


def _box(center: tuple[int, int]):  # type: ignore[no-untyped-def]
    from matplotlib.patches import Rectangle

    return Rectangle((center[1] - 0.5, center[0] - 0.5), 1, 1, fill=False, ec="red", lw=1)


def figure_maps(result: GridCharacterization) -> Figure:
    """Heat maps: MAE, gain, registration quality and overlap, plus the residual distortion
    of the shift map as arrows; gaps and excluded positions marked (module docstring). An
    irregular scan gives scatter maps over the field."""
    irregular = result.layout == "irregular"
    maps = [(result.table("mae") * 1e3, "MAE (shift comp.)", "×10⁻³", ".2g", "magma"),
            (result.table("mae_gain_compensated") * 1e3, "MAE (shift + gain comp.)", "×10⁻³",
             ".2g", "magma"),
            (result.table("gain"), "relative gain", "gain", ".2f", "cividis"),
            (result.table("quality"), "registration quality (NCC)", "NCC", ".2f", "viridis"),
            (result.table("overlap"), "overlap with centre PSF", "fraction of sensor", ".2f",
             "Greys_r")]
    with publication_style():
        fig = new_figure(PAGE_IN, 4.6)
        axes = fig.subplots(2, 3)
        for ax, (values, title, label, fmt, cmap) in zip(axes.ravel(), maps, strict=False):
            if irregular:
                _scatter_map(fig, ax, result, values, title, label, fmt, cmap)
            else:
                _heatmap(fig, ax, values, title, label, fmt, cmap, result.center)
                _mark_gaps(ax, result)
        ax = axes[1, 2]
        if result.shift_fit is not None:
            res = result.shift_fit.residuals
            if irregular:
                coords, unit = _scatter_coordinates(result)
                x, y = coords[:, 0], coords[:, 1]
                res = res[0]
            else:
                n, m = result.grid_shape
                rows, cols = np.mgrid[0:n, 0:m]
                x, y = cols.astype(float), rows.astype(float)
            length = np.hypot(res[..., 0], res[..., 1])
            scale = max(float(np.nanmax(length, initial=0.0)), 1e-9)
            if irregular:   # arrows a tenth of the field's extent at the largest residual
                extent = float(np.nanmax(np.ptp(coords, axis=0))) or 1.0
                q = ax.quiver(x, y, np.ma.masked_invalid(res[..., 0]),
                              np.ma.masked_invalid(res[..., 1]), angles="xy",
                              scale=scale * 10 / extent, scale_units="xy", color="C3")
                ax.invert_yaxis()
                ax.set_aspect("equal", adjustable="datalim")
                ax.set_xlabel(f"x ({unit})")
                ax.set_ylabel(f"y ({unit})")
            else:
                q = ax.quiver(x, y, np.ma.masked_invalid(res[..., 0]),
                              np.ma.masked_invalid(-res[..., 1]), angles="xy",
                              scale=2.5 * scale, scale_units="xy", color="C3")
                ax.set_xlim(-0.7, m - 0.3)
                ax.set_ylim(n - 0.3, -0.7)
                ax.set_aspect("equal")
                ax.set_xlabel("column")
                ax.set_ylabel("row")
                _mark_gaps(ax, result)
            ax.quiverkey(q, 0.75, -0.2, scale, f"{scale:.2f} px", labelpos="E")
            ax.set_title(f"shift-map residual (rms {result.shift_fit.rms_residual:.3f} px)")
        else:
            ax.set_visible(False)
        if result.missing or result.excluded:
            fig.text(0.5, 0.005, GAP_NOTE, ha="center", va="bottom", fontsize=6)
    return fig


def figure_montage(result: GridCharacterization) -> Figure:
    """The grid of PSFs (luminance, square-root scaled to the centre PSF's peak)."""
    thumbs = result.thumbnails
    n, m = result.grid_shape
    peak = float(thumbs[result.center].max()) or 1.0
    status = result.status()
    reasons = {(e.row, e.col): e.reason for e in result.excluded}
    cells = [(r, c) for r in range(n) for c in range(m)]
    if result.layout == "irregular":     # the scan's positions in manifest order, row by row
        m = int(np.ceil(np.sqrt(len(cells))))
        n = int(np.ceil(len(cells) / m))
    with publication_style():
        fig = new_figure(PAGE_IN, PAGE_IN * n * thumbs.shape[2] / (m * thumbs.shape[3]) + 0.3)
        axes = np.atleast_2d(fig.subplots(n, m, squeeze=False))
        for i, ax in enumerate(axes.ravel()):
            _no_ticks(ax)
            if i >= len(cells):
                ax.set_visible(False)
                continue
            r, c = cells[i]
            ax.imshow(np.sqrt(np.clip(thumbs[r, c], 0, None) / peak), cmap="gray",
                      vmin=0, vmax=1)
            if status[r, c] != "ok":
                style = MISSING_STYLE if status[r, c] == "missing" else EXCLUDED_STYLE
                ax.add_patch(matplotlib.patches.Rectangle(
                    (0, 0), 1, 1, transform=ax.transAxes, **style))
                ax.text(0.5, 0.5, reasons.get((r, c), "not captured"), ha="center",
                        va="center", transform=ax.transAxes, fontsize=5,
                        color="#c00000" if status[r, c] == "excluded" else "0.3")
            if (r, c) == result.center:
                for spine in ax.spines.values():
                    spine.set_visible(True)
                    spine.set_color("red")
        note = "; hatched: not captured or excluded" if result.missing or result.excluded \
            else ""
        fig.suptitle(f"PSF grid (√ intensity, common scale; red: centre{note})")
    return fig


def figure_warp(result: GridCharacterization, max_panels: int = 6) -> Figure:
    """Residual displacement fields (after the affine part) at the outermost reliable
    positions, as arrows over the PSF."""
    candidates = [p for p in result.positions
                  if (p.row, p.col) in result.flows and p.overlap >= RELIABLE_OVERLAP]
    if not candidates:
        candidates = [p for p in result.positions if (p.row, p.col) in result.flows]
    candidates.sort(key=lambda p: -np.hypot(*p.shift))
    picks = candidates[:max_panels]
    cols = min(3, max(1, len(picks)))
    rows = int(np.ceil(len(picks) / cols)) or 1
    with publication_style():
        fig = new_figure(PAGE_IN, 2.4 * rows)
        axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False).ravel())
        scale = max([float(np.nanmax(np.hypot(*result.flows[(p.row, p.col)][:2])))
                     for p in picks] + [1e-6])
        for ax, p in zip(axes, picks, strict=False):
            flow = result.flows[(p.row, p.col)]
            h, w = flow.shape[1:]
            # the flow lives in the centre PSF's frame (the off-axis PSF is aligned to it)
            ax.imshow(np.sqrt(np.clip(result.thumbnails[result.center], 0, None)), cmap="gray",
                      extent=(-0.5, w - 0.5, h - 0.5, -0.5))
            keep = flow[2] > 0.2
            vv, uu = np.nonzero(keep)
            q = ax.quiver(uu, vv, flow[0][keep], -flow[1][keep], color="C1", angles="xy",
                          scale_units="xy", scale=scale / 1.2, width=0.006)
            t = np.deg2rad(p.warp["azimuth_deg"]) if p.warp else 0.0
            ax.annotate("", xy=(w * 0.12 + 3 * np.cos(t), h * 0.12 + 3 * np.sin(t)),
                        xytext=(w * 0.12, h * 0.12),
                        arrowprops={"arrowstyle": "->", "color": "C0"})
            ax.set_title(f"{_field_label(result, p.row, p.col)}: rms {p.warp['residual_rms']:.2f}"
                         f" px, t/s {p.warp['anisotropy']:.1f}", fontsize=7)
            _no_ticks(ax)
        for ax in axes[len(picks):]:
            ax.set_visible(False)
        if picks:
            axes[0].quiverkey(q, 0.75, -0.08, scale, f"{scale:.2f} px", labelpos="E")
        fig.suptitle("residual displacement after the affine part, on the centre PSF "
                     "(orange; blue: tangential direction)")
    return fig


def figure_warp_summary(result: GridCharacterization) -> Figure:
    """Residual displacement vs field angle with its growth fit, and the tangential/sagittal
    anisotropy against the geometric-optics prediction."""
    theta = result.field_angle_deg()
    with publication_style():
        fig = new_figure(PAGE_IN, 2.4)
        ax1, ax2 = fig.subplots(1, 2)
        if theta is None:
            ax1.text(0.5, 0.5, "no field angles in the manifest", ha="center",
                     transform=ax1.transAxes)
            ax2.set_visible(False)
            return fig
        reliable = result.table("overlap") >= RELIABLE_OVERLAP
        rms = result.warp_table("residual_rms")
        rt, rs = result.warp_table("rms_tangential"), result.warp_table("rms_sagittal")
        for sel, marker, label in [(reliable, "o", "overlap ≥ 50%"),
                                   (~reliable, "x", "overlap < 50%")]:
            ax1.plot(theta[sel], rms[sel], marker, color="C0", ls="", label=f"total, {label}")
        ax1.plot(theta[reliable], rt[reliable], "^", color="C1", ls="", label="tangential")
        ax1.plot(theta[reliable], rs[reliable], "v", color="C2", ls="", label="sagittal")
        growth = result.warp_growth
        if growth is not None:
            t = np.linspace(0, np.nanmax(theta), 100)
            ax1.plot(t, np.sqrt(growth.floor**2 + (growth.scale_10deg * (t / 10) ** growth.exponent)
                                ** 2), "k-", lw=0.8,
                     label=f"fit: θ^{growth.exponent:.2f}±{growth.exponent_std:.2f}")
        ax1.set_xlabel("field angle θ (°)")
        ax1.set_ylabel("residual displacement rms (px)")
        ax1.legend(frameon=False)
        anis = result.warp_table("anisotropy")
        ax2.plot(theta[reliable], anis[reliable], "o", label="measured (transport spectrum)")
        t = np.linspace(max(0.2, np.nanmin(theta[theta > 0])), np.nanmax(theta), 100)
        ax2.plot(t, geometric_anisotropy(t), "k-", lw=0.8,
                 label="geometric optics (1/cos³θ−1)/(1/cosθ−1)")
        ax2.set_xlabel("field angle θ (°)")
        ax2.set_ylabel("tangential / sagittal")
        ax2.set_ylim(0, max(4.0, float(np.nanmax(anis[reliable])) * 1.1)
                     if np.isfinite(anis[reliable]).any() else 4.0)
        ax2.legend(frameon=False)
    return fig
