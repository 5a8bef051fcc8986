"""Publication-quality figures (matplotlib, PNG + PDF)."""

from psfkit.report.figures.eigen import (
    difference_sizes,
    figure_eigen_diagnostics,
    figure_kernels,
    figure_weight_maps,
)
from psfkit.report.figures.maps import figure_maps
from psfkit.report.figures.montage import figure_montage
from psfkit.report.figures.shift_variance import figure_shift_variance
from psfkit.report.figures.style import (
    Fitted,
    fitted,
    new_figure,
    png_base64,
    publication_style,
    save_figure,
)
from psfkit.report.figures.warp import figure_warp, figure_warp_summary

__all__ = [
    "Fitted", "difference_sizes", "figure_eigen_diagnostics", "figure_kernels", "figure_maps",
    "figure_montage", "figure_shift_variance", "figure_warp", "figure_warp_summary",
    "figure_weight_maps", "fitted", "new_figure", "png_base64", "publication_style",
    "save_figure",
]
