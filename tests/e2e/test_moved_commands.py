"""Commands that left the user CLI for research/ (issue 44): hidden from ``--help``,
their old spelling is one line naming the replacement, status 2, nothing written; the
replacement runs from the repository root."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from ekdun.cli import main

REPO = Path(__file__).resolve().parents[2]


@pytest.mark.parametrize(("argv", "replacement"), [
    (["oracle", "DATA", "--out", "o.npz", "--kind", "psf"], "python -m research.oracle"),
    (["benchmark-tiny", "OUT", "--epochs", "1"], "python -m research.benchmark_tiny"),
    (["benchmark-tiny", "--help"], "python -m research.benchmark_tiny"),
])
def test_removed_command_says_where_it_went(argv, replacement, tmp_path, capsys,
                                            monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and replacement in lines[0] and "docs/migration.md" in lines[0]
    assert lines[0].startswith(f"ekdun: error: `ekdun {argv[0]}`")
    assert captured.out == "" and list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(("flag", "value", "module"), [
    ("--kernel-param", "flow", "research/kernel_models.py"),
    ("--physics-weight", "1", "research/physics_loss.py"),
])
def test_removed_train_flags_say_where_they_went(flag, value, module, tmp_path, capsys):
    argv = ["train", str(tmp_path / "data"), str(tmp_path / "run"), "--kernels",
            str(tmp_path / "k.npz"), flag, value]
    assert main(argv) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and flag in lines[0] and module in lines[0], captured.err
    assert captured.out == "" and list(tmp_path.iterdir()) == []
    assert main(["train", "--help"]) == 0
    assert flag not in capsys.readouterr().out


def test_removed_commands_are_not_listed(capsys):
    assert main(["--help"]) == 0
    listed = capsys.readouterr().out
    assert "oracle" not in listed and "benchmark-tiny" not in listed
    assert "reconstruct" in listed and "train" in listed      # the user commands are


def test_the_replacements_run_from_the_repository(tmp_path):
    # the same one-line refusal as a product command for a folder that is not a dataset
    for module, args in (("research.oracle", [str(tmp_path), "--out", str(tmp_path / "o.npz")]),
                         ("research.benchmark_tiny", ["--help"])):
        done = subprocess.run([sys.executable, "-m", module, *args], cwd=REPO,
                              capture_output=True, text=True, timeout=120, check=False)
        if args == ["--help"]:
            assert done.returncode == 0 and "--n-train" in done.stdout
        else:
            assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1
            assert "not a virtual-bench dataset" in done.stderr
    assert not (tmp_path / "o.npz").exists()


def test_psfkit_compare_says_where_it_went(tmp_path, capsys, monkeypatch):
    """``psfkit compare`` (the paper's Fig. 7 study) moved to ``python -m research.compare``."""
    from psfkit.cli import main as psfkit_main

    monkeypatch.chdir(tmp_path)
    assert psfkit_main(["compare", "learned.npz", "GRID", "--out", "cmp"]) == 2
    captured = capsys.readouterr()
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "python -m research.compare" in lines[0], captured.err
    assert lines[0].startswith("psfkit: error: `psfkit compare`")
    assert captured.out == "" and list(tmp_path.iterdir()) == []
    assert psfkit_main(["--help"]) == 0
    assert "compare" not in capsys.readouterr().out
    done = subprocess.run([sys.executable, "-m", "research.compare", str(tmp_path / "a.npz"),
                           str(tmp_path / "b.npz"), "--out", str(tmp_path / "cmp")], cwd=REPO,
                          capture_output=True, text=True, timeout=120, check=False)
    assert done.returncode == 2 and len(done.stderr.strip().splitlines()) == 1, done.stderr
    assert "a.npz" in done.stderr and not (tmp_path / "cmp").exists()
