"""Writing a grid characterization: JSON and CSV numbers, figures, one self-contained HTML page.

``write_report`` creates its output folder atomically (nothing appears until everything is
written)::

    OUT/
      report.html        figures embedded, readable offline
      results.json       every number, with the conventions and options used
      positions.csv      one row per grid position
      figures/*.png|pdf  publication-quality figures
"""

from __future__ import annotations

import csv
import html
import math
import os
from pathlib import Path
from typing import Any

from psfkit import __version__
from psfkit.calibration.alignment import RELIABLE_OVERLAP, ExcludedPosition
from psfkit.characterization.results import GridCharacterization, PositionResult
from psfkit.errors import InvalidInputError
from psfkit.io.atomic import atomic_directory, atomic_file
from psfkit.io.json_documents import dumps_finite
from psfkit.io.jsonable import jsonable
from psfkit.report.html import (
    estimate_html,
    figures_html,
    format_value,
    grid_table,
    html_page,
    html_table,
)

CSV_COLUMNS = (
    "row", "col", "file", "field_x_deg", "field_y_deg", "monitor_x_px", "monitor_y_px",
    "shift_du_px", "shift_dv_px", "shift_residual_du_px", "shift_residual_dv_px", "quality",
    "overlap", "gain", "mae", "mae_gain_compensated", "n_saturated", "warp_residual_rms_px",
    "warp_rms_tangential_px", "warp_rms_sagittal_px", "warp_anisotropy", "affine_scale_u",
    "affine_scale_v", "affine_shear", "affine_rotation_deg", "affine_scale_tangential",
    "affine_scale_sagittal", "status", "reason")


_POSITION_COLUMNS = ("quality", "overlap", "gain", "mae", "mae_gain_compensated", "n_saturated")
_WARP_COLUMNS = {"warp_residual_rms_px": "residual_rms", "warp_rms_tangential_px": "rms_tangential",
                 "warp_rms_sagittal_px": "rms_sagittal", "warp_anisotropy": "anisotropy"}
_AFFINE_KEYS = ("scale_u", "scale_v", "shear", "rotation_deg", "scale_tangential",
                "scale_sagittal")


def _where(p: PositionResult | ExcludedPosition) -> dict[str, Any]:
    """The CSV columns that place a position: grid index, file, field angles, monitor px."""
    fx, fy = p.field_deg if p.field_deg is not None else (None, None)
    mx, my = p.monitor_px if p.monitor_px is not None else (None, None)
    return {"row": p.row, "col": p.col, "file": p.file, "field_x_deg": fx, "field_y_deg": fy,
            "monitor_x_px": mx, "monitor_y_px": my}


def csv_rows(result: GridCharacterization) -> list[dict[str, Any]]:
    """One dictionary of :data:`CSV_COLUMNS` per captured position (excluded ones with their
    ``reason`` and no numbers; row and col empty for an irregular scan)."""
    residuals = result.shift_fit.residuals if result.shift_fit is not None else None
    irregular = result.layout == "irregular"
    rows = [jsonable({**dict.fromkeys(CSV_COLUMNS), **_where(e), "status": "excluded",
                      "reason": e.reason}) for e in result.excluded]
    for p in result.positions:
        warp = p.warp or {}
        affine = warp.get("affine", {})
        res = residuals[p.row, p.col] if residuals is not None else (None, None)
        rows.append(jsonable({
            **_where(p), "shift_du_px": p.shift[0], "shift_dv_px": p.shift[1],
            "shift_residual_du_px": res[0], "shift_residual_dv_px": res[1],
            **{k: getattr(p, k) for k in _POSITION_COLUMNS},
            **{column: warp.get(k) for column, k in _WARP_COLUMNS.items()},
            **{f"affine_{k}": affine.get(k) for k in _AFFINE_KEYS},
            "status": "ok", "reason": None}))
    rows.sort(key=lambda r: (r["row"], r["col"]))
    if irregular:
        for r in rows:
            r["row"] = r["col"] = None
    return rows


def _write_csv(path: Path, result: GridCharacterization) -> None:
    with open(path, "w", newline="", encoding="utf-8") as fh:
        writer = csv.DictWriter(fh, fieldnames=CSV_COLUMNS)
        writer.writeheader()
        for row in csv_rows(result):
            writer.writerow({k: "" if v is None else v for k, v in row.items()})


