"""Figures of eigen-kernel models: kernels and differences (Fig. 7), weight maps (Fig. 3),
and the diagnostics of a grid fit (scree plot, cross-validation, residuals)."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import matplotlib
import numpy as np
from matplotlib import colors
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.image import AxesImage
from matplotlib.ticker import MaxNLocator

from psfkit.calibration.preprocess import luminance
from psfkit.calibration.support import support_box
from psfkit.fitting.grid.result import GridEigenResult
from psfkit.forward.weights import get_basis
from psfkit.report.figures.style import (
    PAGE_IN,
    Fitted,
    axis_labels,
    fitted,
    new_figure,
    no_ticks,
    psf_image,
    publication_style,
)

#: Fig. 7 in one row (the paper's layout) up to this many kernels; more wrap into rows
ONE_ROW_KERNELS = 4
#: panels per row of a wrapped Fig. 7 or Fig. 3
WRAP = 6


def zoom_box(box: tuple[slice, slice], zoom: float) -> tuple[slice, slice]:
    """The central ``zoom`` fraction of ``box``."""
    (r0, r1), (c0, c1) = (box[0].start, box[0].stop), (box[1].start, box[1].stop)
    hr, hc = max(1, int((r1 - r0) * zoom / 2)), max(1, int((c1 - c0) * zoom / 2))
    mr, mc = (r0 + r1) // 2, (c0 + c1) // 2
    return slice(max(mr - hr, 0), mr + hr), slice(max(mc - hc, 0), mc + hc)


def difference_limit(lum: np.ndarray) -> float:
    """Colour limit of ``K_k − K_base`` of ``(K, h, w)`` kernels, as a fraction of their peak
    (99.9th percentile of ``|difference|``; 1 where there is none)."""
    if len(lum) < 2:
        return 1.0
    diffs = (lum[1:] - lum[0]) / (float(np.nanmax(lum)) or 1.0)
    return float(np.percentile(np.abs(diffs), 99.9)) or 1.0


def draw_kernels(kernel_axes: Sequence[Axes], diff_axes: Sequence[Axes], lum: np.ndarray,
                 names: Sequence[str], titles: bool = True,
                 sizes: Sequence[Fitted] | None = None, limit: float | None = None
                 ) -> AxesImage | None:
    """The kernels' luminance ``lum`` ``(K, h, w)`` as fractions of their peak (√ scale), and
    ``K_k − K_base`` in that unit within ±``limit`` (default :func:`difference_limit`).

    ``sizes`` (optional, one per difference) are printed under the titles; a non-significant
    difference is faded. Returns the last difference image (``None`` for one kernel).
    """
    k = len(names)
    peak = float(np.nanmax(lum)) or 1.0
    diffs = (lum[1:] - lum[0]) / peak
    limit = limit or difference_limit(lum)
    for i in range(k):
        ax = kernel_axes[i]
        psf_image(ax, lum[i] / peak)
        ax.set_title(f"K_{names[i]}" if titles else "")
        no_ticks(ax)           # (the axis stays: a row label may be set on it)
    cmap = matplotlib.colormaps["RdBu_r"]
    im = None
    for i in range(1, k):
        ax = diff_axes[i - 1]
        size = sizes[i - 1] if sizes is not None else None
        faded = size is not None and not size.detected
        im = ax.imshow(diffs[i - 1], cmap=cmap, vmin=-limit, vmax=limit,
                       alpha=0.35 if faded else None)
        title = f"K_{names[i]} − K_{names[0]}" if titles else ""
        if size is not None:
            title += f"\n{size.text('.2g')}"
        ax.set_title(title, color=size.colour if size is not None else "k")
        ax.set_axis_off()
    return im


def _kernel_axes(fig: Figure, k: int) -> tuple[list[Axes], list[Axes]]:
    """Axes for ``k`` kernels and ``k − 1`` differences: one row up to
    :data:`ONE_ROW_KERNELS` kernels, else kernels above differences, :data:`WRAP` a row."""
    if k <= ONE_ROW_KERNELS:
        axes = list(np.atleast_1d(fig.subplots(1, 2 * k - 1)))
        return axes[:k], axes[k:]
    top, bottom = fig.subfigures(2, 1, height_ratios=[math.ceil(k / WRAP),
                                                      math.ceil((k - 1) / WRAP)])
    out = []
    for sub, n in ((top, k), (bottom, k - 1)):
        grid = list(np.atleast_1d(sub.subplots(math.ceil(n / WRAP), min(n, WRAP),
                                               squeeze=False).ravel()))
        for ax in grid[n:]:
            ax.set_visible(False)
        out.append(grid[:n])
    return out[0], out[1]


def figure_kernels(kernels: np.ndarray, names: Sequence[str], title: str = "",
                   zoom: float | None = None, sizes: Sequence[Fitted] | None = None
                   ) -> Figure:
    """Fig. 7: every kernel ``(K, C, H, W)`` (base first) and its difference from the base,
    cropped to the base kernel's support, in one unit (the kernels' peak).

    ``zoom``: only the central fraction of the support's box; ``sizes``: the ``K − 1``
    differences' sizes (:func:`difference_sizes`), non-significant ones greyed.
    """
    lum = np.stack([luminance(k.astype(np.float32)) for k in kernels])
    box = support_box(lum[0])
    if zoom is not None:
        box = zoom_box(box, zoom)
    lum = lum[:, box[0], box[1]]
    k = len(kernels)
    rows = 1 if k <= ONE_ROW_KERNELS else math.ceil(k / WRAP) + math.ceil((k - 1) / WRAP)
    with publication_style():
        fig = new_figure(PAGE_IN, 2.6 if rows == 1 else 1.3 * rows + 0.8)
        kernel_axes, diff_axes = _kernel_axes(fig, k)
        im = draw_kernels(kernel_axes, diff_axes, lum, names, sizes=sizes)
        fig.colorbar(kernel_axes[0].images[0], ax=kernel_axes, location="bottom", shrink=0.8,
                     label="kernel (fraction of peak, √ scale)")
        if im is not None:
            fig.colorbar(im, ax=diff_axes, location="bottom", shrink=0.8,
                         label=f"K_k − K_{names[0]} (fraction of peak)")
        if title:
            fig.suptitle(title)
    return fig


def difference_sizes(result: Any, names: Sequence[str]) -> list[Fitted] | None:
    """Sizes of ``K_k − K_base`` from ``result.differences`` (by kernel name: ``value``,
    ``sigma``, ``significant``); ``None`` where the result lacks them."""
    table = getattr(result, "differences", None)
    if not isinstance(table, dict) or not all(name in table for name in names[1:]):
        return None
    return [fitted(table[name], "value") for name in names[1:]]


def figure_weight_maps(basis_name: str, sensor_shape: tuple[int, int]) -> Figure:
    """Fig. 3: the weight maps of a basis on the sensor, each on its own colour range."""
    basis = get_basis(basis_name)
    maps = basis.maps(sensor_shape)
    labels = ["base (1 − Σ W)"] + [f"W_{name}" for name in basis.kernel_names[1:]]
    with publication_style():
        n = len(maps)
        cols = min(n, 3)
        rows = int(np.ceil(n / cols))
        aspect = float(np.clip(sensor_shape[0] / sensor_shape[1], 0.4, 1.6))
        fig = new_figure(PAGE_IN, rows * (1.5 * aspect + 0.8) + 0.35)   # bars as tall as maps
        axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False).ravel())
        for ax, m, label in zip(axes, maps, labels, strict=False):
            lo, hi = float(m.min()), float(m.max())
            if hi - lo < 1e-6:          # a constant map (the SI basis): a readable bar
                lo, hi = lo - 0.5, hi + 0.5
            im = ax.imshow(m, cmap="viridis", vmin=lo, vmax=hi)
            ax.set_title(label)
            axis_labels(ax, "u (px)", "v (px)", (4, 4))
            fig.colorbar(im, ax=ax, shrink=0.8, pad=0.08, label="weight (dimensionless)")
        for ax in axes[n:]:
            ax.set_visible(False)
        fig.suptitle(f"weight maps, basis {basis_name!r}")
    return fig


def _cv_panel(ax: Axes, cv: dict[str, Any]) -> None:
    errors = cv["held_out_relative_error"]
    names = list(errors)
    # 1σ of each candidate's held-out error, where the cross-validation provides it
    sigma = next((cv[key] for key in ("held_out_relative_error_sigma",
                                      "held_out_relative_error_std")
                  if isinstance(cv.get(key), dict)), None)
    bar_colours = ["0.6" if n == "centre PSF only" else
                   ("C0" if n.endswith("/sensor") else "C1") for n in names]
    xerr = [sigma.get(n, 0.0) for n in names] if sigma else None
    ax.barh(range(len(names)), [errors[n] for n in names], color=bar_colours, xerr=xerr,
            error_kw={"lw": 0.8, "capsize": 2})
    ax.set_yticks(range(len(names)), names)
    ax.invert_yaxis()
    ax.xaxis.set_major_locator(MaxNLocator(4))
    ax.set_xlabel("held-out relative error" + (" (±1σ)" if sigma else ""))
    ax.set_title(f"{cv['folds']}-fold leave-positions-out CV")


def _residual_panels(fig: Figure, axes: Sequence[Axes], result: GridEigenResult) -> None:
    """In-sample residual per position for both conventions on one scale (lattice maps, or
    points at the PSFs' sensor positions for an irregular scan)."""
    residuals = [result.residuals[conv] for conv in ("sensor", "source")]
    values = np.concatenate([r.ravel() for r in residuals])
    norm = colors.Normalize(float(np.nanmin(values)), float(np.nanmax(values)))
    irregular = result.layout == "irregular"
    for ax, conv, residual in zip(axes, ("sensor", "source"), residuals, strict=True):
        if irregular:       # the registered shift places each PSF on the sensor
            shifts = result.shifts[0]
            ok = np.isfinite(residual[0])
            im = ax.scatter(shifts[ok, 0], shifts[ok, 1], c=residual[0][ok], cmap="magma",
                            norm=norm, s=18, ec="k", lw=0.3)
            ax.set_aspect("equal", adjustable="datalim")
            ax.invert_yaxis()
            axis_labels(ax, "PSF shift u (px)", "PSF shift v (px)", (3, 4))
        else:
            im = ax.imshow(residual, cmap="magma", norm=norm)
            axis_labels(ax, "column", "row", (5, 5), integer=True)
        ax.set_title(f"{conv}-side fit:\nresidual per position")
    fig.colorbar(im, ax=list(axes), location="bottom", shrink=0.8,
                 label="in-sample error (‖model − PSF‖ / ‖PSF‖)")


def figure_eigen_diagnostics(result: GridEigenResult) -> Figure:
    """Scree plot of the grid's PCA, cross-validated errors of the candidates (±1σ where known)
    and in-sample residuals per position."""
    panels = [result.pca is not None, result.cv is not None]
    ratios = [r for r, shown in zip((1.1, 1.6), panels, strict=True) if shown] + [1, 1]
    with publication_style():
        fig = new_figure(PAGE_IN, 2.8)
        axes = list(np.atleast_1d(fig.subplots(1, len(ratios), width_ratios=ratios)))
        if result.pca is not None:
            ax = axes.pop(0)
            ranks = np.arange(1, len(result.pca.explained) + 1)
            ax.semilogy(ranks, result.pca.residual(), "o-", label="uncentred")
            ax.semilogy(ranks, result.pca.residual(centred=True), "s--", label="centred")
            ax.set_xlabel("rank")
            ax.set_ylabel("relative residual")
            ax.set_title("PCA of the registered grid")
            ax.legend(frameon=False)
        if result.cv is not None:
            _cv_panel(axes.pop(0), result.cv)
        _residual_panels(fig, axes, result)
    return fig
