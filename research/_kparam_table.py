"""The Markdown report of ``research/kernel_parameterisations.py``: one row per run, the reference
rows against the oracle, mean ± sd over training seeds and the paired PSNR differences to free
pixels.

``doc`` is the benchmark's ``results.json``: ``{"runs": [...], "references": [...], "oracle":
{...} or None, "oracle_note": str or None}``; the list of rows of earlier versions (no λ, no
oracle) is read as ``{"runs": rows}``.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from psfkit.errors import InvalidInputError

#: Run settings that make two rows the same set-up (with the training seed: the same run);
#: defaults for rows written before they were recorded.
SETUP_DEFAULTS: dict[str, Any] = {"schedule": "last-2", "preset": "tiny",
                                  "physics_weight": 0.0, "train_seed": 0}
#: Row order of the table.
SEED_ORDER = ("measured", "pairs-free", "pairs", "one-psf")
PARAM_ORDER = ("free", "physical", "physical-gain", "flow")


def as_document(doc: Any) -> dict[str, Any]:
    """``results.json`` in the current form (a bare list of rows is the earlier form)."""
    if isinstance(doc, list):
        return {"runs": doc, "references": [], "oracle": None, "oracle_note": None}
    if not isinstance(doc, dict) or not isinstance(doc.get("runs"), list):
        raise InvalidInputError("results.json: expected a list of rows or an object with "
                                "'runs'")
    return doc


def setting(row: dict[str, Any], key: str) -> Any:
    """A run's setting, with the default of rows that predate it."""
    value = row.get(key)
    return SETUP_DEFAULTS.get(key) if value is None else value


def run_key(row: dict[str, Any]) -> tuple:
    """What identifies a run in ``results.json`` (merging across invocations)."""
    return (row["seed"], row["param"], setting(row, "schedule"), setting(row, "preset"),
            float(setting(row, "physics_weight")), int(setting(row, "train_seed")),
            row["epochs"])


def format_number(value: Any, fmt: str = "+.2f") -> str:
    """``value`` formatted, ``n/a`` for None or NaN."""
    return "n/a" if value is None or value != value else format(value, fmt)


def _pair(row: dict[str, Any], prefix: str, suffix: str, fmt: str) -> str:
    return (f"{format_number(row.get(f'{prefix}v_{suffix}'), fmt)} / "
            f"{format_number(row.get(f'{prefix}h_{suffix}'), fmt)}")


def _angles(values: Any) -> str:
    return ", ".join(f"{a:.1f}" for a in (values or []))


def _label(row: dict[str, Any]) -> str:
    schedule = setting(row, "schedule")
    label = row["param"] + ("" if schedule == "last-2" else f", {schedule}")
    return label + (f" (training seed {row['train_seed']})" if row.get("train_seed") else "")


def has_oracle(doc: dict[str, Any]) -> bool:
    """Whether the runs were compared with an oracle (the dataset has one)."""
    return doc.get("oracle") is not None


def _order(row: dict[str, Any]) -> tuple:
    seed, param, *rest = run_key(row)
    return (SEED_ORDER.index(seed) if seed in SEED_ORDER else len(SEED_ORDER), seed,
            PARAM_ORDER.index(param) if param in PARAM_ORDER else len(PARAM_ORDER), param,
            *rest)


def markdown_table(doc: Any) -> str:
    """The results as Markdown: runs, reference rows, spread and paired differences."""
    doc = as_document(doc)
    rows, oracle = sorted(doc["runs"], key=_order), has_oracle(doc)
    head = ("| seed | kernels | λ | PSNR (dB) | SSIM | pedestal share of change | kernel mass "
            "outside support | disp. corr Kv / Kh | diff. NCC Kv / Kh | angles to top-3 PCA "
            "(°) | test prediction error |")
    if oracle:
        head += (" oracle: diff. NCC Kv / Kh | oracle: disp. corr Kv / Kh | oracle: EPE px "
                 "Kv / Kh | oracle: angles (°) |")
    lines = [head, "|" + " --- |" * (head.count("|") - 1)]
    for r in rows:
        line = (f"| {r['seed']} | {_label(r)} | {float(setting(r, 'physics_weight')):g} | "
                f"{r['psnr']:.2f} | {r['ssim']:.4f} | {100 * r['pedestal_share']:.1f} % | "
                f"{100 * r['outside_mass']:.1f} % | {_pair(r, '', 'disp_corr', '+.2f')} | "
                f"{_pair(r, '', 'diff_ncc', '.3f')} | {_angles(r.get('angles_pca'))} | "
                f"{format_number(r.get('test_prediction_error'), '.4f')} |")
        if oracle:
            line += (f" {_pair(r, 'oracle_', 'diff_ncc', '.3f')} | "
                     f"{_pair(r, 'oracle_', 'disp_corr', '+.2f')} | "
                     f"{_pair(r, 'oracle_', 'epe_px', '.3f')} | "
                     f"{_angles(r.get('oracle_angles'))} |")
        lines.append(line)
    return "\n".join([*lines, *_reference_lines(doc), *_spread_lines(rows, oracle),
                      *_paired_lines(rows)])


