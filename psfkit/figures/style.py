"""Publication style and saving for all psfkit figures (PNG at 300 dpi and vector PDF)."""

from __future__ import annotations

import base64
import contextlib
import io
from collections.abc import Iterator
from pathlib import Path

import matplotlib
from matplotlib.figure import Figure

from psfkit.io.atomic import atomic_file

STYLE = {
    "font.size": 8,
    "axes.titlesize": 8,
    "axes.labelsize": 8,
    "xtick.labelsize": 7,
    "ytick.labelsize": 7,
    "legend.fontsize": 7,
    "axes.linewidth": 0.6,
    "lines.linewidth": 1.0,
    "lines.markersize": 3.5,
    "savefig.dpi": 300,
    "savefig.bbox": "tight",
    "savefig.pad_inches": 0.02,
    "pdf.fonttype": 42,  # embed TrueType: text stays editable in a paper's figure
    "ps.fonttype": 42,
    "image.interpolation": "nearest",
    "axes.spines.top": False,
    "axes.spines.right": False,
}

#: widths (inches) of a single and a double journal column
COLUMN_IN, PAGE_IN = 3.5, 7.2


@contextlib.contextmanager
def publication_style() -> Iterator[None]:
    """Temporarily apply the toolkit's figure style."""
    with matplotlib.rc_context(STYLE):
        yield


def new_figure(width_in: float, height_in: float) -> Figure:
    """A figure detached from pyplot's global state: no backend or display needed, safe in
    threads and long sessions (Jupyter shows it with ``display(fig)``)."""
    return Figure(figsize=(width_in, height_in), layout="constrained")


def save_figure(fig: Figure, stem: str | Path, formats: tuple[str, ...] = ("png", "pdf")
                ) -> list[Path]:
    """Write ``stem.png`` and ``stem.pdf`` atomically; returns the paths."""
    paths = []
    for fmt in formats:
        path = Path(f"{stem}.{fmt}")
        with publication_style(), atomic_file(path) as tmp:
            fig.savefig(tmp, format=fmt)
        paths.append(path)
    return paths


def png_base64(fig: Figure, dpi: int) -> str:
    """``fig`` as a base64-encoded PNG at ``dpi`` in the publication style (for an ``<img>``
    embedded in an HTML page)."""
    buffer = io.BytesIO()
    with publication_style():
        fig.savefig(buffer, format="png", dpi=dpi)
    return base64.b64encode(buffer.getvalue()).decode()
