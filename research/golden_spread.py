"""Measure how far the golden test's outputs move when nothing but rounding changes.

``tests/e2e/test_golden_outputs.py`` compares the outputs of four commands with files in
``tests/e2e/golden/``. Its tolerances are derived from what this script measures: each variant
below runs the same commands in a fresh process (so that thread settings take) and every number
of every output is compared with the baseline run (one thread, inputs as stored):

- ``threads2``: two torch/MKL/OpenMP/OpenCV threads instead of one (the summation order of
  multi-threaded reductions and FFTs changes);
- ``ulp1``, ``ulp2``: every float32 input value moved by one ulp up or down (a random sign per
  value, seeds 1 and 2): the PSF images as the grid reader returns them for the demo (pixels at
  the sensor's saturation level are left alone: a clipped pixel reads the same on every
  machine), the scene and measurement ``.npy`` files (copied to a temporary folder) for
  ``fit-pairs`` and ``eval-model``;
- ``avx2``: torch's and MKL's AVX2 kernels and numpy without AVX-512
  (``ATEN_CPU_CAPABILITY``, ``MKL_ENABLE_INSTRUCTIONS``, ``NPY_DISABLE_CPU_FEATURES``), the
  code paths of a machine without AVX-512 (only meaningful where the CPU has AVX-512).

The commands are those of the golden test: ``psfkit demo --downsample 8``, ``psfkit fit-pairs
--basis si|ek --downsample 4 --convention source`` on ``../shared/data/dlmd_mirflickr`` and
``psfkit eval-model`` of both kernel files. The report (``spread.json`` in ``--out``, and a
table on stdout) gives, per group of numbers (list indices replaced by ``*``), the largest
absolute deviation from the baseline, and the largest deviation relative to each number's own
magnitude, for each variant; for kernel arrays the largest absolute pixel deviation relative
to the array's largest value.

    python -m research.golden_spread --out /tmp/golden-spread
    python -m research.golden_spread --out /tmp/golden-spread --variants base threads2
    python -m research.golden_spread --out /tmp/golden-spread --demo-only \
        --tolerances tests/e2e/golden/tolerances.json

``--demo-only`` runs the demo alone (a change of the characterization or the eigen fit) and
replaces only the demo's entries of an existing ``--tolerances`` table.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

DEFAULT_DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "dlmd_mirflickr"
GOLDEN = Path(__file__).resolve().parents[1] / "tests" / "e2e" / "golden"
#: numpy's (2.4) AVX-512 dispatch targets: ``X86_V4`` and the two wider groups.
NUMPY_AVX512 = "X86_V4 AVX512_ICL AVX512_SPR"
#: variant -> (threads, ulp seed or None, extra environment)
VARIANTS: dict[str, tuple[int, int | None, dict[str, str]]] = {
    "base": (1, None, {}),
    "threads2": (2, None, {}),
    "ulp1": (1, 1, {}),
    "ulp2": (1, 2, {}),
    "avx2": (1, None, {"ATEN_CPU_CAPABILITY": "avx2", "MKL_ENABLE_INSTRUCTIONS": "AVX2",
                       "NPY_DISABLE_CPU_FEATURES": NUMPY_AVX512}),
}
#: extra fit-pairs flags of the golden pairs fits: seven pairs do not determine the correction
#: kernels without the difference prior (no longer the default since issue 23)
PAIRS_FLAGS = {"si": ["--tikhonov", "0"], "ek": ["--difference", "1"]}
#: output files of one run: JSON documents and kernel files (as named in ``golden/``)
JSON_OUTPUTS = ("demo_ds8_results.json", "dlmd_ds4_si_errors.json", "dlmd_ds4_ek_errors.json")
KERNEL_OUTPUTS = ("demo_ds8_kernels.npz", "dlmd_ds4_si.npz", "dlmd_ds4_ek.npz")
PATH_KEYS = {"grid", "model", "pairs", "software"}


def one_ulp(values: np.ndarray, rng: np.random.Generator,
            keep: np.ndarray | None = None) -> np.ndarray:
    """``values`` (float32) with each element moved by one ulp towards +inf or -inf at random
    (elements where ``keep`` is true unchanged)."""
    values = np.asarray(values, dtype=np.float32)
    up = rng.random(values.shape) < 0.5
    moved = np.where(up, np.nextafter(values, np.float32(np.inf)),
                     np.nextafter(values, np.float32(-np.inf))).astype(np.float32)
    return np.where(keep, values, moved) if keep is not None else moved


def _perturb_grid_reader(seed: int) -> None:
    """Make :meth:`PsfGrid.load` return every PSF moved by one ulp (same draw per file)."""
    from psfkit.io.grid import PsfGrid

    original = PsfGrid.load

    def load(self: PsfGrid, row: int, col: int) -> np.ndarray:
        image = original(self, row, col)
        # the sensor's clip level (12-bit data here) is exact on every machine: keep it
        clipped = image >= np.float32(2.0 ** (self.bit_depth or 16) - 1)
        rng = np.random.default_rng([seed, row, col])
        return one_ulp(image, rng, clipped)

    PsfGrid.load = load  # type: ignore[method-assign]


def _perturbed_pairs(source: Path, target: Path, seed: int) -> Path:
    """Copy a pairs folder of float32 ``.npy`` files with every value moved by one ulp."""
    rng = np.random.default_rng(seed)
    for file in sorted(source.rglob("*")):
        out = target / file.relative_to(source)
        if file.is_dir():
            out.mkdir(parents=True, exist_ok=True)
        elif file.suffix == ".npy":
            out.parent.mkdir(parents=True, exist_ok=True)
            np.save(out, one_ulp(np.load(file), rng))
        else:
            out.parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(file, out)
    return target


def run_variant(out: Path, data: Path, threads: int, seed: int | None,
                demo_only: bool = False) -> None:
    """The golden test's commands, in this process, writing the files of ``golden/`` to
    ``out`` (``demo_only``: the demo's)."""
    import cv2
    import torch

    from psfkit.cli.main import main

    torch.set_num_threads(threads)
    cv2.setNumThreads(threads)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        pairs = data
        if seed is not None:
            _perturb_grid_reader(seed)
            pairs = _perturbed_pairs(data, work / "pairs", seed)
        demo = work / "demo"
        assert main(["demo", "--out", str(demo), "--downsample", "8", "--quiet"]) == 0
        shutil.copy(demo / "report" / "results.json", out / "demo_ds8_results.json")
        shutil.copy(demo / "kernels.npz", out / "demo_ds8_kernels.npz")
        for model in () if demo_only else ("si", "ek"):
            kernels = out / f"dlmd_ds4_{model}.npz"
            assert main(["fit-pairs", str(pairs), "--basis", model, "--downsample", "4",
                         "--convention", "source", *PAIRS_FLAGS[model], "--out", str(kernels),
                         "--quiet"]) == 0
            assert main(["eval-model", str(kernels), str(pairs), "--downsample", "4",
                         "--out", str(out / f"dlmd_ds4_{model}_errors.json")]) == 0


def numbers(doc: Any, where: str = "") -> Iterator[tuple[str, float]]:
    """``(path, value)`` of every number of a JSON document (path-valued keys skipped)."""
    if isinstance(doc, dict):
        for key, value in doc.items():
            if key not in PATH_KEYS:
                yield from numbers(value, f"{where}.{key}" if where else key)
    elif isinstance(doc, list):
        for i, value in enumerate(doc):
            yield from numbers(value, f"{where}[{i}]")
    elif isinstance(doc, (int, float)) and not isinstance(doc, bool):
        yield where, float(doc)


def group_of(path: str, unreliable: frozenset[int] = frozenset()) -> str:
    """The group a number belongs to: its path with list indices replaced by ``*``; a grid
    position below the report's ``reliable_overlap`` (index in ``unreliable``) is its own
    group (``positions[unreliable]``)."""
    match = re.match(r"positions\[(\d+)\]", path)
    if match and int(match.group(1)) in unreliable:
        path = "positions[unreliable]" + path[match.end():]
    return re.sub(r"\[\d+\]", "[*]", re.sub(r"^per_pair\.[^.]+\.", "per_pair.*.", path))


def unreliable_positions(doc: Any) -> frozenset[int]:
    """Indices of the positions of a ``results.json`` below its ``reliable_overlap`` (the
    centre PSF's light in their overlap, ``support_overlap``; before issue 43 the sensor's
    share, ``overlap``)."""
    if not isinstance(doc, dict) or "positions" not in doc:
        return frozenset()
    return frozenset(i for i, p in enumerate(doc["positions"])
                     if p.get("support_overlap", p["overlap"]) < doc["reliable_overlap"])


def _kernel_doc(file: Path) -> tuple[np.ndarray, Any]:
    with np.load(file) as z:
        return z["kernels"].astype(np.float64), json.loads(str(z["metadata"]))


def prediction_difference(new: Path, old: Path, data: Path) -> float:
    """``‖A_new x − A_old x‖ / ‖A_old x‖`` over the (stored) DLMD scenes at 1/4 resolution:
    the kernels compared in the norm the fit minimises."""
    from psfkit.cli.pairs_folder import load_pairs
    from psfkit.fitting.pairs.fit import predict
    from psfkit.forward.kernelfile import load_kernels

    _, scenes, _ = load_pairs(str(data), 4)
    a = predict(load_kernels(new), scenes).astype(np.float64)
    b = predict(load_kernels(old), scenes).astype(np.float64)
    return float(np.linalg.norm(a - b) / np.linalg.norm(b))


def deviations(run: Path, base: Path, data: Path, demo_only: bool = False
               ) -> dict[str, dict[str, dict[str, float]]]:
    """Per output file and group: the largest absolute deviation of ``run`` from ``base``, the
    largest relative one (to the base value's magnitude), and the magnitude of the group
    (``demo_only``: the demo's outputs)."""
    report: dict[str, dict[str, dict[str, float]]] = {}

    def compare(name: str, new: Any, old: Any) -> None:
        groups = report.setdefault(name, {})
        new_values = dict(numbers(new))
        unreliable = unreliable_positions(old)
        for path, value in numbers(old):
            group = group_of(path, unreliable)
            if path not in new_values and SKIPPED.match(group):
                continue          # NaN (null) in this run: an ill-conditioned, skipped group
            entry = groups.setdefault(group, {"abs": 0.0, "rel": 0.0, "size": 0.0})
            delta = abs(new_values[path] - value) if path in new_values else float("inf")
            entry["abs"] = max(entry["abs"], delta)
            entry["rel"] = max(entry["rel"], delta / abs(value) if value else
                               (0.0 if delta == 0 else float("inf")))
            entry["size"] = max(entry["size"], abs(value))

    for name in _outputs(JSON_OUTPUTS, demo_only):
        compare(name, json.loads((run / name).read_text()), json.loads((base / name).read_text()))
    for name in _outputs(KERNEL_OUTPUTS, demo_only):
        (new_k, new_meta), (old_k, old_meta) = _kernel_doc(run / name), _kernel_doc(base / name)
        scale = float(np.abs(old_k).max())
        delta = np.abs(new_k - old_k)
        report.setdefault(name, {})["kernels"] = {
            "abs": float(delta.max()), "rel_to_max": float(delta.max() / scale),
            "size": scale,
            "fraction_changed": float(np.mean(delta > 0)),
            # deviation per kernel relative to that kernel's energy (L2), the conditioning
            # that matters for a forward model
            "rel_l2": float(np.linalg.norm(new_k - old_k) / np.linalg.norm(old_k))}
        if name.startswith("dlmd"):
            report[name]["kernels"]["prediction"] = prediction_difference(run / name,
                                                                          base / name, data)
        compare(name + ":metadata", new_meta, old_meta)
    return report


def _outputs(names: tuple[str, ...], demo_only: bool) -> tuple[str, ...]:
    return tuple(n for n in names if n.startswith("demo")) if demo_only else names


#: tolerance = SAFETY × the largest measured deviation (floored): room for machines and
#: perturbations not sampled here, still far below what a wrong result changes
SAFETY = 10.0
#: groups whose one-ulp spread is not a machine effect: the SNR's noise level is a median
#: absolute deviation of 12-bit quantised data, whose ties a one-ulp change breaks; integer reads,
#: elementwise IEEE arithmetic and order statistics give the same bits on every machine
#: (threads and ISA spread 0), so its tolerance comes from the machine spread alone
ULP_TIES = {"positions[*].snr", "positions[unreliable].snr"}
#: ill-conditioned groups not compared: ECC and dense flow on a PSF that overlaps the centre PSF
#: by less than ``reliable_overlap`` (the report marks these unreliable and leaves them out of
#: the warp growth fit, which is compared)
SKIPPED = re.compile(r"^positions\[unreliable\]\.warp\.")


def _round_up(x: float) -> float:
    """``x`` rounded up to one significant digit (1, 2 or 5 times a power of ten)."""
    if x <= 0:
        return 0.0
    exponent = np.floor(np.log10(x))
    for step in (1.0, 2.0, 5.0, 10.0):
        if x <= step * 10**exponent * (1 + 1e-12):
            return float(step * 10**exponent)
    return float(10 ** (exponent + 1))


def tolerance_table(spread: dict[str, Any]) -> dict[str, Any]:
    """Per output and group: ``abs`` tolerance (``SAFETY`` × the largest absolute deviation
    of any variant, at least 1e-9 × the group's largest magnitude), beside the measured spread.
    Kernel arrays get ``max_rel_to_peak`` (pixels), ``rel_l2`` and, for the pairs fits,
    ``prediction`` tolerances, or none where ``max_rel_to_peak`` is ill-conditioned."""
    machine = [v for v in ("threads2", "avx2") if v in spread]
    ulp = [v for v in spread if v.startswith("ulp")]
    table: dict[str, Any] = {}
    for name in spread[machine[0]]:
        out = table.setdefault(name, {})
        # the golden files of a changed output (deliberately regenerated) are no other machine
        others = ["vs_golden"] if "vs_golden" in spread and name.startswith("dlmd") else []
        for group, first in spread[machine[0]][name].items():
            measured = {
                "threads_1_vs_2": spread["threads2"][name][group]["abs"],
                "avx2_vs_avx512": spread["avx2"][name][group]["abs"] if "avx2" in spread
                else None,
                "one_ulp": max(spread[v][name][group]["abs"] for v in ulp) if ulp else None,
                "golden_machine": spread["vs_golden"][name][group]["abs"] if others else None}
            if group == "kernels":
                keys = ["rel_to_max", "rel_l2"] + (["prediction"] if "prediction" in first
                                                   else [])
                entry: dict[str, Any] = {}
                for key in keys:
                    worst = max(spread[v][name][group][key] for v in machine + ulp + others)
                    entry[key] = {"tolerance": _round_up(SAFETY * worst) or 1e-9,
                                  "measured": {v: spread[v][name][group][key]
                                               for v in machine + ulp + others}}
                # a pixel deviation of more than 1 % of the peak under rounding alone: the pixels
                # are ill-conditioned, compared only through rel_l2 and the prediction
                if entry["rel_to_max"]["tolerance"] > 1e-2:
                    entry["rel_to_max"]["tolerance"] = None
                out[group] = entry
                continue
            if SKIPPED.match(group):
                out[group] = {"abs": None, "measured": measured}
                continue
            used = [m for k, m in measured.items() if m is not None and
                    not (group in ULP_TIES and k == "one_ulp")]
            floor = 1e-9 * first["size"]
            out[group] = {"abs": max(_round_up(SAFETY * max(used)), floor) if floor else
                          _round_up(SAFETY * max(used)), "measured": measured}
    return table


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True, help="folder for the runs and "
                        "spread.json")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA, help="DLMD pairs folder")
    parser.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    parser.add_argument("--reuse", action="store_true", help="keep runs already in --out")
    parser.add_argument("--tolerances", type=Path, help="also write the tolerance table "
                        "derived from the spread here (tests/e2e/golden/tolerances.json)")
    parser.add_argument("--demo-only", action="store_true", help="run the demo alone and "
                        "replace only its entries of the --tolerances table")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args(argv)
    if args.worker:
        threads, seed, _ = VARIANTS[args.worker]
        run_variant(args.out / args.worker, args.data, threads, seed, args.demo_only)
        return 0
    variants = ["base", *[v for v in args.variants if v != "base"]]
    kernel_outputs = _outputs(KERNEL_OUTPUTS, args.demo_only)
    for name in variants:
        if args.reuse and (args.out / name / kernel_outputs[-1]).exists():
            continue
        threads, _, extra = VARIANTS[name]
        env = {**os.environ, "OMP_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
               "OPENBLAS_NUM_THREADS": str(threads), **extra}
        print(f"running {name} ...", flush=True)
        subprocess.run([sys.executable, __file__, "--out", str(args.out), "--data",
                        str(args.data), "--worker", name]
                       + (["--demo-only"] if args.demo_only else []), env=env, check=True,
                       stdout=subprocess.DEVNULL)
    spread = {name: deviations(args.out / name, args.out / "base", args.data, args.demo_only)
              for name in variants[1:]}
    # what this machine computes against the golden files (another machine's baseline; only
    # the pairs' outputs are compared, see tolerance_table)
    if not args.demo_only and all((GOLDEN / f).exists()
                                  for f in (*JSON_OUTPUTS, *KERNEL_OUTPUTS)):
        spread["vs_golden"] = deviations(args.out / "base", GOLDEN, args.data)
    from psfkit.io.jsonable import write_json

    write_json(args.out / "spread.json", spread)
    if args.tolerances:
        table = tolerance_table(spread)
        if args.demo_only and args.tolerances.exists():     # the pairs' entries kept
            table = {**json.loads(args.tolerances.read_text()), **table}
        write_json(args.tolerances, table)
    columns = list(spread)
    print(f"{'output / group':70s}" + "".join(f"{c:>20s}" for c in columns))
    json_outputs = _outputs(JSON_OUTPUTS, args.demo_only)
    for name in (*json_outputs, *kernel_outputs, *(k + ":metadata" for k in kernel_outputs)):
        for group, first in spread[columns[0]][name].items():
            cells = []
            for c in columns:
                e = spread[c][name].get(group)
                if e is None:        # a group the golden files do not have yet (a new output)
                    cells.append(f"{'new':>19s}")
                    continue
                rel = e.get("rel_to_max", e.get("rel", 0.0))
                cells.append(f"{e['abs']:9.2e}/{rel:9.2e}")
                if "rel_l2" in e:
                    extra = f" l2 {e['rel_l2']:.2e}" + (f" pred {e['prediction']:.2e}"
                                                       if "prediction" in e else "")
                    cells[-1] += extra
            if any(spread[c][name].get(group, {"abs": 1})["abs"] > 0 for c in columns) \
                    or "kernels" in group:
                print(f"{(name + ' ' + group)[:70]:70s}" + "".join(f"{s:>20s}" for s in cells)
                      + f"   |x|<={first['size']:.3g}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
