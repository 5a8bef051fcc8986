"""HTML building blocks of self-contained report pages (psfkit's grid report, and the
research comparison's page): the stylesheet, table cells and embedded figures."""

from __future__ import annotations

import html
import math
from collections.abc import Iterable, Sequence
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
.verdict { background: #eef5ff; padding: 0.6em 1em; border-left: 4px solid #2a6fdb;
           font-size: 1.05em; }
.nd { color: #999; } .nd small { font-size: 0.8em; }
"""
"""The stylesheet shared by psfkit's HTML reports."""


class Html(str):
    """Text that is already HTML (a cell :func:`format_value` must not escape)."""


def format_value(value: Any, spec: str = ".4g") -> str:
    """A number or text for an HTML cell (``–`` for missing or non-finite values)."""
    if isinstance(value, Html):
        return value
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "–"
    if isinstance(value, float):
        return format(value, spec)
    return html.escape(str(value))


def html_page(title: str, body: str) -> str:
    """A self-contained HTML page with the shared stylesheet."""
    return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{title}</title>'
            f"\n<style>{REPORT_CSS}</style></head><body>\n{body}</body></html>\n")


def grid_table(head: Sequence[str], rows: Iterable[Sequence[Any]], spec: str = ".4g") -> str:
    """A table of numbers: the header ``head``, then one row of :func:`format_value` cells per
    item of ``rows``."""
    header = "".join(f"<th>{html.escape(h)}</th>" for h in head)
    body = "".join("<tr>" + "".join(f"<td>{format_value(v, spec)}</td>" for v in row) + "</tr>"
                   for row in rows)
    return f"<table class='grid'><tr>{header}</tr>{body}</table>"


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


def estimate_html(estimate: dict[str, Any] | None, spec: str = ".4g") -> Html:
    """An ``Estimate.to_dict()`` as a table cell: ``value ± sigma`` when significant, else greyed
    ``not detected`` (number in small print, z and p as tooltip) or ``not determined`` (the
    reason as tooltip)."""
    if not estimate:
        return Html("<span class='nd'>not measured</span>")
    if estimate.get("status") == "not determined" or estimate.get("value") is None:
        reason = html.escape(str(estimate.get("reason", "")), quote=True)
        return Html(f"<span class='nd' title='{reason}'>not determined</span>")
    number = f"{format(estimate['value'], spec)} ± {format(estimate['sigma'], spec)}"
    if estimate.get("significant"):
        return Html(html.escape(number))
    z, p = estimate.get("z"), estimate.get("p_value")
    tip = f"{number}; z = {z:.2f}" + (f", p = {p:.2g}" if p is not None else "") \
        if z is not None else number
    return Html(f"<span class='nd' title='{html.escape(tip, quote=True)}'>not detected "
                f"<small>({html.escape(number)})</small></span>")
