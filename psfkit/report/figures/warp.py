"""Warp plots of a grid characterization: the residual displacement fields after the affine
part as arrows over the centre PSF, and their growth with field angle against the
geometric-optics anisotropy."""

from __future__ import annotations

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from psfkit.calibration.alignment import RELIABLE_OVERLAP
from psfkit.calibration.preprocess import luminance
from psfkit.calibration.support import crop_window
from psfkit.calibration.warp import geometric_anisotropy
from psfkit.characterization.results import QUIVER_CELLS, GridCharacterization
from psfkit.numerics.resample import binning_factor
from psfkit.report.figures.grid_layout import field_label, support_box
from psfkit.report.figures.style import (
    COLUMN_IN,
    PAGE_IN,
    fitted,
    new_figure,
    no_ticks,
    psf_image,
    publication_style,
)


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
    box = support_box(result)
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
            psf_image(ax, ref / peak, extent=(c0 - 0.5, c1 - 0.5, r1 - 0.5, r0 - 0.5))
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
            ax.set_title(f"{field_label(result, p.row, p.col)}\n{_warp_numbers(p.warp)}")
            no_ticks(ax)
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
    """Residual displacement vs field angle (or distance) with its growth fit, and the
    measured tangential/sagittal anisotropy against geometric optics."""
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
