"""The report's and fit-eigen's figures read like paper figures (issue 43, item 6).

Every figure is rendered (as saved: publication style) for three grids, and its text and
panels are measured with matplotlib's own extents: a small bench lattice (the paper's
caustic), an irregular scan of the same camera, and a compact PSF (a few-pixel spot on a large
frame, irregular positions). A figure fails on any of:

- two text boxes that overlap (titles, tick labels, axis labels, colour-bar labels,
  annotations, legends);
- a font under 7 pt at the saved size (a single- or double-column figure);
- ``nan`` or ``inf`` in any text;
- a colour bar without a label naming its unit (``quantity (unit)``);
- a visible panel that shows nothing (no image, line, marker or bar with finite data);
- an image one pixel high or wide (a 1 × P "map" of an irregular scan);
- a PSF image in which the PSF is invisible (under 1 % of its pixels above 10 % of the peak:
  a few-pixel spot in a whole frame).
"""

from __future__ import annotations

import re
from collections.abc import Callable, Iterator
from pathlib import Path

import matplotlib
import numpy as np
import pytest
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.collections import Collection
from matplotlib.figure import Figure
from matplotlib.quiver import QuiverKey
from matplotlib.text import Text

from psfkit.bench import BenchConfig, simulate_grid, simulate_scan
from psfkit.characterize import characterize_grid
from psfkit.figures import (
    figure_eigen_diagnostics,
    figure_kernels,
    figure_maps,
    figure_montage,
    figure_shift_variance,
    figure_warp,
    figure_warp_summary,
    figure_weight_maps,
    publication_style,
)
from psfkit.grid_fit import EigenFitOptions, fit_eigen_grid
from psfkit.io import GridWriter, read_grid

MIN_POINTS = 7.0
NAN = re.compile(r"\b(nan|inf)\b", re.IGNORECASE)
UNIT = re.compile(r"\(.+\)")
FIT = EigenFitOptions(folds=3, cv_bases=("si",))


# ---- the checks -----------------------------------------------------------------------------

def _render(fig: Figure):  # type: ignore[no-untyped-def]
    FigureCanvasAgg(fig)
    fig.canvas.draw()
    return fig.canvas.get_renderer()


def _all_axes(fig: Figure) -> list[Axes]:
    return [ax for ax in fig.findobj(Axes) if ax.get_visible()]


def _drawn_texts(fig: Figure) -> list[tuple[Text, Axes | None]]:
    """The texts a reader sees, each with the panel it belongs to: visible, non-empty, in a
    visible axes; of an axis (its label, offset and tick labels) only where the axis is drawn,
    and of the ticks only those inside the view (an axis keeps spare tick objects outside
    it); quiver keys' labels."""
    hidden, drawn, keys = set(), set(), []
    for ax in fig.findobj(Axes):
        for axis in (ax.xaxis, ax.yaxis):
            shown = ax.axison and axis.get_visible()
            for tick in axis.majorTicks + axis.minorTicks:
                hidden |= {id(tick.label1), id(tick.label2)}
            if shown:
                drawn |= {id(t) for tick in axis._update_ticks()
                          for t in (tick.label1, tick.label2)}
                drawn |= {id(axis.label), id(axis.offsetText)}
            hidden |= {id(axis.label), id(axis.offsetText)}
        keys += [(child.text, ax) for child in ax.get_children()
                 if isinstance(child, QuiverKey) and child.get_visible()]
    out = []
    for text, owner in [*((t, t.axes) for t in fig.findobj(Text)), *keys]:
        if not text.get_visible() or not text.get_text().strip():
            continue
        if id(text) in hidden and id(text) not in drawn:
            continue
        if owner is not None and not owner.get_visible():
            continue
        out.append((text, owner))
    return out


def _colorbars(fig: Figure) -> Iterator[tuple[Axes, object]]:
    for ax in fig.findobj(Axes):
        bar = getattr(ax, "_colorbar", None)
        if bar is not None and ax.get_visible():
            yield ax, bar


def _has_data(ax: Axes) -> bool:
    for image in ax.images:
        if np.isfinite(np.ma.filled(image.get_array().astype(float), np.nan)).any():
            return True
    for line in ax.lines:
        x, y = (np.asarray(v, float) for v in line.get_data())
        if (np.isfinite(x) & np.isfinite(y)).any():
            return True
    for collection in ax.collections:
        if isinstance(collection, Collection) and len(collection.get_offsets()) and \
                np.isfinite(np.asarray(collection.get_offsets(), float)).any():
            return True
    return any(patch.get_fill() and not patch.get_hatch()
               and patch.get_width() * patch.get_height() != 0
               for patch in ax.patches if isinstance(patch, matplotlib.patches.Rectangle))


def figure_defects(fig: Figure) -> list[str]:
    """Every defect of the module docstring in ``fig``, one line each (measured in the
    publication style the figure is saved in: ticks made while measuring take its sizes)."""
    with publication_style():
        return _defects(fig)