def _reference_lines(doc: dict[str, Any]) -> list[str]:
    if not has_oracle(doc):
        note = doc.get("oracle_note")
        return [f"\nNo oracle: {note}"] if note else []
    o = doc["oracle"]
    lines = [f"\nAgainst the operator oracle ({o['file']}, {o['convention']} side), the seeds "
             "and the oracle itself:\n",
             "| reference | diff. NCC Kv / Kh | disp. corr Kv / Kh | EPE px Kv / Kh | "
             "angles (°) | test prediction error |", "| --- | --- | --- | --- | --- | --- |"]
    for r in doc.get("references", []):
        lines.append(f"| {r['reference']} | {_pair(r, 'oracle_', 'diff_ncc', '.3f')} | "
                     f"{_pair(r, 'oracle_', 'disp_corr', '+.2f')} | "
                     f"{_pair(r, 'oracle_', 'epe_px', '.3f')} | "
                     f"{_angles(r.get('oracle_angles'))} | "
                     f"{format_number(r.get('test_prediction_error'), '.4f')} |")
    return lines


def _mean_sd(values: list[Any], fmt: str) -> str:
    x = np.array([np.nan if v is None else v for v in values], float)
    x = x[np.isfinite(x)]
    if not x.size:
        return "n/a"
    sd = x.std(ddof=1) if x.size > 1 else float("nan")
    return f"{format(x.mean(), fmt)} ± {format_number(sd, fmt.lstrip('+'))}"


def _groups(rows: list[dict[str, Any]], exclude: str) -> dict[tuple, list[dict[str, Any]]]:
    out: dict[tuple, list[dict[str, Any]]] = {}
    for r in rows:
        key = tuple(v for k, v in zip(("seed", "param", "schedule", "preset", "physics_weight",
                                       "train_seed", "epochs"), run_key(r), strict=True)
                    if k != exclude)
        out.setdefault(key, []).append(r)
    return out


def _spread_lines(rows: list[dict[str, Any]], oracle: bool) -> list[str]:
    """Mean ± standard deviation over training seeds, where a set-up ran with several."""
    lines = []
    for key, runs in _groups(rows, "train_seed").items():
        if len(runs) < 2:
            continue
        seed, param, schedule, _preset, lam, _epochs = key
        psnrs = np.array([r["psnr"] for r in runs])
        text = (f"\n{seed} / {param}" + ("" if schedule == "last-2" else f" / {schedule}")
                + f", λ = {lam:g}, {len(runs)} training seeds: PSNR "
                f"{_mean_sd(list(psnrs), '.2f')} dB (range {psnrs.min():.2f}–"
                f"{psnrs.max():.2f}); vs measured: disp. corr "
                f"{_mean_sd([r['v_disp_corr'] for r in runs], '+.2f')} / "
                f"{_mean_sd([r['h_disp_corr'] for r in runs], '+.2f')}, diff. NCC "
                f"{_mean_sd([r['v_diff_ncc'] for r in runs], '.3f')} / "
                f"{_mean_sd([r['h_diff_ncc'] for r in runs], '.3f')}; test prediction error "
                f"{_mean_sd([r.get('test_prediction_error') for r in runs], '.4f')}")
        if oracle:
            text += (f"; vs oracle: diff. NCC "
                     f"{_mean_sd([r.get('oracle_v_diff_ncc') for r in runs], '.3f')} / "
                     f"{_mean_sd([r.get('oracle_h_diff_ncc') for r in runs], '.3f')}, disp. "
                     f"corr {_mean_sd([r.get('oracle_v_disp_corr') for r in runs], '+.2f')} / "
                     f"{_mean_sd([r.get('oracle_h_disp_corr') for r in runs], '+.2f')}")
        lines.append(text)
    return lines


def paired_differences(rows: list[dict[str, Any]]) -> dict[tuple, list[tuple[int, float]]]:
    """PSNR of each non-free run minus free pixels' with the same seed, schedule, preset, λ,
    training seed and epochs: set-up key → ``[(training seed, ΔPSNR), ...]``."""
    free = {run_key(r)[:1] + run_key(r)[2:]: r for r in rows if r["param"] == "free"}
    out: dict[tuple, list[tuple[int, float]]] = {}
    for r in rows:
        if r["param"] == "free":
            continue
        k = run_key(r)
        partner = free.get(k[:1] + k[2:])
        if partner is not None:
            out.setdefault(k[:5] + k[6:], []).append((k[5], r["psnr"] - partner["psnr"]))
    return out


def _paired_lines(rows: list[dict[str, Any]]) -> list[str]:
    lines = []
    for (seed, param, schedule, _preset, lam, _epochs), diffs in paired_differences(
            rows).items():
        d = np.array([v for _, v in diffs])
        text = (f"\npaired ΔPSNR to free pixels, {seed} / {param}"
                + ("" if schedule == "last-2" else f" / {schedule}") + f", λ = {lam:g}: "
                + ", ".join(f"{v:+.2f}" for v in d) + " dB (training seeds "
                + ", ".join(str(t) for t, _ in diffs) + ")")
        if len(d) > 1:
            text += f": mean {d.mean():+.2f} ± {d.std(ddof=1):.2f} dB"
        lines.append(text)
    return lines
