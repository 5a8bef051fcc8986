"""Figures of eigen-kernel models: kernels and differences (Fig. 7), weight maps (Fig. 3),
and the diagnostics of a grid fit (scree plot, cross-validation, residuals)."""

from __future__ import annotations

from collections.abc import Sequence

import matplotlib
import numpy as np
from matplotlib.figure import Figure

from psfkit.figures.style import PAGE_IN, new_figure, publication_style
from psfkit.grid_fit import GridEigenResult
from psfkit.preprocess import luminance
from psfkit.weights import get_basis


def _crop_box(image: np.ndarray, level: float = 0.02, margin: int = 4) -> tuple[slice, slice]:
    rows, cols = np.nonzero(image > level * image.max())
    if rows.size == 0:
        return slice(None), slice(None)
    return (slice(max(rows.min() - margin, 0), rows.max() + margin + 1),
            slice(max(cols.min() - margin, 0), cols.max() + margin + 1))


def figure_kernels(kernels: np.ndarray, names: Sequence[str], title: str = "",
                   zoom: float | None = None) -> Figure:
    """Fig. 7: every kernel (√ luminance) and every kernel minus the base kernel.

    Parameters
    ----------
    kernels : numpy.ndarray
        ``(K, C, H, W)``, base kernel first.
    names : sequence of str
        Kernel names (``base, v, h`` for the paper's basis).
    zoom : float, optional
        Show only the central ``zoom`` fraction of the caustic's bounding box (sub-pixel spot
        displacements become visible).
    """
    lum = np.stack([luminance(k.astype(np.float32)) for k in kernels])
    box = _crop_box(lum[0])
    if zoom is not None:
        rs, cs = box
        r0, r1 = rs.start, rs.stop
        c0, c1 = cs.start, cs.stop
        hr, hc = int((r1 - r0) * zoom / 2), int((c1 - c0) * zoom / 2)
        mr, mc = (r0 + r1) // 2, (c0 + c1) // 2
        box = (slice(mr - hr, mr + hr), slice(mc - hc, mc + hc))
    lum = lum[:, box[0], box[1]]
    k = len(kernels)
    diffs = lum[1:] - lum[0]
    limit = float(np.percentile(np.abs(diffs), 99.9)) if k > 1 else 1.0
    peak = float(lum.max()) or 1.0
    with publication_style():
        fig = new_figure(PAGE_IN, 1.9 * (2 if k > 1 else 1) + 0.2)
        axes = np.atleast_2d(fig.subplots(2 if k > 1 else 1, k, squeeze=False))
        for i in range(k):
            ax = axes[0, i]
            ax.imshow(np.sqrt(np.clip(lum[i], 0, None) / peak), cmap="gray", vmin=0, vmax=1)
            ax.set_title(f"K_{names[i]}")
            ax.set_axis_off()
        if k > 1:
            cmap = matplotlib.colormaps["RdBu_r"]
            axes[1, 0].set_axis_off()
            for i in range(1, k):
                ax = axes[1, i]
                im = ax.imshow(diffs[i - 1], cmap=cmap, vmin=-limit, vmax=limit)
                ax.set_title(f"K_{names[i]} − K_{names[0]}")
                ax.set_axis_off()
            fig.colorbar(im, ax=list(axes[1, 1:]), shrink=0.8, label="difference (lum.)")
        if title:
            fig.suptitle(title)
    return fig


def figure_weight_maps(basis_name: str, sensor_shape: tuple[int, int]) -> Figure:
    """Fig. 3: the weight maps of a basis on the sensor (``1 − Wh − Wv``, ``Wv``, ``Wh`` for
    the paper's)."""
    basis = get_basis(basis_name)
    maps = basis.maps(sensor_shape)
    labels = ["base (1 − Σ W)"] + [f"W_{name}" for name in basis.kernel_names[1:]]
    with publication_style():
        n = len(maps)
        cols = min(n, 4)
        rows = int(np.ceil(n / cols))
        fig = new_figure(PAGE_IN, 1.9 * rows + 0.3)
        axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False).ravel())
        for ax, m, label in zip(axes, maps, labels, strict=False):
            im = ax.imshow(m, cmap="viridis", vmin=min(0.0, m.min()), vmax=max(1.0, m.max()))
            ax.set_title(label)
            ax.set_xlabel("u (px)")
            ax.set_ylabel("v (px)")
            fig.colorbar(im, ax=ax, shrink=0.8)
        for ax in axes[n:]:
            ax.set_visible(False)
        fig.suptitle(f"weight maps, basis {basis_name!r}")
    return fig


def figure_eigen_diagnostics(result: GridEigenResult) -> Figure:
    """Scree plot of the grid's PCA, cross-validated errors of the candidate models, and the
    in-sample residual of each position for both weight conventions."""
    with publication_style():
        fig = new_figure(PAGE_IN, 2.6)
        ax1, ax2, ax3, ax4 = fig.subplots(1, 4, width_ratios=[1.1, 1.6, 1, 1])
        if result.pca is not None:
            ranks = np.arange(1, len(result.pca.explained) + 1)
            ax1.semilogy(ranks, result.pca.residual(), "o-", label="uncentred")
            ax1.semilogy(ranks, result.pca.residual(centred=True), "s--", label="centred")
            ax1.set_xlabel("rank")
            ax1.set_ylabel("relative residual")
            ax1.set_title("PCA of the registered grid")
            ax1.legend(frameon=False)
        if result.cv is not None:
            errors = result.cv["held_out_relative_error"]
            names = list(errors)
            colors = ["0.6" if n == "centre PSF only" else
                      ("C0" if n.endswith("/sensor") else "C1") for n in names]
            ax2.barh(range(len(names)), [errors[n] for n in names], color=colors)
            ax2.set_yticks(range(len(names)), names)
            ax2.invert_yaxis()
            ax2.set_xlabel("held-out relative error")
            ax2.set_title(f"{result.cv['folds']}-fold leave-positions-out CV")
        for ax, conv in zip((ax3, ax4), ("sensor", "source"), strict=True):
            residual = result.residuals[conv]
            im = ax.imshow(residual, cmap="magma")
            ax.set_title(f"{conv}-side fit:\nresidual per position")
            ax.set_xticks(range(residual.shape[1]))
            ax.set_yticks(range(residual.shape[0]))
            ax.set_xlabel("column")
            ax.set_ylabel("row")
            fig.colorbar(im, ax=ax, shrink=0.6, location="bottom")
    return fig
