"""Tables 1 and 2 as Markdown and JSON (written atomically)."""

from __future__ import annotations

import math
import os
from pathlib import Path
from typing import Any

from ekdun.errors import ConfigurationError, InvalidInputError
from psfkit.io.atomic import atomic_file
from psfkit.validation import dumps_finite, read_json_file

MODEL_LABELS = {"le-admm-u": "Le-ADMM-U", "updn": "UPDN", "ekdun": "EK-DUN"}
SCHEDULE_LABELS = {"base": "base only", "last-2": "last-2", "last-k": "last-2", "all": "all"}


def label_for(model: str, schedule: str | None) -> str:
    """Row label of a run, e.g. ``EK-DUN (last-2)``."""
    name = MODEL_LABELS.get(model, model)
    return f"{name} ({schedule})" if model == "ekdun" and schedule else name


def _fmt(value: Any, digits: int) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if isinstance(value, int):
        return f"{value:,}"
    return f"{value:.{digits}f}"


def markdown_table(rows: list[dict[str, Any]], columns: list[tuple[str, str, int]]) -> str:
    """``columns``: ``(key, header, digits)``."""
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    sep = "|" + "|".join("---" for _ in columns) + "|"
    body = ["| " + " | ".join(str(r.get(k, "")) if d < 0 else _fmt(r.get(k), d)
                              for k, _, d in columns) + " |" for r in rows]
    return "\n".join([head, sep, *body])


TABLE1_COLUMNS = [("label", "Method", -1), ("psnr", "PSNR (dB)", 2), ("ssim", "SSIM", 4),
                  ("lpips", "LPIPS", 4), ("parameters", "Parameters", 0),
                  ("runtime_ms_median", "Runtime / image (ms, median)", 1),
                  ("peak_memory_mib", "Peak memory (MiB)", 1)]
TABLE2_COLUMNS = [("label", "Eigen-kernel model in", -1), ("psnr", "PSNR (dB)", 2),
                  ("ssim", "SSIM", 4), ("lpips", "LPIPS", 4)]


def split_tables(results: list[dict[str, Any]]) -> tuple[list[dict], list[dict]]:
    """Table 1: Le-ADMM-U, UPDN, EK-DUN (last-2); Table 2: EK-DUN schedules."""
    table1, table2 = [], []
    for r in results:
        if r.get("model") in ("le-admm-u", "updn"):
            table1.append(r)
        elif r.get("model") == "ekdun":
            sched = SCHEDULE_LABELS.get(str(r.get("schedule")), str(r.get("schedule")))
            table2.append({**r, "label": sched})
            if sched == "last-2":
                table1.append(r)
    order = {"base only": 0, "last-2": 1, "all": 2}
    table2.sort(key=lambda r: order.get(r["label"], 9))
    return table1, table2


TABLES: dict[str, tuple[str, list[tuple[str, str, int]]]] = {
    "table1": ("Table 1: comparison with Le-ADMM-U and UPDN", TABLE1_COLUMNS),
    "table2": ("Table 2: where EK-DUN uses the eigen-kernel model", TABLE2_COLUMNS),
}
EXPECTED = {"table1": ("EK-DUN (last-2)", "Le-ADMM-U", "UPDN"),
            "table2": ("base only", "last-2", "all")}


def _check_table(which: str) -> None:
    if which not in TABLES:
        raise ConfigurationError(f"unknown table {which!r} (use {', '.join(TABLES)})")


def table_rows(results: list[dict[str, Any]], which: str) -> list[dict[str, Any]]:
    """The rows of one table (``"table1"`` or ``"table2"``), in the paper's order.

    Parameters
    ----------
    results : list of dict
        Evaluation rows (:func:`ekdun.evaluation.evaluate_model` plus ``model`` and
        ``schedule``), as in ``results.json``.
    which : {"table1", "table2"}
        Table 1: Le-ADMM-U, UPDN and EK-DUN (last-2); Table 2: the EK-DUN schedules.

    Returns
    -------
    list of dict
    """
    _check_table(which)
    table1, table2 = split_tables(results)
    return table1 if which == "table1" else table2


