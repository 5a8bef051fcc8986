"""Tables 1 and 2 as Markdown and JSON (written atomically)."""

from __future__ import annotations

import math
import os
import statistics
from pathlib import Path
from typing import Any

from ekdun.errors import ConfigurationError, InvalidInputError
from psfkit.forward.zones import ZONE_NAMES
from psfkit.io.atomic import atomic_file
from psfkit.io.json_documents import dumps_finite, read_json_file

MODEL_LABELS = {"le-admm-u": "Le-ADMM-U", "updn": "UPDN", "ekdun": "EK-DUN"}
SCHEDULE_LABELS = {"base": "base only", "last-2": "last-2", "last-k": "last-2", "all": "all"}


def label_for(model: str, schedule: str | None) -> str:
    """Row label of a run, e.g. ``EK-DUN (last-2)``."""
    name = MODEL_LABELS.get(model, model)
    return f"{name} ({schedule})" if model == "ekdun" and schedule else name


def variant_of(row: dict[str, Any]) -> str:
    """What sets an EK-DUN run apart from the paper's training, e.g. ``one-PSF seed, flow
    kernels, λ = 1, frozen kernels`` (``""`` for none)."""
    parts = ["one-PSF seed"] if row.get("seed_kernels_one_psf") else []
    param = row.get("kernel_param")
    if param not in (None, "free"):
        parts.append(f"{param} kernels")
    weight = row.get("physics_weight")
    if weight:
        parts.append(f"λ = {float(weight):g}")
    if row.get("model") == "ekdun" and row.get("kernel_lr_scale") == 0:
        parts.append("frozen kernels")
    return ", ".join(parts)


def _fmt(value: Any, digits: int) -> str:
    if value is None or (isinstance(value, float) and math.isnan(value)):
        return "n/a"
    if isinstance(value, int):
        return f"{value:,}"
    return f"{value:.{digits}f}"


def zone_cells(row: dict[str, Any]) -> dict[str, str]:
    """The Markdown cells of :data:`ZONE_COLUMNS` for one row, e.g. ``"21.30 / 20.12 / 18.95"``
    (centre / middle / edge), ``"n/a"`` for rows without zones."""
    by_zone = row.get("by_zone")
    cells = {}
    for key, metric, digits in (("psnr_by_zone", "psnr", 2), ("ssim_by_zone", "ssim", 4)):
        try:
            cells[key] = " / ".join(_fmt(by_zone[zone][metric], digits)
                                    for zone in ZONE_NAMES)
        except (KeyError, TypeError):
            cells[key] = "n/a"
    return cells


def markdown_table(rows: list[dict[str, Any]], columns: list[tuple[str, str, int]]) -> str:
    """``columns``: ``(key, header, digits)``."""
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    sep = "|" + "|".join("---" for _ in columns) + "|"
    body = ["| " + " | ".join(str(r.get(k, "")) if d < 0 else _fmt(r.get(k), d)
                              for k, _, d in columns) + " |" for r in rows]
    return "\n".join([head, sep, *body])


#: The field-zone columns (``by_zone`` of :func:`ekdun.evaluation.evaluate_model`; cells by
#: :func:`zone_cells`): where in the field a network gains or loses.
ZONE_COLUMNS = [("psnr_by_zone", "PSNR centre / middle / edge (dB)", -1),
                ("ssim_by_zone", "SSIM centre / middle / edge", -1)]
TABLE1_COLUMNS = [("label", "Method", -1), ("seed", "Training seed", 0),
                  ("psnr", "PSNR (dB)", 2), ("ssim", "SSIM", 4),
                  ("lpips", "LPIPS", 4), ("parameters", "Parameters", 0),
                  ("runtime_ms_median", "Runtime / image (ms, median)", 1),
                  ("peak_memory_mib", "Peak memory (MiB)", 1), *ZONE_COLUMNS]
TABLE2_COLUMNS = [("label", "Eigen-kernel model in", -1), ("seed", "Training seed", 0),
                  ("psnr", "PSNR (dB)", 2), ("ssim", "SSIM", 4), ("lpips", "LPIPS", 4),
                  ("runtime_ms_median", "Inference / image (ms, median)", 2), *ZONE_COLUMNS]

#: Each table's reference row, the one the others are compared with seed by seed.
REFERENCE = {"table1": "EK-DUN (last-2)", "table2": "base only"}


def summary_columns(which: str) -> list[tuple[str, str, int]]:
    """The columns of table ``which``'s summary over training seeds."""
    return [("label", "Method" if which == "table1" else "Eigen-kernel model in", -1),
            ("psnr_text", "PSNR (dB), mean ± sd", -1), ("ssim_mean", "SSIM", 4),
            ("delta_text", f"Δ PSNR to {REFERENCE[which]}, paired by seed (dB)", -1),
            ("runtime_ms_median", "Inference / image (ms, median)", 2)]