def results_document(result: GridCharacterization) -> dict[str, Any]:
    """The JSON document: results plus software version and warnings."""
    doc = result.to_dict()
    doc["software"] = {"psfkit": __version__}
    doc["warnings"] = warnings_for(result)
    return jsonable(doc)


def check_numbers_path(path: str | os.PathLike) -> Path:
    """Validate an output path for :func:`write_numbers` before any work is done."""
    path = Path(path)
    if path.suffix not in (".json", ".csv"):
        raise InvalidInputError(f"{path}: output must end in .json or .csv")
    if path.is_dir():
        raise InvalidInputError(f"{path}: is a directory, expected a file name")
    return path


def write_numbers(result: GridCharacterization, path: str | os.PathLike) -> Path:
    """Write the numbers alone, as JSON (``.json``) or per-position CSV (``.csv``)."""
    path = check_numbers_path(path)
    with atomic_file(path) as tmp:
        if path.suffix == ".json":
            tmp.write_text(dumps_finite(results_document(result), str(path), indent=1) + "\n",
                           encoding="utf-8")
        else:
            _write_csv(tmp, result)
    return path


def warnings_for(result: GridCharacterization) -> list[str]:
    """Plain-language warnings a lab should read before trusting the numbers."""
    out = []
    if result.missing:
        n, m = result.grid_shape
        out.append(f"incomplete lattice: {len(result.missing)} of the {n}×{m} positions were "
                   "not captured (hatched grey on the maps); the fits use the "
                   f"{len(result.positions)} measured positions.")
    if result.excluded:
        listed = ", ".join(f"{e.file} ({e.reason})" for e in result.excluded[:8])
        more = f" and {len(result.excluded) - 8} more" if len(result.excluded) > 8 else ""
        out.append(f"{len(result.excluded)} position(s) excluded after a failed quality check "
                   f"(red × on the maps): {listed}{more}.")
    saturated = [p for p in result.positions if p.n_saturated]
    if saturated:
        worst = max(saturated, key=lambda p: p.saturated_fraction)
        out.append(f"{len(saturated)} PSF(s) have saturated pixels (worst: {worst.file}, "
                   f"{worst.n_saturated} px, {100 * worst.saturated_fraction:.2f}% of the bright "
                   "PSF); they are excluded from the comparisons. Lower the exposure if you can.")
    partial = [p for p in result.positions if p.support_overlap < RELIABLE_OVERLAP]
    if partial:
        out.append(f"{len(partial)} position(s) have less than {100 * RELIABLE_OVERLAP:.0f}% "
                   "of the centre PSF's light inside their registered overlap: only part of "
                   "their PSF is seen, and as the PSF also deforms off axis, their shift is "
                   "uncertain by up to a few tenths of a pixel and their warp statistics are "
                   "less reliable.")
    weak = [p for p in result.positions if p.quality < 0.5]
    if weak:
        out.append(f"{len(weak)} position(s) register poorly (correlation < 0.5): "
                   + ", ".join(p.file for p in weak[:5]))
    return out


FIGURES = (
    ("fig2_shift_variance", "Fig. 2: breakdown of shift invariance", "figure_shift_variance"),
    ("maps", "Maps: MAE, gain, registration quality, overlap, shift-map residual",
     "figure_maps"),
    ("warp_summary", "Warp: residual displacement and tangential/sagittal anisotropy",
     "figure_warp_summary"),
    ("warp_fields", "Warp fields at the outermost reliable positions", "figure_warp"),
    ("montage", "The PSF grid", "figure_montage"),
)


def write_report(result: GridCharacterization, out_dir: str | os.PathLike,
                 overwrite: bool = False) -> Path:
    """Write figures, JSON, CSV and the HTML report into ``out_dir`` (atomically)."""
    # matplotlib loads only when a report is drawn (not for `psfkit characterize --help`)
    from psfkit.report import figures as fig_module
    from psfkit.report.figures.style import write_figures

    out_dir = Path(out_dir)
    with atomic_directory(out_dir, overwrite=overwrite) as tmp:
        figures = ((stem, caption, getattr(fig_module, fn_name)(result))
                   for stem, caption, fn_name in FIGURES
                   if result.flows or fn_name not in ("figure_warp", "figure_warp_summary"))
        embedded = write_figures(tmp / "figures", figures, dpi=150)
        doc = results_document(result)
        (tmp / "results.json").write_text(
            dumps_finite(doc, str(Path(out_dir) / "results.json"), indent=1) + "\n",
            encoding="utf-8")
        _write_csv(tmp / "positions.csv", result)
        (tmp / "report.html").write_text(_html(result, doc, embedded), encoding="utf-8")
    return out_dir


