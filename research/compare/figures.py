"""Figures of a learned-vs-measured kernel comparison (:mod:`research.compare`): Fig. 7 for the
learned kernels next to the measured ones, and the displacement maps."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.image import AxesImage

from psfkit.calibration.preprocess import luminance
from psfkit.calibration.support import support_box
from psfkit.calibration.warp import bounding_box
from psfkit.report.figures.eigen import difference_limit, draw_kernels, zoom_box
from psfkit.report.figures.style import PAGE_IN, new_figure, no_ticks, publication_style
from research.compare.displacement import DisplacementMap
from research.compare.results import KernelComparison


def _rows(comparison: KernelComparison) -> list[tuple[str, np.ndarray]]:
    rows = [("learned", comparison.learned.kernels)]
    if comparison.initial is not None:
        rows.append(("initial", comparison.initial.kernels))
    rows.append((reference_label(comparison), comparison.measured.model.kernels))
    return rows


def reference_label(comparison: KernelComparison) -> str:
    """The measured side's row label: the grid fit, or the kernel file it was given as."""
    measured = comparison.measured
    if measured.fit is not None:
        return "measured (grid fit)"
    return f"reference: {Path(measured.source).name or measured.source}"


def draw_kernel_row(axes: np.ndarray, lum: np.ndarray, names: tuple[str, ...] | list[str],
                    label: str, titles: bool = True, label_size: float | None = None,
                    limit: float | None = None) -> AxesImage:
    """One Fig. 7 row (:func:`draw_kernels`): ``lum`` ``(K, h, w)`` in ``axes[:K]``, the
    differences in ``axes[K:2K−1]``, ``label`` on the row; returns the last difference image."""
    k = len(names)
    im = draw_kernels(axes[:k], axes[k:2 * k - 1], lum, names, titles, limit=limit)
    axes[0].set_ylabel(label, fontsize=label_size)
    return im


def figure_learned_vs_measured(comparison: KernelComparison, zoom: float | None = None,
                               extra_rows: Sequence[tuple[str, np.ndarray]] = ()) -> Figure:
    """Fig. 7 layout for the learned, initial (if given) and measured kernels, one row each, on
    one crop. ``zoom``: the central fraction of the caustic's box; ``extra_rows``: more
    ``(label, (K, C, H, W) kernels)`` rows on the comparison grid."""
    names = comparison.kernel_names
    rows = [(label, np.stack([luminance(k) for k in kernels]))
            for label, kernels in _rows(comparison)]
    box = support_box(rows[-1][1][0])           # the measured kernels' crop
    rows += [(label, np.stack([luminance(k) for k in kernels])) for label, kernels in extra_rows]
    if zoom is not None:
        box = zoom_box(box, zoom)
    k = len(names)
    cols = 2 * k - 1
    lums = [lum[:, box[0], box[1]] for _, lum in rows]
    limit = max(difference_limit(lum) for lum in lums)    # the rows are compared: one scale
    with publication_style():
        fig = new_figure(PAGE_IN, 1.45 * len(rows) + 0.8)
        axes = np.atleast_2d(fig.subplots(len(rows), cols, squeeze=False))
        for r, ((label, _), lum) in enumerate(zip(rows, lums, strict=True)):
            im = draw_kernel_row(axes[r], lum, names, label, titles=r == 0, limit=limit)
        fig.colorbar(axes[0, 0].images[0], ax=list(axes[:, :k].ravel()), location="bottom",
                     shrink=0.8, label="kernel (fraction of the row's peak, √ scale)")
        fig.colorbar(im, ax=list(axes[:, k:].ravel()), location="bottom", shrink=0.8,
                     label="K_k − K_base (fraction of the row's peak)")
        fig.suptitle("learned vs measured eigen-kernels (Fig. 7 layout)"
                     + (" – zoom" if zoom else ""))
    return fig


def quiver_panel(ax: Axes, disp: DisplacementMap, box: tuple[slice, slice], vmax: float,
                  title: str, step: int) -> AxesImage:
    field = disp.field[:, box[0], box[1]]
    mask = disp.mask[box[0], box[1]]
    magnitude = np.where(mask, np.hypot(field[0], field[1]), np.nan)
    im = ax.imshow(magnitude, cmap="viridis", vmin=0, vmax=vmax)
    rows, cols = np.mgrid[step // 2:mask.shape[0]:step, step // 2:mask.shape[1]:step]
    keep = mask[rows, cols]
    if keep.any():
        # image axes: v grows downwards, so the arrow's v component is drawn as is with
        # angles="xy" on an inverted y axis
        ax.quiver(cols[keep], rows[keep], field[0][rows, cols][keep],
                  field[1][rows, cols][keep], color="w", angles="xy", scale_units="xy",
                  scale=vmax / (1.5 * step), width=0.005,
                  headwidth=4)
    ax.set_title(title)
    no_ticks(ax)
    return im


def arrow_grid(mask: np.ndarray, arrows: int) -> tuple[tuple[slice, slice], int]:
    """The box of a caustic ``(H, W)`` bool ``mask`` (2 px margin) and the spacing (px, at
    least 2) of about ``arrows`` arrows across it."""
    box = bounding_box(mask, margin=2)
    return box, max(2, max(box[0].stop - box[0].start, box[1].stop - box[1].start) // arrows)


def figure_displacements(comparison: KernelComparison, arrows: int = 14) -> Figure:
    """Displacement maps of ``K_k`` relative to ``K_base`` (colour: length in px; arrows:
    direction), one row per correction kernel: learned, initial, measured, warp-predicted."""
    names = list(comparison.kernel_names[1:])
    box, step = arrow_grid(comparison.mask, arrows)
    rows = []
    for name in names:
        maps: dict[str, DisplacementMap | None] = {
            "learned": comparison.learned.displacements.get(name)}
        if comparison.initial is not None:
            maps["initial"] = comparison.initial.displacements.get(name)
        maps["measured kernels"] = comparison.measured_displacements.get(name)
        maps["measured warp"] = comparison.measured.warps.get(name)
        rows.append(maps)
    # a column nothing fills (no warps for a kernel-file reference) is left out
    columns = [c for c in rows[0] if any(row[c] is not None for row in rows)] if rows else []
    with publication_style():
        fig = new_figure(PAGE_IN, 1.75 * len(names) + 0.4)
        axes = np.atleast_2d(fig.subplots(len(names), max(1, len(columns)), squeeze=False))
        for r, (name, maps) in enumerate(zip(names, rows, strict=True)):
            values = [np.hypot(*d.field[:, d.mask]) for d in maps.values()
                      if d is not None and d.mask.any()]
            # robust colour scale: a few large flow errors must not wash out the maps
            vmax = max((float(np.percentile(v, 95)) for v in values if v.size), default=1.0)
            vmax = vmax if vmax > 0 else 1.0
            im = None
            for ax, label in zip(axes[r], columns, strict=False):
                disp = maps[label]
                if disp is None:            # nothing to draw: no empty panel
                    ax.set_visible(False)
                    continue
                im = quiver_panel(ax, disp, box, vmax, f"K_{name}: {label}", step)
            if im is not None:
                fig.colorbar(im, ax=list(axes[r]), shrink=0.8, label="|D| (px)")
        fig.suptitle("local displacement of K_k relative to K_base")
    return fig