def _distinct_variants(results: list[dict[str, Any]]) -> list[str]:
    """:func:`variant_of` of each row, plus ``seed kernels <sha>`` where rows of one schedule
    and variant started from different seed kernels (different experiments)."""
    variants = [variant_of(r) for r in results]
    shas: dict[tuple[str, str], set[str]] = {}
    for r, v in zip(results, variants, strict=True):
        if r.get("seed_kernels_sha"):
            shas.setdefault((str(r.get("schedule")), v), set()).add(str(r["seed_kernels_sha"]))
    out = []
    for r, v in zip(results, variants, strict=True):
        if len(shas.get((str(r.get("schedule")), v), ())) > 1:
            v = ", ".join(filter(None, [v, f"seed kernels {str(r['seed_kernels_sha'])[:8]}"]))
        out.append(v)
    return out


def split_tables(results: list[dict[str, Any]]) -> tuple[list[dict], list[dict]]:
    """Table 1: Le-ADMM-U, UPDN, EK-DUN (last-2); Table 2: EK-DUN schedules."""
    table1, table2 = [], []
    variants = _distinct_variants(results)
    for i, r in enumerate(results):
        if r.get("model") in ("le-admm-u", "updn"):
            table1.append(r)
        elif r.get("model") == "ekdun":
            sched = SCHEDULE_LABELS.get(str(r.get("schedule")), str(r.get("schedule")))
            variant = variants[i]
            # runs trained otherwise than the paper's get their own row label: pooled under
            # "last-2" they would pass for the paper's row
            table2.append({**r, "label": f"{sched} ({variant})" if variant else sched})
            if sched == "last-2":
                table1.append({**r, "label": label_for("ekdun", f"{r.get('schedule')}, "
                                                                  f"{variant}")}
                              if variant else r)
    def by_seed(r: dict[str, Any]) -> int:
        return r.get("seed") if isinstance(r.get("seed"), int) else -1

    # the paper's order; a label's training seeds together
    first = {label: i for i, label in enumerate(dict.fromkeys(str(r.get("label"))
                                                             for r in table1))}
    table1.sort(key=lambda r: (first[str(r.get("label"))], by_seed(r)))
    order = {"base only": 0, "last-2": 1, "all": 2}
    table2.sort(key=lambda r: (order.get(r["label"].split(" (")[0], 9), r["label"],
                               by_seed(r)))
    return table1, table2


def _mean_sd(values: list[float]) -> tuple[float, float | None]:
    """Mean and sample sd (None for one value)."""
    return statistics.fmean(values), statistics.stdev(values) if len(values) > 1 else None


def _pm(mean: float, sd: float | None, n: int, signed: bool = False) -> str:
    text = f"{mean:+.2f}" if signed else f"{mean:.2f}"
    return f"{text} ± {sd:.2f} (n = {n})" if sd is not None else f"{text} (n = 1)"


