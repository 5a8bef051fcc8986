"""Publication-quality figures (matplotlib, PNG + PDF)."""

from psfkit.figures.grid_figures import (
    figure_maps,
    figure_montage,
    figure_shift_variance,
    figure_warp,
    figure_warp_summary,
)
from psfkit.figures.style import new_figure, publication_style, save_figure

__all__ = ["figure_maps", "figure_montage", "figure_shift_variance", "figure_warp",
           "figure_warp_summary", "new_figure", "publication_style", "save_figure"]
