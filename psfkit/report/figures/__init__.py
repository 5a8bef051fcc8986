"""Publication-quality figures (matplotlib, PNG + PDF)."""

from psfkit.report.figures.compare import figure_displacements, figure_learned_vs_measured
from psfkit.report.figures.eigen import (
    difference_sizes,
    figure_eigen_diagnostics,
    figure_kernels,
    figure_weight_maps,
)
from psfkit.report.figures.grid import (
    figure_maps,
    figure_montage,
    figure_shift_variance,
    figure_warp,
    figure_warp_summary,
)
from psfkit.report.figures.style import (
    Fitted,
    fitted,
    new_figure,
    png_base64,
    publication_style,
    save_figure,
)

__all__ = [
    "Fitted",
    "difference_sizes",
    "figure_displacements",
    "figure_eigen_diagnostics",
    "figure_kernels",
    "figure_learned_vs_measured",
    "figure_maps",
    "figure_montage",
    "figure_shift_variance",
    "figure_warp",
    "figure_warp_summary",
    "figure_weight_maps",
    "fitted",
    "new_figure",
    "png_base64",
    "publication_style",
    "save_figure",
]