def _html(result: GridCharacterization, doc: dict[str, Any],
          figures: list[tuple[str, str, str]]) -> str:
    c, h, w = result.image_shape
    shift = doc.get("shift_map") or {}
    gain = doc.get("gain_fit") or {}
    growth = doc.get("warp_growth") or {}
    anis = doc.get("warp_anisotropy") or {}
    if result.layout == "irregular":
        layout = f"irregular scan of {len(result.captured)} positions"
    else:
        layout = f"{result.grid_shape[0]} × {result.grid_shape[1]} ({result.layout})"
    summary = html_table([
        ("grid", result.grid_root),
        ("positions", layout),
        ("measured / excluded / not captured",
         f"{len(result.positions)} / {len(result.excluded)} / {len(result.missing)}"),
        ("images", f"{h} × {w} × {c} ({'/'.join(result.channels)})"),
        ("centre (row, col)", str(result.center)),
        ("normalization", doc["conventions"]["normalization"]),
        ("field coordinates", result.field_units),
    ])
    est = shift.get("estimates") or {}
    registration = html_table([
        ("magnification (px per field unit)", estimate_html(est.get("magnification"), ".6g")),
        ("magnification u / v", f"{format_value(shift.get('magnification_u'))} / "
                                f"{format_value(shift.get('magnification_v'))}"),
        ("rotation (deg; 180 = inverted image)", estimate_html(est.get("rotation_deg"))),
        ("shear", shift.get("shear")),
        ("offset (du, dv) px", str([format_value(v) for v in shift.get("offset_px", [])])),
        (f"distortion beyond the affine map (px rms; polynomial of degree "
         f"{shift.get('distortion_degree', '–')})",
         estimate_html(est.get("distortion_rms_px"), ".3g")),
        ("rms residual of the affine map (px)", shift.get("rms_residual_px")),
    ])
    gains = html_table([
        ("cosⁿ law exponent n (g = A cosⁿθ)",
         estimate_html((gain.get("estimates") or {}).get("cos_exponent"), ".3g")),
        ("cosⁿ law scale A", gain.get("cos_scale")),
        ("cosⁿ fit rms residual", gain.get("cos_rms_residual")),
        ("quadratic fit rms residual", gain.get("poly_rms_residual")),
    ])
    growth_est = growth.get("estimates") or {}
    warp = html_table([
        ("residual at 10° above the floor (px)",
         estimate_html(growth_est.get("scale_10deg"), ".3g")),
        ("residual growth exponent (θ^p)", estimate_html(growth_est.get("exponent"), ".3g")),
        ("flow noise floor (px)", growth.get("floor")),
        ("tangential/sagittal, measured (geometric mean; 1 = none)",
         estimate_html((anis.get("estimates") or {}).get("tangential_sagittal"), ".3g")),
        ("tangential/sagittal, geometric optics", anis.get("median_geometric")),
        ("positions in the comparison", anis.get("positions")),
    ])
    warnings = "".join(f"<li>{html.escape(m)}</li>" for m in doc["warnings"]) or \
        "<li>none</li>"
    figs = figures_html(figures)
    head = ("file", "row", "col", "status", "shift_du_px", "shift_dv_px", "quality", "overlap",
            "gain", "mae", "warp_residual_rms_px", "warp_anisotropy")
    positions = grid_table(head, ([r[k] for k in head] for r in csv_rows(result)))
    excluded = _excluded_html(result)
    return html_page("PSF grid report", f"""<h1>PSF grid report</h1>
{verdict_html(doc.get("verdict"))}
<p>psfkit {html.escape(__version__)}. Numbers: <a href="results.json">results.json</a>,
<a href="positions.csv">positions.csv</a>. Shifts are the displacement (du, dv) of each PSF
relative to the centre PSF, in sensor pixels (u = column, v = row). Every fitted quantity is
given with its 1σ uncertainty; one that is not significant ({_rule_text()}) is greyed as
"not detected" (its number in small print and as a tooltip).</p>
{summary}
<div class="warn"><b>Warnings</b><ul>{warnings}</ul></div>
{excluded}
<h2>Registration and shift map</h2>{registration}
<h2>Gain (relative illumination)</h2>
<p>A gain is the energy of a PSF relative to the centre capture over the region both cover: it
includes any difference in the brightness of the sources (a monitor's uniformity, stars of
different magnitudes), not only the camera's vignetting.</p>{gains}
<h2>Warp: distortion and oblique-incidence astigmatism</h2>
<p>The affine part of each warp is what magnification and distortion cause; the residual is
what oblique-incidence astigmatism causes. Its tangential/sagittal split comes from the
angular spectrum of the intensity change (transport of intensity), because per-pixel flow
components mix the two directions on caustic lines.</p>{warp}
{figs}
<h2>Positions</h2>{positions}
""")


