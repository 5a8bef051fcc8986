"""Regression: restructuring the code must not change what the commands compute.

``golden/`` holds outputs written by the code before the architecture change of issue 11
(commit 9fdec94), on the same inputs and options as below (the demo's two files were written
again by issue 15's third fit-eigen pass, a deliberate change: see CHANGELOG):

- ``psfkit demo --downsample 8`` (virtual bench, seed 0): the report's ``results.json`` and the
  eigen-kernel file ``kernels.npz``;
- ``psfkit fit-pairs`` (``--model si`` and ``--model ek``, ``--downsample 4``) on the real
  DiffuserCam Mirflickr pairs of ``../shared/data``, and ``psfkit eval-model`` of both files.

Every number must agree to 1e-6 (relative to the array's largest value for kernels); strings that
hold paths are ignored. A deliberate change of the numbers means regenerating these files with the
commands above and saying why in the CHANGELOG.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from psfkit.cli.main import main

GOLDEN = Path(__file__).resolve().parent / "golden"
TOLERANCE = 1e-6
PATH_KEYS = {"grid", "model", "pairs", "software"}


def assert_numbers_equal(new: Any, old: Any, where: str = "") -> None:
    """Recursively compare two JSON documents: numbers to ``TOLERANCE``, keys and lengths
    exactly, path-valued strings skipped."""
    if isinstance(old, dict):
        assert isinstance(new, dict), where
        assert set(new) == set(old), f"{where}: keys {sorted(set(new) ^ set(old))} differ"
        for key in old:
            if key not in PATH_KEYS:
                assert_numbers_equal(new[key], old[key], f"{where}.{key}")
    elif isinstance(old, list):
        assert isinstance(new, list) and len(new) == len(old), where
        for i, (a, b) in enumerate(zip(new, old, strict=True)):
            assert_numbers_equal(a, b, f"{where}[{i}]")
    elif isinstance(old, bool) or old is None or isinstance(old, str):
        assert new == old, f"{where}: {new!r} != {old!r}"
    else:
        assert new == pytest.approx(old, rel=TOLERANCE, abs=TOLERANCE), where


def assert_kernel_files_equal(new_file: Path, old_file: Path) -> None:
    new, old = np.load(new_file), np.load(old_file)
    assert new["kernels"].shape == old["kernels"].shape
    scale = float(np.abs(old["kernels"]).max())
    np.testing.assert_allclose(new["kernels"], old["kernels"], rtol=0, atol=TOLERANCE * scale)
    new_meta, old_meta = json.loads(str(new["metadata"])), json.loads(str(old["metadata"]))
    assert_numbers_equal(new_meta, old_meta, "metadata")


def test_demo_outputs_are_unchanged(tmp_path, capsys):
    out = tmp_path / "demo"
    assert main(["demo", "--out", str(out), "--downsample", "8", "--quiet"]) == 0
    capsys.readouterr()
    results = json.loads((out / "report" / "results.json").read_text())
    assert_numbers_equal(results, json.loads((GOLDEN / "demo_ds8_results.json").read_text()),
                         "results")
    assert_kernel_files_equal(out / "kernels.npz", GOLDEN / "demo_ds8_kernels.npz")


@pytest.mark.parametrize("model", ["si", "ek"])
def test_fit_pairs_and_eval_model_outputs_are_unchanged(tmp_path, real_data, model, capsys,
                                                        torch_one_thread):
    # One torch thread, as when the golden files were written: the float32 conjugate-gradient
    # fit stops after a fixed number of iterations, so the summation order of a multi-threaded
    # FFT changes its last digits (about 1e-3 relative on near-zero kernel pixels).
    pairs = real_data("dlmd_mirflickr")
    kernels = tmp_path / f"{model}.npz"
    assert main(["fit-pairs", str(pairs), "--model", model, "--downsample", "4",
                 "--out", str(kernels), "--quiet"]) == 0
    assert_kernel_files_equal(kernels, GOLDEN / f"dlmd_ds4_{model}.npz")
    errors = tmp_path / "errors.json"
    assert main(["eval-model", str(kernels), str(pairs), "--downsample", "4",
                 "--out", str(errors)]) == 0
    capsys.readouterr()
    assert_numbers_equal(json.loads(errors.read_text()),
                         json.loads((GOLDEN / f"dlmd_ds4_{model}_errors.json").read_text()),
                         "errors")