def missing_rows(results: list[dict[str, Any]], which: str) -> list[str]:
    """Labels of the paper's rows of table ``which`` that ``results`` lack."""
    rows = table_rows(results, which)
    if which == "table1":      # its only EK-DUN row is last-2, whatever its label says
        have = {label_for(str(r.get("model")), "last-2") for r in rows}
    else:
        have = {str(r.get("label")) for r in rows}
    return [label for label in EXPECTED[which] if label not in have]


def render_table(results: list[dict[str, Any]], which: str,
                 notes: list[str] | None = None) -> str:
    """Table ``which`` as Markdown (title, table, notes).

    Raises
    ------
    InvalidInputError
        ``results`` hold no row of that table.
    """
    rows = table_rows(results, which)
    title, columns = TABLES[which]
    if not rows:
        raise InvalidInputError(f"no rows for {title.split(':')[0]}: it needs "
                                f"{', '.join(EXPECTED[which])} results")
    footer = "\n".join(f"\n{n}" for n in (notes or []))
    return f"### {title}\n\n{markdown_table(rows, columns)}\n{footer}\n"


def _write_json(path: Path, doc: dict[str, Any]) -> Path:
    with atomic_file(path) as tmp:
        tmp.write_text(dumps_finite(doc, str(path), indent=1, default=float) + "\n",
                       encoding="utf-8")
    return path


def write_table(out_dir: str | os.PathLike, results: list[dict[str, Any]], which: str,
                notes: list[str] | None = None) -> dict[str, Path]:
    """Write one table, ``{which}.md`` and ``{which}.json``, into ``out_dir``.

    Raises
    ------
    InvalidInputError
        ``results`` hold no row of that table (nothing is written).
    """
    text = render_table(results, which, notes)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    doc = {"title": TABLES[which][0], "rows": table_rows(results, which),
           "notes": notes or []}
    written = {f"{which}.json": _write_json(out_dir / f"{which}.json", doc)}
    with atomic_file(out_dir / f"{which}.md") as tmp:
        tmp.write_text(text, encoding="utf-8")
    written[f"{which}.md"] = out_dir / f"{which}.md"
    return written


def write_results(out_dir: str | os.PathLike, results: list[dict[str, Any]],
                  notes: list[str] | None = None) -> Path:
    """Write ``results.json`` (every evaluated run; :func:`read_results` reads it back)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return _write_json(out_dir / "results.json", {"results": results, "notes": notes or []})


def read_results(path: str | os.PathLike) -> tuple[list[dict[str, Any]], list[str]]:
    """Rows and notes of a ``results.json`` written by ``ekdun eval``, ``ekdun
    benchmark-tiny`` or :func:`write_results` (a folder means its ``results.json``).

    Raises
    ------
    InvalidInputError
        Missing file, not JSON, or not a results file (rows need ``model`` and ``psnr``).
    """
    path = Path(path)
    if path.is_dir():
        path = path / "results.json"
    if not path.is_file():
        raise InvalidInputError(f"{path}: no such results file")
    doc = read_json_file(path)
    rows = doc.get("results") if isinstance(doc, dict) else None
    if not isinstance(rows, list) or not all(
            isinstance(r, dict) and "model" in r and "psnr" in r for r in rows):
        raise InvalidInputError(f"{path}: not an ekdun results file (expected "
                                "{\"results\": [{\"model\": ..., \"psnr\": ...}, ...]})")
    notes = doc.get("notes", [])
    return rows, [str(n) for n in notes] if isinstance(notes, list) else []


def write_tables(out_dir: str | os.PathLike, results: list[dict[str, Any]],
                 notes: list[str] | None = None) -> dict[str, Path]:
    """Write ``results.json``, ``table1.md``/``.json`` and ``table2.md``/``.json``.

    A table without rows gets its ``.json`` (empty ``rows``) but no ``.md``.
    """
    out_dir = Path(out_dir)
    written = {"results.json": write_results(out_dir, results, notes)}
    for which, (title, _) in TABLES.items():
        if table_rows(results, which):
            written.update(write_table(out_dir, results, which, notes))
        else:
            written[f"{which}.json"] = _write_json(out_dir / f"{which}.json", {
                "title": title, "rows": [], "notes": notes or []})
    return written