def _excluded_html(result: GridCharacterization) -> str:
    """The section of excluded positions and never-captured cells (empty when none)."""
    from psfkit.calibration.alignment import REJECTION_REASONS

    if not result.excluded and not result.missing:
        return ""
    rows = "".join(
        f"<tr><td>{html.escape(e.file)}</td><td>{format_value(e.row)}</td>"
        f"<td>{format_value(e.col)}</td><td>{html.escape(e.reason)}</td>"
        f"<td>{html.escape(REJECTION_REASONS.get(e.reason, ''))}</td>"
        f"<td>{html.escape(e.detail)}</td></tr>" for e in result.excluded)
    table = ("<table class='excluded'><tr><th>file</th><th>row</th><th>col</th>"
             f"<th>reason</th><th>check</th><th>detail</th></tr>{rows}</table>"
             if result.excluded else "<p>No position was excluded.</p>")
    missing = ""
    if result.missing:
        cells = ", ".join(f"({r}, {c})" for r, c in result.missing)
        missing = (f"<p>Not captured ({len(result.missing)} of the "
                   f"{result.grid_shape[0]} × {result.grid_shape[1]} lattice): {cells}.</p>")
    return (f"<h2 id='excluded'>Excluded and missing positions</h2>{table}{missing}"
            "<p>Maps: hatched grey = not captured, hatched red with × = excluded.</p>")


def _rule_text() -> str:
    from psfkit.numerics.significance import Z_SIGNIFICANT, alpha

    return f"|value − null| ≤ {Z_SIGNIFICANT:g}σ, or its test's p ≥ {alpha():.2g}"


def verdict_html(verdict: dict[str, Any] | None) -> str:
    """The report's opening: the verdict, its evidence (held-out errors ±1σ, noise floor, test)
    and the field effects."""
    if not verdict:
        return ""
    evidence = verdict.get("evidence", {})
    rows = []
    floor = evidence.get("noise_floor")
    if floor:
        rows.append((f"noise floor: held-out error of {floor['model']}",
                     _error_cell(floor)))
    for name, value in (evidence.get("held_out") or {}).items():
        rows.append((f"held-out error, {name}", _error_cell(value)))
    for name, value in (evidence.get("field_models") or {}).items():
        rows.append((f"held-out error, {name} (field test)", _error_cell(value)))
    test = evidence.get("field_test")
    if test:
        rows.append((f"reduction of the relative squared error per position, {test['model']} "
                     f"vs {test['against']}",
                     estimate_html(test["mean_reduction_of_relative_squared_error"], ".3g")))
    rows.append(("held-out positions", evidence.get("positions")))
    effects = html_table([(f"{name}: {value['meaning']}", estimate_html(
        value.get("estimate"), ".3g") if value.get("measured") else "not measured")
        for name, value in (verdict.get("effects") or {}).items()])
    return (f"<div class='verdict'><b>Verdict.</b> {html.escape(verdict['summary'])}</div>"
            f"<h2 id='verdict'>Verdict: evidence</h2>"
            f"<p>{html.escape(evidence.get('rule', ''))}.</p>{html_table(rows)}"
            f"<h3>Field effects</h3>{effects}")


def _error_cell(summary: dict[str, Any]) -> str:
    sigma = summary.get("sigma")
    if sigma is None or not math.isfinite(sigma):
        return format_value(summary.get("error"))
    return f"{summary['error']:.4f} ± {sigma:.4f}"
