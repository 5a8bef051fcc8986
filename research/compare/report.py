"""Writing a learned-vs-measured comparison: figures, ``compare.json`` and an HTML page.

``write_comparison`` creates its output folder atomically::

    OUT/
      compare.html        the comparison section as a page, figures embedded
      compare.json        every number (KernelComparison.to_dict)
      figures/fig7_learned_vs_measured[_zoom].png|pdf, displacements.png|pdf
"""

from __future__ import annotations

import html
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from matplotlib.figure import Figure

from psfkit import __version__
from psfkit.io.atomic import atomic_directory
from psfkit.report.figures.style import save_figure, write_figures
from psfkit.report.html import figures_html, grid_table, html_page, html_table
from research.compare import KernelComparison
from research.compare.figures import figure_displacements, figure_learned_vs_measured

FIGURES = (
    ("fig7_learned_vs_measured", "Fig. 7 layout: learned kernels, their differences, and the "
     "same for the kernels fitted to the grid", "kernels", None),
    ("fig7_learned_vs_measured_zoom", "Fig. 7, central part of the caustic (sub-pixel "
     "displacements of the spots)", "kernels", 0.3),
    ("displacements", "Local displacement of K_k relative to K_base: learned, measured "
     "eigen-kernels, predicted by the measured warps", "displacements", None),
)


def _metric_rows(comparison: KernelComparison) -> str:
    head = ("model", "kernel", "vs", "corr", "corr_u", "corr_v", "EPE (px)", "slope",
            "RMS model (px)", "RMS measured (px)", "diff. NCC")
    body = []
    for cmp in (comparison.learned, comparison.initial):
        if cmp is None:
            continue
        for name, m in cmp.metrics.items():
            for vs, key in (("measured kernels", "vs_measured_kernels"),
                            ("measured warp", "vs_measured_warp")):
                a = m[key]
                if a is None:
                    continue
                body.append((cmp.label, f"K_{name}", vs, a["corr"], a["corr_u"], a["corr_v"],
                             a["epe_px"], a["slope"], a["rms_a_px"], a["rms_b_px"],
                             m["difference_ncc"] if key == "vs_measured_kernels" else None))
    return grid_table(head, body, ".3f")


def _change_rows(comparison: KernelComparison) -> str:
    head = ("change", "kernel", "gain", "gain part", "pedestal", "displacement", "other",
            "outside mass")
    body = []
    for vs, split in comparison.kernel_change.items():
        if not isinstance(split, dict):
            continue
        for name, part in split.items():
            if name == "all":
                continue
            f = part["fractions"]
            body.append((vs.replace("_", " "), f"K_{name}", part["gain"], f["gain"],
                         f["pedestal"], f["displacement"], f["other"],
                         part["outside_mass_fraction"]))
    if not body:
        return ""
    return ("<p>Kernel change split (light fractions, research/compare/README.md): gain on "
            "the caustic, pedestal outside its dilated support, displacement (optical flow), "
            "other.</p>"
            + grid_table(head, body, ".3f"))


def html_section(comparison: KernelComparison, figures: list[tuple[str, str, str]]) -> str:
    """The comparison as an HTML ``<section>`` (for a report page); ``figures`` are
    ``(stem, caption, base64 PNG)``."""
    doc = comparison.to_dict()
    angles = []
    for cmp in (comparison.learned, comparison.initial):
        if cmp is None:
            continue
        for what, values in (("eigen-kernels", cmp.angles_eigen_deg),
                             ("top PCA modes", cmp.angles_pca_deg)):
            angles.append((f"{cmp.label} vs measured {what} (deg)",
                           "–" if values is None else ", ".join(f"{a:.1f}" for a in values)))
    ceiling = [(f"measured K_{n} vs measured warp: corr", a["corr"])
               for n, a in comparison.measured_kernels_vs_warp.items()]
    notes = "".join(f"<li>{html.escape(n)}</li>" for n in doc["notes"]) or "<li>none</li>"
    figs = figures_html(figures)
    return f"""<section id="learned-vs-measured">
<h2>Learned vs measured eigen-kernels</h2>
<p>Displacements D = (D_u, D_v) in pixels of the kernel file's sensor grid (u = column,
v = row), K_k(x + D(x)) ≈ K_base(x), on the caustic mask of the measured K_base
({doc['mask_pixels']} px). "Measured warp" is the displacement predicted from the dense flow
between the centre PSF and the outermost reliable PSFs on the kernel's axis (both sides),
divided by the change of the kernel's weight. Correlations are Pearson over the mask;
"–" means undefined (a map without displacement). See research/compare/README.md.</p>
{html_table([(k, v) for k, v in angles] + ceiling)}
{_metric_rows(comparison)}
{_change_rows(comparison)}
<div class="warn"><b>Notes</b><ul>{notes}</ul></div>
{figs}
</section>"""


def _page(section: str) -> str:
    return html_page("Learned vs measured kernels", f"<p>psfkit {html.escape(__version__)}. "
                     f'Numbers: <a href="compare.json">compare.json</a>.</p>\n{section}\n')


def comparison_figures(comparison: KernelComparison) -> list[tuple[str, str, Any]]:
    """``(stem, caption, Figure)`` of every comparison figure."""
    out = []
    for stem, caption, kind, zoom in FIGURES:
        fig = figure_learned_vs_measured(comparison, zoom=zoom) if kind == "kernels" \
            else figure_displacements(comparison)
        out.append((stem, caption, fig))
    return out


def write_comparison(comparison: KernelComparison, out_dir: str | os.PathLike,
                     overwrite: bool = False,
                     extra_figures: Sequence[tuple[str, Figure]] = (),
                     extra_files: Sequence[tuple[str, str]] = ()) -> Path:
    """Write figures (PNG + PDF), ``compare.json`` and ``compare.html`` into ``out_dir``
    atomically, with ``extra_figures`` ``(stem, figure)`` under ``figures/`` and
    ``extra_files`` ``(name, text)`` in the same transaction."""
    out_dir = Path(out_dir)
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        fig_dir = tmp / "figures"
        embedded = write_figures(fig_dir, comparison_figures(comparison), dpi=120)
        for stem, fig in extra_figures:
            save_figure(fig, fig_dir / stem)
        doc = comparison.to_dict()
        doc["software"] = {"psfkit": __version__}
        (tmp / "compare.json").write_text(json.dumps(doc, indent=1) + "\n", encoding="utf-8")
        (tmp / "compare.html").write_text(_page(html_section(comparison, embedded)),
                                          encoding="utf-8")
        for name, text in extra_files:
            if Path(name).name != name or name in ("compare.json", "compare.html", "figures"):
                raise ValueError(f"extra file name {name!r}: a new plain file name is needed")
            (tmp / name).write_text(text, encoding="utf-8")
    return out_dir
