"""HTML building blocks shared by psfkit's self-contained report pages (grid report,
learned-vs-measured comparison): the stylesheet, table cells and embedded figures."""

from __future__ import annotations

import html
import math
from typing import Any

REPORT_CSS = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto; color: #222; }
h1 { font-size: 1.5em; } h2 { font-size: 1.2em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; font-size: 0.85em; margin: 0.5em 0; }
th, td { padding: 2px 8px; text-align: left; border-bottom: 1px solid #eee; }
table.grid td { text-align: right; }
figure { margin: 1em 0; } img { max-width: 100%; }
figcaption { font-size: 0.85em; color: #555; }
.warn { background: #fff6e0; padding: 0.5em 1em; border-left: 3px solid #e0a000; }
"""
"""The stylesheet shared by psfkit's HTML reports."""


def format_value(value: Any, spec: str = ".4g") -> str:
    """A number or text for an HTML cell (``–`` for missing or non-finite values)."""
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if isinstance(value, float):
        return format(value, spec)
    return html.escape(str(value))


def html_table(rows: list[tuple[str, Any]]) -> str:
    """A two-column key/value HTML table."""
    cells = "".join(f"<tr><th>{html.escape(k)}</th><td>{format_value(v)}</td></tr>"
                    for k, v in rows)
    return f"<table class='kv'>{cells}</table>"


def figures_html(figures: list[tuple[str, str, str]]) -> str:
    """``<figure>`` elements of ``(stem, caption, base64 PNG)``, each linking to
    ``figures/<stem>.pdf`` and ``.png``."""
    return "".join(
        f"<figure id='{stem}'><img alt='{html.escape(caption)}' "
        f"src='data:image/png;base64,{data}'><figcaption>{html.escape(caption)} "
        f"(<a href='figures/{stem}.pdf'>PDF</a>, <a href='figures/{stem}.png'>PNG</a>)"
        f"</figcaption></figure>" for stem, caption, data in figures)
