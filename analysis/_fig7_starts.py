"""Fig. 7 remade: measured modes (and, on the virtual bench, the operator oracle) next to the
kernels learned from several starts (seeded from the measured fit, from one PSF), with the
displacement fields as arrows over the caustic and the numbers that say whether the learned
kernels are the measured ones, and the oracle's."""

from __future__ import annotations

import textwrap
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from psfkit.calibration.preprocess import luminance
from psfkit.calibration.support import support_box
from psfkit.report.figures.eigen import difference_limit
from psfkit.report.figures.style import PAGE_IN, new_figure, publication_style
from research.compare.figures import arrow_grid, draw_kernel_row, quiver_panel
from research.compare.results import KernelComparison, KernelSetComparison


def start_numbers(comparison: KernelComparison) -> dict[str, Any]:
    """The caption's numbers for one start: displacement correlation and difference NCC vs
    the measured eigen-kernels, pedestal share of the change and outside-support mass (vs the
    initial kernels when known, else vs the measured ones), angles to the top PCA modes."""
    doc = comparison.to_dict()
    change = doc["kernel_change"]
    split = change.get("learned_vs_initial", change["learned_vs_measured"])
    out: dict[str, Any] = {
        "pedestal_share": split["all"]["pedestal_share_of_change"],
        "outside_mass": split["all"]["outside_mass_fraction"],
        "angles_pca_deg": doc["learned"]["principal_angles_deg_vs_measured_pca"]}
    for name, m in doc["learned"]["metrics"].items():
        out[f"{name}_disp_corr"] = m["vs_measured_kernels"]["corr"]
        out[f"{name}_diff_ncc"] = m["difference_ncc"]
    return out


def _fmt(value: Any) -> str:
    return "n/a" if value is None or value != value else f"{value:+.2f}"


def caption(numbers: dict[str, dict[str, Any]]) -> str:
    """One caption sentence per start."""
    parts = []
    for label, n in numbers.items():
        names = [k[:-10] for k in n if k.endswith("_disp_corr")]
        disp = " / ".join(_fmt(n[f"{k}_disp_corr"]) for k in names)
        ncc = " / ".join(_fmt(n[f"{k}_diff_ncc"]) for k in names)
        angles = n["angles_pca_deg"]
        parts.append(f"{label}: displacement corr. (K_{'/K_'.join(names)}) {disp}, "
                     f"difference NCC {ncc}, pedestal {100 * n['pedestal_share']:.1f} % of the "
                     f"change, {100 * n['outside_mass']:.1f} % of the kernel mass outside the "
                     f"caustic support" + ("" if angles is None else
                                           ", angles to top PCA modes "
                                           + ", ".join(f"{a:.0f}°" for a in angles)))
    return "; ".join(parts) + "."


def _numbers_text(n: dict[str, Any]) -> str:
    names = [k[:-9] for k in n if k.endswith("_diff_ncc")]
    ncc = " / ".join("n/a" if n[f"{k}_diff_ncc"] != n[f"{k}_diff_ncc"]
                     else f"{n[f'{k}_diff_ncc']:.2f}" for k in names)
    disp = " / ".join(_fmt(n[f"{k}_disp_corr"]) for k in names)
    angles = n.get("angles_deg")
    return (f"difference NCC (K_{'/K_'.join(names)}) {ncc}, displacement corr. {disp}"
            + ("" if not angles else ", principal angles "
               + ", ".join(f"{a:.0f}°" for a in angles)))


def oracle_caption(oracle: str, numbers: dict[str, dict[str, Any]]) -> str:
    """One sentence: each model (learned starts, the measured fit) against the oracle.

    ``numbers``: label → :meth:`~research.compare.results.KernelSetComparison.numbers` of that
    model compared with the oracle (the oracle the reference)."""
    parts = [f"{label}: {_numbers_text(n)}" for label, n in numbers.items()]
    return f"Against the operator oracle ({oracle}): " + "; ".join(parts) + "."


def figure_starts(comparisons: dict[str, KernelComparison],
                  oracle: tuple[str, KernelSetComparison] | None = None) -> Figure:
    """Rows: the measured fit, the oracle (``(label, comparison of the oracle with the
    measured modes)``, when given), then the learned kernels of each start. Columns:
    ``K_base``, the correction kernels, their differences from ``K_base``, and their
    displacement fields (colour = length in px, arrows = direction, on the measured caustic
    mask)."""
    first = next(iter(comparisons.values()))
    names = first.kernel_names
    rows: list[tuple[str, np.ndarray, dict]] = [
        ("measured fit", first.measured.model.kernels, first.measured_displacements)]
    if oracle is not None:
        rows.append((oracle[0], oracle[1].kernels, oracle[1].displacements))
    rows += [(f"learned: {label}", c.learned.kernels, c.learned.displacements)
             for label, c in comparisons.items()]
    k = len(names)
    box = support_box(luminance(first.measured.model.kernels[0]))
    mask_box, step = arrow_grid(first.mask, 12)
    values = [np.hypot(*d.field[:, d.mask]) for _, _, disp in rows for d in disp.values()
              if d.mask.any()]
    vmax = max((float(np.percentile(v, 95)) for v in values if v.size), default=1.0) or 1.0
    lums = [np.stack([luminance(x) for x in kernels])[:, box[0], box[1]]
            for _, kernels, _ in rows]
    limit = max(difference_limit(lum) for lum in lums)     # the rows are compared: one scale
    cols = 3 * k - 2
    with publication_style():
        fig = new_figure(PAGE_IN, 1.2 * len(rows) + 1.0)
        axes = np.atleast_2d(fig.subplots(len(rows), cols, squeeze=False))
        disp_image = None
        for r, ((label, _, disp), lum) in enumerate(zip(rows, lums, strict=True)):
            diff_image = draw_kernel_row(axes[r], lum, names, textwrap.fill(label, 16),
                                         titles=r == 0, label_size=7, limit=limit)
            for i in range(1, k):
                ax = axes[r, 2 * k + i - 2]
                d = disp.get(names[i])
                if d is None:
                    ax.set_visible(False)
                    continue
                disp_image = quiver_panel(ax, d, mask_box, vmax,
                                          f"D_{names[i]}" if r == 0 else "", step)
        for image, columns, label in (
                (axes[0, 0].images[0], slice(0, k), "kernel (fraction of the row's peak, √ scale)"),
                (diff_image, slice(k, 2 * k - 1), "K_k − K_base (fraction of the row's peak)"),
                (disp_image, slice(2 * k - 1, cols), "|D| (px)")):
            if image is not None:
                fig.colorbar(image, ax=list(axes[:, columns].ravel()), location="bottom",
                             shrink=0.9, label=label)
        fig.suptitle(f"measured modes{' and oracle' if oracle is not None else ''} vs "
                     "learned kernels (arrows: displacement)")
    return fig