def _defects(fig: Figure) -> list[str]:
    renderer = _render(fig)
    defects = []
    owned = _drawn_texts(fig)
    texts = [text for text, _ in owned]
    # boxes grown by 1 pt: text that touches other text reads as one string
    boxes = [t.get_window_extent(renderer).padded(renderer.points_to_pixels(0.5))
             for t in texts]
    for i in range(len(texts)):
        for j in range(i + 1, len(texts)):
            a, b = boxes[i], boxes[j]
            if min(a.x1, b.x1) > max(a.x0, b.x0) and min(a.y1, b.y1) > max(a.y0, b.y0):
                defects.append(f"text overlap: {texts[i].get_text()!r} / {texts[j].get_text()!r}")
    panels = [(ax, ax.get_window_extent(renderer)) for ax in _all_axes(fig)]
    for (text, owner), box in zip(owned, boxes, strict=True):
        if text.get_fontsize() < MIN_POINTS:
            defects.append(f"font {text.get_fontsize():.1f} pt: {text.get_text()!r}")
        if NAN.search(text.get_text()):
            defects.append(f"nan in text: {text.get_text()!r}")
        for ax, frame in panels:
            if ax is not owner and min(box.x1, frame.x1) - max(box.x0, frame.x0) > 1 \
                    and min(box.y1, frame.y1) - max(box.y0, frame.y0) > 1:
                defects.append(f"text over another panel: {text.get_text()!r} over "
                               f"{ax.get_title() or ax.get_label()!r}")
    bar_axes = set()
    for ax, bar in _colorbars(fig):
        bar_axes.add(ax)
        label = bar.long_axis.get_label_text()  # type: ignore[attr-defined]
        if not UNIT.search(label):
            defects.append(f"colour bar without 'quantity (unit)' label: {label!r}")
    for ax in _all_axes(fig):
        if ax in bar_axes:
            continue
        if not _has_data(ax):
            defects.append(f"empty panel: {ax.get_title()!r}")
        for image in ax.images:
            shape = image.get_array().shape[:2]
            if min(shape) == 1 and max(shape) > 1:
                defects.append(f"{shape[0]}×{shape[1]} strip image: {ax.get_title()!r}")
            if image.get_cmap().name.startswith("gray") and image.get_array().ndim == 2:
                data = np.ma.filled(image.get_array().astype(float), np.nan)
                data = data[np.isfinite(data)]         # NaN: off the sensor
                lit = float(np.mean(data > 0.1 * data.max())) if data.size else 0.0
                if data.size and data.max() > 0 and lit < 0.01:
                    defects.append(f"PSF invisible ({100 * lit:.2f}% of the pixels lit): "
                                   f"{ax.get_title()!r}")
    return defects


# ---- the grids --------------------------------------------------------------------------------

def compact_scan(out: Path, positions: int = 30, frame: tuple[int, int] = (240, 320),
                 sigma_px: float = 1.2, seed: int = 43) -> Path:
    """An irregular scan of a Gaussian spot of ``sigma_px`` on a large dark frame (a lens
    camera's PSF, the same at every field position): the on-axis position and random ones."""
    rng = np.random.default_rng(seed)
    h, w = frame
    focal_px = 0.4 * min(h, w) / np.tan(np.deg2rad(10.0))      # 10° → 40 % of the frame
    angles = np.vstack([[0.0, 0.0], rng.uniform(-10, 10, (positions - 1, 2))])
    rows, cols = np.mgrid[0:h, 0:w]
    with GridWriter(out, grid_shape=None, suffix=".npy") as writer:
        for index, (tx, ty) in enumerate(angles):
            # a source at +x moves its PSF towards −u (docs/grid-format.md)
            u = (w - 1) / 2 - focal_px * np.tan(np.deg2rad(tx))
            v = (h - 1) / 2 - focal_px * np.tan(np.deg2rad(ty))
            spot = 1000.0 * np.exp(-((cols - u) ** 2 + (rows - v) ** 2) / (2 * sigma_px**2))
            image = spot + 20.0 + rng.normal(0.0, 2.0, (h, w))
            writer.add_scan(index, image[None].astype(np.float32), field_deg=(tx, ty))
        writer.add_dark((20.0 + rng.normal(0.0, 2.0, (h, w)))[None].astype(np.float32))
    return out


@pytest.fixture(scope="module")
def grids(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    root = tmp_path_factory.mktemp("figures")
    config = BenchConfig(downsample=8)
    rng = np.random.default_rng(43)
    fov_h, fov_w = config.fov_monitor_px
    scattered = np.column_stack([rng.uniform(-0.5, 0.5, 29) * fov_w,
                                 rng.uniform(-0.5, 0.5, 29) * fov_h])
    return {
        "lattice": simulate_grid(root / "lattice", config, grid_shape=(5, 5), progress=False),
        "scan": simulate_scan(root / "scan", np.vstack([[0.0, 0.0], scattered]), config,
                              progress=False),
        "compact": compact_scan(root / "compact"),
    }


@pytest.fixture(scope="module")
def characterized(grids):
    return {name: characterize_grid(read_grid(path)) for name, path in grids.items()}


@pytest.fixture(scope="module")
def fitted(grids):
    return {name: fit_eigen_grid(read_grid(path), FIT) for name, path in grids.items()}


REPORT: dict[str, Callable[..., Figure]] = {
    "fig2_shift_variance": figure_shift_variance, "maps": figure_maps,
    "warp_summary": figure_warp_summary, "warp_fields": figure_warp, "montage": figure_montage}
CASES = ("lattice", "scan", "compact")


# ---- the tests ------------------------------------------------------------------------------

@pytest.mark.parametrize("case", CASES)
@pytest.mark.parametrize("name", list(REPORT))
def test_report_figures_are_legible(characterized, case, name):
    fig = REPORT[name](characterized[case])
    assert figure_defects(fig) == []


@pytest.mark.parametrize("case", CASES)
def test_fit_eigen_figures_are_legible(fitted, case):
    result = fitted[case]
    model = result.kernel_model()
    names = list(model.kernel_names)
    figures = {"fig7": figure_kernels(model.kernels, names, "measured eigen-kernels"),
               "fig7_zoom": figure_kernels(model.kernels, names, "zoom", zoom=0.3),
               "fig3": figure_weight_maps(model.basis, model.sensor_shape),
               "diagnostics": figure_eigen_diagnostics(result)}
    defects = {name: figure_defects(fig) for name, fig in figures.items()}
    assert defects == {name: [] for name in figures}
