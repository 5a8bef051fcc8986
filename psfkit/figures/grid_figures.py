"""Figures of a grid characterization: Fig. 2 of the paper, heat maps, montage, warp plots.

Each function takes a :class:`~psfkit.characterize.GridCharacterization` and returns a
matplotlib ``Figure`` (nothing is shown or saved; see :func:`psfkit.figures.save_figure`).
"""

from __future__ import annotations

import matplotlib
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


def _field_label(result: GridCharacterization, row: int, col: int) -> str:
    pos = result.positions[row * result.grid_shape[1] + col]
    if pos.field_deg is not None:
        return f"({pos.field_deg[0]:+.1f}°, {pos.field_deg[1]:+.1f}°)"
    return f"[{row}, {col}]"


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
        keys = sorted(result.examples, key=lambda k: abs(k[0] - result.center[0])
                      + abs(k[1] - result.center[1]))
        n_off = len(keys)
        fig = new_figure(PAGE_IN, 2.3)
        axes = fig.subplots(1, 2 + 2 * n_off, width_ratios=[1] * (1 + 2 * n_off) + [1.5])
        letters = "BC" if n_off == 2 else "C"
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
    of the shift map as arrows."""
    with publication_style():
        fig = new_figure(PAGE_IN, 4.6)
        axes = fig.subplots(2, 3)
        _heatmap(fig, axes[0, 0], result.table("mae") * 1e3, "MAE (shift comp.)", "×10⁻³",
                 ".2g", "magma", result.center)
        _heatmap(fig, axes[0, 1], result.table("mae_gain_compensated") * 1e3,
                 "MAE (shift + gain comp.)", "×10⁻³", ".2g", "magma", result.center)
        _heatmap(fig, axes[0, 2], result.table("gain"), "relative gain", "gain", ".2f",
                 "cividis", result.center)
        _heatmap(fig, axes[1, 0], result.table("quality"), "registration quality (NCC)",
                 "NCC", ".2f", "viridis", result.center)
        _heatmap(fig, axes[1, 1], result.table("overlap"), "overlap with centre PSF",
                 "fraction of sensor", ".2f", "Greys_r", result.center)
        ax = axes[1, 2]
        if result.shift_fit is not None:
            res = result.shift_fit.residuals
            n, m = result.grid_shape
            rows, cols = np.mgrid[0:n, 0:m]
            scale = max(float(np.max(np.hypot(res[..., 0], res[..., 1]))), 1e-9)
            q = ax.quiver(cols, rows, res[..., 0], -res[..., 1], angles="xy",
                          scale=2.5 * scale, scale_units="xy", color="C3")
            ax.quiverkey(q, 0.75, -0.2, scale, f"{scale:.2f} px", labelpos="E")
            ax.set_xlim(-0.7, m - 0.3)
            ax.set_ylim(n - 0.3, -0.7)
            ax.set_aspect("equal")
            ax.set_title(f"shift-map residual (rms {result.shift_fit.rms_residual:.3f} px)")
            ax.set_xlabel("column")
            ax.set_ylabel("row")
        else:
            ax.set_visible(False)
    return fig


def figure_montage(result: GridCharacterization) -> Figure:
    """The grid of PSFs (luminance, square-root scaled to the centre PSF's peak)."""
    thumbs = result.thumbnails
    n, m = result.grid_shape
    peak = float(thumbs[result.center].max()) or 1.0
    with publication_style():
        fig = new_figure(PAGE_IN, PAGE_IN * n * thumbs.shape[2] / (m * thumbs.shape[3]) + 0.3)
        axes = np.atleast_2d(fig.subplots(n, m, squeeze=False))
        for r in range(n):
            for c in range(m):
                ax = axes[r, c]
                ax.imshow(np.sqrt(np.clip(thumbs[r, c], 0, None) / peak), cmap="gray",
                          vmin=0, vmax=1)
                _no_ticks(ax)
                if (r, c) == result.center:
                    for spine in ax.spines.values():
                        spine.set_visible(True)
                        spine.set_color("red")
        fig.suptitle("PSF grid (√ intensity, common scale; red: centre)")
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
