"""Publication style and saving (PNG at 300 dpi, PDF) for all psfkit figures. Conventions
(checked by tests/psfkit/test_figures.py): text ≥ 7 pt; colour bars labelled ``quantity
(unit)``, compared panels on one scale; PSFs cropped to their support on a √ scale, off-sensor
pixels in :data:`OFF_SENSOR`; fitted quantities with 1σ, greyed when not significant.
"""

from __future__ import annotations

import base64
import contextlib
import io
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
from matplotlib import colors
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.image import AxesImage
from matplotlib.ticker import MaxNLocator

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
#: colour of a PSF window's pixels that lie off the sensor, and of a non-significant quantity
OFF_SENSOR, NOT_SIGNIFICANT = "#b9c9de", "0.6"


def psf_image(ax: Axes, image: np.ndarray, **imshow: Any) -> AxesImage:
    """Draw a PSF ``image`` (fractions of a peak) in grey on a square-root scale from 0 to 1
    (caustics span a large dynamic range; its colour bar shows the intensities themselves),
    NaN (off the sensor) pale blue."""
    return ax.imshow(image, cmap=matplotlib.colormaps["gray"].with_extremes(bad=OFF_SENSOR),
                     norm=colors.PowerNorm(0.5, vmin=0.0, vmax=1.0), **imshow)


@dataclass(frozen=True)
class Fitted:
    """A fitted quantity with its 1σ uncertainty and significance, as far as known."""

    value: float
    sigma: float | None = None
    significant: bool | None = None

    @property
    def detected(self) -> bool:
        """Finite and significant (without a flag: at least 2σ from zero, σ determined)."""
        if not math.isfinite(self.value):
            return False
        if self.significant is not None:
            return bool(self.significant)
        if self.sigma is None:
            return True
        return math.isfinite(self.sigma) and abs(self.value) >= 2 * self.sigma

    def value_text(self, fmt: str = ".2f") -> str:
        """``1.94 ± 0.13``, ``0.71, σ undetermined`` or ``not determined``; never ``nan``."""
        if not math.isfinite(self.value):
            return "not determined"
        core = format(self.value, fmt)
        if self.sigma is None:
            return core
        if not math.isfinite(self.sigma):
            return f"{core}, σ undetermined"
        return f"{core} ± {format(self.sigma, fmt)}"

    def text(self, fmt: str = ".2f") -> str:
        """:meth:`value_text`, as ``not detected (…)`` when not significant."""
        core = self.value_text(fmt)
        return core if self.detected else f"not detected ({core})"

    @property
    def colour(self) -> str:
        return "k" if self.detected else NOT_SIGNIFICANT


def _field(source: Any, key: str) -> Any:
    if isinstance(source, dict):
        return source.get(key)
    return getattr(source, key, None)


def fitted(source: Any, name: str) -> Fitted:
    """``source.name`` (attribute or dict key) with its σ (``name_sigma``, ``name_std`` or
    ``sigma``) and flag (``name_significant`` or ``significant``; either may be a dict by
    name) where given."""
    value = _field(source, name)
    value = float("nan") if value is None else float(value)
    sigma = next((s for s in (_field(source, f"{name}_sigma"), _field(source, f"{name}_std"),
                              _field(source, "sigma")) if s is not None), None)
    if isinstance(sigma, dict):
        sigma = sigma.get(name)
    flag = next((f for f in (_field(source, f"{name}_significant"),
                             _field(source, "significant")) if f is not None), None)
    if isinstance(flag, dict):
        flag = flag.get(name)
    return Fitted(value, None if sigma is None else float(sigma),
                  None if flag is None else bool(flag))


@contextlib.contextmanager
def publication_style() -> Iterator[None]:
    """Temporarily apply the toolkit's figure style."""
    with matplotlib.rc_context(STYLE):
        yield


def new_figure(width_in: float, height_in: float) -> Figure:
    """A figure detached from pyplot's global state (no backend; thread-safe)."""
    fig = Figure(figsize=(width_in, height_in), layout="constrained")
    # 4.3 pt between rows (matplotlib's 3 pt lets a suptitle touch the panel titles)
    fig.get_layout_engine().set(h_pad=0.06)
    return fig


def save_figure(fig: Figure, stem: str | Path) -> list[Path]:
    """Write ``stem.png`` and ``stem.pdf`` atomically; returns the paths."""
    paths = []
    for fmt in ("png", "pdf"):
        path = Path(f"{stem}.{fmt}")
        with publication_style(), atomic_file(path) as tmp:
            fig.savefig(tmp, format=fmt)
        paths.append(path)
    return paths


def write_figures(folder: Path, figures: Iterable[tuple[str, str, Figure]], dpi: int
                  ) -> list[tuple[str, str, str]]:
    """Save each ``(stem, caption, figure)`` in a new ``folder`` (:func:`save_figure`); returns
    ``(stem, caption, base64 PNG at dpi)`` of each for the HTML page."""
    folder.mkdir()
    embedded = []
    for stem, caption, fig in figures:
        save_figure(fig, folder / stem)
        embedded.append((stem, caption, png_base64(fig, dpi)))
    return embedded


def no_ticks(ax: Axes) -> None:
    """Bare image axes: no ticks, no frame."""
    ax.set_xticks([])
    ax.set_yticks([])
    for spine in ax.spines.values():
        spine.set_visible(False)


def axis_labels(ax: Axes, xlabel: str, ylabel: str, ticks: tuple[int, int],
                integer: bool = False) -> None:
    """Label both axes, with at most ``ticks`` ``(x, y)`` major ticks."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.xaxis.set_major_locator(MaxNLocator(ticks[0], integer=integer))
    ax.yaxis.set_major_locator(MaxNLocator(ticks[1], integer=integer))


def png_base64(fig: Figure, dpi: int) -> str:
    """``fig`` as a base64 PNG at ``dpi`` in the publication style (for an HTML ``<img>``)."""
    buffer = io.BytesIO()
    with publication_style():
        fig.savefig(buffer, format="png", dpi=dpi)
    return base64.b64encode(buffer.getvalue()).decode()
