"""Fig. 2 of the paper: the centre PSF, two off-axis PSFs, their differences and the MAE."""

from __future__ import annotations

import matplotlib
import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure

from psfkit.calibration.preprocess import luminance
from psfkit.calibration.support import crop_window
from psfkit.characterization.results import GridCharacterization
from psfkit.report.figures.grid_layout import field_label, scatter_coordinates, support_box
from psfkit.report.figures.style import (
    PAGE_IN,
    new_figure,
    no_ticks,
    psf_image,
    publication_style,
)


def figure_shift_variance(result: GridCharacterization) -> Figure:
    """Centre PSF (A), off-axis PSFs B and C, their differences from A after shift
    compensation, and the MAE against position; cropped to A's support, on A's scale."""
    box = support_box(result)
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
    panels = [(ref, f"A\n{field_label(result, *result.center)}")]
    panels += [(np.where(ok, crop_window(luminance(result.examples[k][0]), box), np.nan),
                f"{letter}\n{field_label(result, *k)}")
               for letter, k, ok in zip(letters, keys, valid, strict=True)]
    diffs = [(ref - image) / peak for image, _ in panels[1:]]
    with publication_style():
        fig = new_figure(PAGE_IN, 2.7)
        axes = fig.subplots(1, 2 + 2 * n_off, width_ratios=[1] * (1 + 2 * n_off) + [1.7])
        for ax, (img, title) in zip(axes[:1 + n_off], panels, strict=True):
            im = psf_image(ax, img / peak)
            ax.set_title(title)
            no_ticks(ax)
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
                no_ticks(ax)
            fig.colorbar(im, ax=list(diff_axes), location="bottom", shrink=0.8,
                         label="difference (fraction of A's peak)")
        _mae_panel(axes[-1], result)
    return fig


def _mae_panel(ax: Axes, result: GridCharacterization) -> None:
    """MAE along the centre column (row of a one-row grid), or against the distance from the
    centre for an irregular scan."""
    if result.layout == "irregular":
        coords, unit = scatter_coordinates(result)
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