def seed_summary(rows: list[dict[str, Any]], reference: str = "base only"
                 ) -> list[dict[str, Any]]:
    """A table over training seeds: per row label, PSNR mean ± sample sd, mean SSIM, median
    inference time and the PSNR difference to the ``reference`` label paired by seed.

    Parameters
    ----------
    rows : list of dict
        A table's rows (:func:`table_rows`).
    reference : str
        The label the others are compared with (:data:`REFERENCE`).

    Returns
    -------
    list of dict
        One entry per label, in the rows' order: ``label``, ``runs``, ``seeds``,
        ``psnr_mean``, ``psnr_sd`` (None for one run), ``ssim_mean``, ``runtime_ms_median``,
        ``reference``, ``delta_mean`` / ``delta_sd`` / ``delta_seeds`` (None where no seed
        has exactly one run of both), and the Markdown cells ``psnr_text`` / ``delta_text``.
    """
    groups: dict[str, list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(str(r["label"]), []).append(r)

    def by_seed(group: list[dict[str, Any]]) -> dict[Any, float]:
        seeds = [r.get("seed") for r in group]
        return {r.get("seed"): float(r["psnr"]) for r in group
                if r.get("seed") is not None and seeds.count(r.get("seed")) == 1}

    base = by_seed(groups.get(reference, []))
    summary = []
    for label, group in groups.items():
        psnr_mean, psnr_sd = _mean_sd([float(r["psnr"]) for r in group])
        times = [float(r["runtime_ms_median"]) for r in group
                 if r.get("runtime_ms_median") is not None]
        entry: dict[str, Any] = {
            "label": label, "runs": len(group),
            "seeds": [r.get("seed") for r in group],
            "psnr_mean": psnr_mean, "psnr_sd": psnr_sd,
            "ssim_mean": statistics.fmean(float(r["ssim"]) for r in group),
            "runtime_ms_median": statistics.median(times) if times else None,
            "psnr_text": _pm(psnr_mean, psnr_sd, len(group)),
            "reference": reference, "delta_mean": None, "delta_sd": None, "delta_seeds": [],
            "delta_text": "-" if label == reference else "n/a",
        }
        own = by_seed(group)
        paired = sorted((s for s in own if s in base), key=str)
        if label != reference and paired:
            deltas = [own[s] - base[s] for s in paired]
            mean, sd = _mean_sd(deltas)
            entry.update(delta_mean=mean, delta_sd=sd, delta_seeds=paired,
                         delta_text=_pm(mean, sd, len(paired), signed=True))
        summary.append(entry)
    return summary


TABLES: dict[str, tuple[str, list[tuple[str, str, int]]]] = {
    "table1": ("Table 1: comparison with Le-ADMM-U and UPDN", TABLE1_COLUMNS),
    "table2": ("Table 2: where EK-DUN uses the eigen-kernel model", TABLE2_COLUMNS),
}
EXPECTED = {"table1": ("EK-DUN (last-2)", "Le-ADMM-U", "UPDN"),
            "table2": ("base only", "last-2", "all")}


def table_rows(results: list[dict[str, Any]], which: str) -> list[dict[str, Any]]:
    """The rows of table ``which`` (``"table1"``: Le-ADMM-U, UPDN and EK-DUN (last-2);
    ``"table2"``: the EK-DUN schedules) among evaluation ``results``, in the paper's order."""
    if which not in TABLES:
        raise ConfigurationError(f"unknown table {which!r} (use {', '.join(TABLES)})")
    table1, table2 = split_tables(results)
    return table1 if which == "table1" else table2


def render_table(results: list[dict[str, Any]], which: str,
                 notes: list[str] | None = None) -> str:
    """Table ``which`` as Markdown (title, table, notes); :class:`InvalidInputError` when
    ``results`` hold no row of it."""
    rows = [{**r, **zone_cells(r)} for r in table_rows(results, which)]
    title, columns = TABLES[which]
    if not any(isinstance(r.get("seed"), int) for r in rows):   # runs of unknown seed
        columns = [c for c in columns if c[0] != "seed"]
    if not rows:
        raise InvalidInputError(f"no rows for {title.split(':')[0]}: it needs "
                                f"{', '.join(EXPECTED[which])} results")
    footer = "\n".join(f"\n{n}" for n in (notes or []))
    text = f"### {title}\n\n{markdown_table(rows, columns)}\n"
    if len(rows) > len({r["label"] for r in rows}):
        summary = seed_summary(rows, REFERENCE[which])
        text += ("\nOver training seeds (sample sd; Δ paired by training seed):\n\n"
                 f"{markdown_table(summary, summary_columns(which))}\n")
    return f"{text}{footer}\n"


def _write_text(path: Path, text: str) -> Path:
    with atomic_file(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return path


def _write_json(path: Path, doc: dict[str, Any]) -> Path:
    return _write_text(path, dumps_finite(doc, str(path), indent=1, default=float) + "\n")


def write_table(out_dir: str | os.PathLike, results: list[dict[str, Any]], which: str,
                notes: list[str] | None = None) -> dict[str, Path]:
    """Write ``{which}.md`` and ``{which}.json`` into ``out_dir``
    (:class:`InvalidInputError`, nothing written, when ``results`` hold no row of it)."""
    text = render_table(results, which, notes)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    rows = table_rows(results, which)
    doc: dict[str, Any] = {"title": TABLES[which][0], "rows": rows, "notes": notes or []}
    if which == "table2" or len(rows) > len({r["label"] for r in rows}):
        doc["over_seeds"] = seed_summary(rows, REFERENCE[which])
    return {f"{which}.json": _write_json(out_dir / f"{which}.json", doc),
            f"{which}.md": _write_text(out_dir / f"{which}.md", text)}


def write_results(out_dir: str | os.PathLike, results: list[dict[str, Any]],
                  notes: list[str] | None = None) -> Path:
    """Write ``results.json`` (every evaluated run; :func:`read_results` reads it back)."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return _write_json(out_dir / "results.json", {"results": results, "notes": notes or []})


def read_results(path: str | os.PathLike) -> tuple[list[dict[str, Any]], list[str]]:
    """Rows and notes of a ``results.json`` (:func:`write_results`; a folder means its
    ``results.json``); :class:`InvalidInputError` unless it is one."""
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
    """Write ``results.json`` and ``table{1,2}.md``/``.json`` (a table without rows: only its
    ``.json``)."""
    out_dir = Path(out_dir)
    written = {"results.json": write_results(out_dir, results, notes)}
    for which, (title, _) in TABLES.items():
        if table_rows(results, which):
            written.update(write_table(out_dir, results, which, notes))
        else:
            written[f"{which}.json"] = _write_json(out_dir / f"{which}.json", {
                "title": title, "rows": [], "notes": notes or []})
    return written
