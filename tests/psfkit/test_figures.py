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

from psfkit.characterization.characterize import characterize_grid
from psfkit.fitting.grid.fit import fit_eigen_grid
from psfkit.fitting.grid.options import EigenFitOptions
from psfkit.io import GridWriter, read_grid
from psfkit.report.figures import (
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
from psfkit.report.figures.style import NOT_SIGNIFICANT, Fitted
from psfkit.simulate import BenchConfig, simulate_grid, simulate_scan

pytestmark = pytest.mark.slow      # three small grids characterized and fitted (~30 s CPU)

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
    hidden, drawn, keys, owners = set(), set(), [], {}
    for ax in fig.findobj(Axes):
        for axis in (ax.xaxis, ax.yaxis):
            shown = ax.axison and axis.get_visible()
            for tick in axis.majorTicks + axis.minorTicks:
                hidden |= {id(tick.label1), id(tick.label2)}
                owners |= {id(tick.label1): ax, id(tick.label2): ax}
            if shown:
                drawn |= {id(t) for tick in axis._update_ticks()
                          for t in (tick.label1, tick.label2)}
                drawn |= {id(axis.label), id(axis.offsetText)}
            hidden |= {id(axis.label), id(axis.offsetText)}
        keys += [(child.text, ax) for child in ax.get_children()
                 if isinstance(child, QuiverKey) and child.get_visible()]
    out = []
    for text, owner in [*((t, owners.get(id(t), t.axes)) for t in fig.findobj(Text)), *keys]:
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

def compact_scan(out: Path, positions: int = 20, frame: tuple[int, int] = (240, 320),
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
    scattered = np.column_stack([rng.uniform(-0.5, 0.5, 19) * fov_w,
                                 rng.uniform(-0.5, 0.5, 19) * fov_h])
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


# ---- what each figure must show ----------------------------------------------------------

def _bar_of(fig: Figure, image) -> object:  # type: ignore[no-untyped-def]
    return next(bar for _, bar in _colorbars(fig) if bar.mappable is image)  # type: ignore[attr-defined]


def test_fig3_colour_bars_span_their_own_maps(fitted):
    """The paper basis's correction weights reach 0.5, not 1: each bar spans its map."""
    model = fitted["lattice"].kernel_model()
    fig = figure_weight_maps(model.basis, model.sensor_shape)
    from psfkit.forward.weights import get_basis

    maps = get_basis(model.basis).maps(model.sensor_shape)
    images = [ax.images[0] for ax in fig.axes if ax.images]
    assert len(images) == len(maps) == 3
    for image, values in zip(images, maps, strict=True):
        assert image.norm.vmin == pytest.approx(values.min())
        assert image.norm.vmax == pytest.approx(values.max())
    assert max(image.norm.vmax for image in images[1:]) < 0.51


@pytest.mark.parametrize("case", ["lattice", "scan"])
def test_diagnostics_residuals_share_one_labelled_scale(fitted, case):
    fig = figure_eigen_diagnostics(fitted[case])
    panels = [ax for ax in fig.axes if "residual per position" in ax.get_title()]
    mappables = [(ax.images or ax.collections)[0] for ax in panels]
    assert len(mappables) == 2
    assert mappables[0].norm.vmin == mappables[1].norm.vmin
    assert mappables[0].norm.vmax == mappables[1].norm.vmax
    bars = [bar for _, bar in _colorbars(fig)]
    assert len(bars) == 1 and bars[0].mappable.norm is mappables[1].norm
    values = np.concatenate([fitted[case].residuals[c].ravel() for c in ("sensor", "source")])
    assert mappables[0].norm.vmax == pytest.approx(np.nanmax(values))
    if case == "scan":      # the scan's positions as points, not a 1 × P strip
        assert all(not ax.images for ax in panels)
        assert len(mappables[0].get_offsets()) == fitted[case].n_positions


def test_fig7_reads_the_correction_against_the_kernel(fitted):
    """One row (the paper's layout, no empty panel), a colour bar for the kernels and one for
    their differences, both in fractions of the same peak."""
    model = fitted["lattice"].kernel_model()
    fig = figure_kernels(model.kernels, list(model.kernel_names))
    panels = [ax for ax in fig.axes if ax.images and not hasattr(ax, "_colorbar")]
    assert len(panels) == 5
    labels = sorted(bar.long_axis.get_label_text() for _, bar in _colorbars(fig))
    assert labels == ["K_k − K_base (fraction of peak)", "kernel (fraction of peak, √ scale)"]
    kernels = np.stack([ax.images[0].get_array() for ax in panels[:3]])
    assert float(kernels.max()) == pytest.approx(1.0)
    differences = np.stack([ax.images[0].get_array() for ax in panels[3:]])
    np.testing.assert_allclose(differences, kernels[1:] - kernels[0], atol=1e-6)


def test_montage_names_every_column_and_row_or_position(characterized):
    lattice = figure_montage(characterized["lattice"])
    axes = np.array([ax for ax in lattice.axes if ax.images and not hasattr(ax, "_colorbar")])
    grid = axes.reshape(5, 5)
    assert [ax.get_title() for ax in grid[0]] == [
        f"θx {x:+.1f}°" for x in sorted({p.field_deg[0] for p in
                                          characterized["lattice"].positions})]
    assert all(ax.get_ylabel().startswith("θy ") for ax in grid[:, 0])
    scan = figure_montage(characterized["scan"])
    titles = [ax.get_title() for ax in scan.axes if ax.images and not hasattr(ax, "_colorbar")]
    assert len(titles) == 20 and all(t.endswith("°") for t in titles)


def test_montage_windows_follow_each_compact_psf(characterized):
    """Every thumbnail of the compact scan is centred on its spot (the window is the centre
    PSF's support moved by the registered shift) and the spot fills a visible part of it."""
    result = characterized["compact"]
    thumbs = result.thumbnails[0]
    h, w = thumbs.shape[1:]
    assert max(h, w) < 40             # the spot's support, not the 240 × 320 frame
    for thumb in thumbs:
        r, c = np.unravel_index(np.nanargmax(thumb), thumb.shape)
        assert abs(r - (h - 1) / 2) <= 2 and abs(c - (w - 1) / 2) <= 2


def test_a_large_scan_montage_shows_a_spread_subset(characterized, monkeypatch):
    import psfkit.report.figures.montage as montage
    from psfkit.report.figures.grid_layout import scatter_coordinates

    monkeypatch.setattr(montage, "MONTAGE_MAX", 8)
    result = characterized["compact"]
    cells, rows, cols = montage._montage_cells(result)
    assert len(cells) == 8 and (0, result.center[1]) in cells and rows * cols >= 8
    fig = figure_montage(result)
    assert "8 of 20 positions" in fig.get_suptitle()
    # spread: the picks reach farther out than the 8 positions nearest the centre
    coords, _ = scatter_coordinates(result)
    radius = np.hypot(*(coords - coords[result.center[1]]).T)
    assert max(radius[c] for _, c in cells) == pytest.approx(radius.max())
    assert figure_defects(fig) == []


def test_fitted_quantities_show_their_uncertainty_and_grey_when_not_significant(
        characterized):
    """With a significance flag (as the fit results carry them, issue 43 item 1) the growth
    fit is drawn with its ±1σ, or dashed grey and "no growth detected"."""
    import copy
    from types import SimpleNamespace

    result = copy.copy(characterized["lattice"])
    for flag in (True, False):
        result.warp_growth = SimpleNamespace(floor=0.03, scale_10deg=0.2, exponent=1.94,
                                             exponent_std=0.13, significant=flag)
        line = figure_warp_summary(result).axes[0].lines[-1]
        if flag:
            assert line.get_label().endswith("n = 1.94 ± 0.13") and line.get_linestyle() == "-"
        else:
            assert line.get_label() == "no growth detected (fit n = 1.94 ± 0.13)"
            assert matplotlib.colors.same_color(line.get_color(), NOT_SIGNIFICANT)
            assert line.get_linestyle() == "--"
    # without a flag: not detected where the exponent is within 2σ of nothing
    result.warp_growth = SimpleNamespace(floor=0.03, scale_10deg=0.2, exponent=29.8,
                                         exponent_std=4.6e5)
    assert figure_warp_summary(result).axes[0].lines[-1].get_label().startswith(
        "no growth detected")


def test_kernel_differences_that_are_not_significant_are_greyed(fitted):
    model = fitted["lattice"].kernel_model()
    sizes = [Fitted(0.031, 0.004, True), Fitted(0.002, 0.004, False)]
    fig = figure_kernels(model.kernels, list(model.kernel_names), sizes=sizes)
    titles = {ax.get_title(): ax for ax in fig.axes if "−" in ax.get_title()}
    detected, undetected = titles["K_v − K_base\n0.031 ± 0.004"], \
        titles["K_h − K_base\nnot detected (0.002 ± 0.004)"]
    assert matplotlib.colors.same_color(undetected.title.get_color(), NOT_SIGNIFICANT)
    assert undetected.images[0].get_alpha() < 1 and detected.images[0].get_alpha() is None
    assert figure_defects(fig) == []


@pytest.mark.parametrize(("value", "sigma", "flag", "text"), [
    (1.94, 0.13, None, "1.94 ± 0.13"), (1.94, 0.13, False, "not detected (1.94 ± 0.13)"),
    (0.1, 0.13, None, "not detected (0.10 ± 0.13)"), (0.1, 0.13, True, "0.10 ± 0.13"),
    (0.71, float("inf"), None, "not detected (0.71, σ undetermined)"),
    (float("nan"), None, None, "not detected (not determined)"), (3.0, None, None, "3.00")])
def test_fitted_text_never_prints_nan(value, sigma, flag, text):
    assert Fitted(value, sigma, flag).text() == text


def test_comparison_figures_are_legible(fitted):
    """``research.compare``'s Fig. 7 layout and displacement maps (a model against itself),
    by the same legibility checks as the product's figures."""
    from research.compare import compare_kernels
    from research.compare.figures import figure_displacements, figure_learned_vs_measured

    model = fitted["lattice"].kernel_model()
    comparison = compare_kernels(model, model)
    for fig in (figure_learned_vs_measured(comparison), figure_displacements(comparison)):
        assert figure_defects(fig) == []


@pytest.mark.parametrize("basis", ["si", "paper+odd+cross", "poly:2"])
def test_richer_bases_wrap_without_empty_panels(basis):
    """Fig. 7 of more than four kernels wraps into a block of kernels above a block of
    differences; Fig. 3 of any basis; the single-kernel (SI) model has no difference row."""
    from psfkit.forward.weights import get_basis

    names = list(get_basis(basis).kernel_names)
    rows, cols = np.mgrid[0:48, 0:64]
    kernels = np.stack([np.exp(-((rows - 24 - 0.3 * k) ** 2 + (cols - 30 - 0.2 * k) ** 2) / 18.0)
                        for k in range(len(names))])[:, None]
    for fig in (figure_kernels(kernels, names, "kernels"), figure_weight_maps(basis, (60, 80))):
        assert figure_defects(fig) == []
    panels = [ax for ax in figure_kernels(kernels, names).axes
              if ax.get_visible() and ax.images and not hasattr(ax, "_colorbar")]
    assert len(panels) == 2 * len(names) - 1


def test_a_grid_without_field_positions_is_drawn_against_grid_steps(characterized):
    """No field angles or monitor positions in the manifest: the warp summary is one panel
    against the distance in grid steps (no empty anisotropy panel), the montage names rows
    and columns by index."""
    import copy
    from dataclasses import replace

    result = copy.copy(characterized["lattice"])
    result.positions = [replace(p, field_deg=None, monitor_px=None) for p in result.positions]
    result.field_units, result.warp_growth = "grid steps", None
    summary = figure_warp_summary(result)
    assert len(summary.axes) == 1 and "grid steps" in summary.axes[0].get_xlabel()
    montage = figure_montage(result)
    assert "col 0" in [ax.get_title() for ax in montage.axes]
    for fig in (summary, montage, figure_shift_variance(result), figure_warp(result)):
        assert figure_defects(fig) == []
