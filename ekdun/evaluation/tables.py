"""Tables 1 and 2 as Markdown and JSON (written atomically)."""

from __future__ import annotations

import json
import math
import os
from pathlib import Path
from typing import Any

from psfkit.io.atomic import atomic_file

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


def write_tables(out_dir: str | os.PathLike, results: list[dict[str, Any]],
                 notes: list[str] | None = None) -> dict[str, Path]:
    """Write ``results.json``, ``table1.md``/``.json`` and ``table2.md``/``.json``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    table1, table2 = split_tables(results)
    written = {}
    footer = "\n".join(f"\n{n}" for n in (notes or []))
    docs = {
        "results": {"results": results, "notes": notes or []},
        "table1": {"title": "Table 1: comparison with Le-ADMM-U and UPDN", "rows": table1,
                   "notes": notes or []},
        "table2": {"title": "Table 2: where EK-DUN uses the eigen-kernel model", "rows": table2,
                   "notes": notes or []},
    }
    for name, doc in docs.items():
        path = out_dir / f"{name}.json"
        with atomic_file(path) as tmp:
            tmp.write_text(json.dumps(doc, indent=1, default=float) + "\n", encoding="utf-8")
        written[f"{name}.json"] = path
    for name, rows, cols in (("table1", table1, TABLE1_COLUMNS),
                             ("table2", table2, TABLE2_COLUMNS)):
        if not rows:
            continue
        text = f"### {docs[name]['title']}\n\n{markdown_table(rows, cols)}\n{footer}\n"
        path = out_dir / f"{name}.md"
        with atomic_file(path) as tmp:
            tmp.write_text(text, encoding="utf-8")
        written[f"{name}.md"] = path
    return written
