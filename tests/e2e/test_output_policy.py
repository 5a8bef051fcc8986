"""The output policy through the real commands: no silent replacement, all-or-nothing
outputs, stale temporaries removed, and the kill test (SIGKILL / SIGTERM while writing)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ekdun.cli import main as ekdun_main
from psfkit.cli import main
from psfkit.forward.kernelfile import load_kernels
from psfkit.io.atomic import TEMP_TAG
from psfkit.io.temps import HOST

FAST_FIT = ["--cv-bases", "none", "--quiet"]
PSFKIT = [str(Path(sys.executable).parent / "psfkit")]   # the installed console script


def temps(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*") if TEMP_TAG in p.name)


def one_error_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "Traceback" not in err[0]
    return err[0]


# ---------------------------------------------------------------- no silent replacement

def test_fit_eigen_refuses_an_existing_kernel_file_unless_overwrite(grid_3x3, tmp_path, capsys):
    out = tmp_path / "k.npz"
    out.write_bytes(b"precious")
    assert main(["fit-eigen", str(grid_3x3), "--out", str(out), *FAST_FIT]) == 2
    assert "k.npz: output file exists (use --overwrite" in one_error_line(capsys)
    assert out.read_bytes() == b"precious"
    assert main(["fit-eigen", str(grid_3x3), "--out", str(out), "--overwrite", *FAST_FIT]) == 0
    assert load_kernels(out).kernel_names == ("base", "v", "h")
    assert temps(tmp_path) == []


@pytest.mark.parametrize("command", ["register", "mae"])
def test_numbers_files_refused_unless_overwrite(grid_3x3, tmp_path, capsys, command):
    out = tmp_path / "numbers.json"
    out.write_text("{}")
    assert main([command, str(grid_3x3), "--out", str(out), "--quiet"]) == 2
    assert "numbers.json: output file exists" in one_error_line(capsys)
    assert out.read_text() == "{}"
    assert main([command, str(grid_3x3), "--out", str(out), "--quiet", "--overwrite"]) == 0
    assert '"positions"' in out.read_text()


def test_report_folder_refused_unless_overwrite_then_replaced(grid_3x3, tmp_path, capsys):
    out = tmp_path / "rep"
    out.mkdir()
    (out / "old.txt").write_text("old")
    assert main(["report", str(grid_3x3), "--out", str(out), "--quiet"]) == 2
    assert "not empty" in one_error_line(capsys)
    assert main(["report", str(grid_3x3), "--out", str(out), "--quiet", "--overwrite"]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["figures", "positions.csv",
                                                     "report.html", "results.json"]
    assert temps(tmp_path) == []


def test_two_concurrent_reports_to_one_folder_one_wins(grid_3x3, tmp_path):
    out = tmp_path / "rep"
    argv = [*PSFKIT, "report", str(grid_3x3), "--out", str(out), "--quiet"]
    procs = [subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    results = [(p.wait(timeout=600), p.stderr.read()) for p in procs]
    assert sorted(rc for rc, _ in results) == [0, 2], results
    loser = next(err for rc, err in results if rc == 2).strip().splitlines()
    assert len(loser) == 1 and str(out) in loser[0] and "--overwrite" in loser[0]
    assert sorted(p.name for p in out.iterdir()) == ["figures", "positions.csv",
                                                     "report.html", "results.json"]
    assert temps(tmp_path) == []


def test_eval_model_out_refused_unless_overwrite(tiny_data, tmp_path, capsys):
    pairs, kernels = tiny_data
    out = tmp_path / "errors.json"
    out.write_text("mine")
    assert main(["eval-model", str(kernels), str(pairs), "--out", str(out)]) == 2
    assert "errors.json: output file exists" in one_error_line(capsys)
    assert out.read_text() == "mine"


@pytest.mark.parametrize("argv, existing", [
    (["export-kernels", "{ck}", "--out", "{dir}/k.npz"], "k.npz"),
    (["admm", "{psf}", "{psf}", "--out", "{dir}/x.npy"], "x.npy"),
    (["admm", "{psf}", "{psf}", "--out", "{dir}/y.npy"], "y.png"),   # the preview counts too
    (["eval", "{ck}", "--data", "{dir}", "--out", "{dir}/tables"], "tables/table1.md"),
])
def test_ekdun_outputs_refused_before_any_work(tmp_path, capsys, argv, existing):
    # the inputs do not even exist: the output is refused first, before anything is read
    target = tmp_path / existing
    target.parent.mkdir(exist_ok=True)
    target.write_text("mine")
    args = [a.format(ck=tmp_path / "absent.pt", psf=tmp_path / "absent.png", dir=tmp_path)
            for a in argv]
    assert ekdun_main(args) == 2
    assert "(use --overwrite to replace it)" in one_error_line(capsys)
    assert target.read_text() == "mine" and temps(tmp_path) == []


# ---------------------------------------------------------------- all or nothing

def test_fit_eigen_bad_out_leaves_no_figures(grid_3x3, tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    figures = tmp_path / "figs"
    assert main(["fit-eigen", str(grid_3x3), "--figures", str(figures),
                 "--out", str(tmp_path / "afile" / "k.npz"), *FAST_FIT]) == 2
    assert "afile" in one_error_line(capsys)
    assert sorted(os.listdir(tmp_path)) == ["afile"]


def test_fit_pairs_bad_report_leaves_no_kernel_file(tiny_data, tmp_path, capsys):
    pairs, _ = tiny_data
    (tmp_path / "afile").write_text("x")
    out = tmp_path / "k.npz"
    assert main(["fit-pairs", str(pairs), "--out", str(out), "--iterations", "3",
                 "--report", str(tmp_path / "afile" / "r.json"), "--quiet"]) == 2
    assert "r.json" in one_error_line(capsys)
    assert sorted(os.listdir(tmp_path)) == ["afile"]


def test_fit_pairs_writes_both_outputs_together(tiny_data, tmp_path, capsys):
    pairs, _ = tiny_data
    out, report = tmp_path / "k.npz", tmp_path / "sub" / "r.json"
    assert main(["fit-pairs", str(pairs), "--out", str(out), "--iterations", "3",
                 "--report", str(report), "--quiet"]) == 0
    assert load_kernels(out).basis == "si" and report.is_file()
    assert temps(tmp_path) == []


def test_train_with_a_bad_batch_size_writes_nothing(tiny_data, tmp_path, capsys):
    pairs, kernels = tiny_data
    run_dir = tmp_path / "run"
    assert ekdun_main(["train", str(pairs), str(run_dir), "--kernels", str(kernels),
                       "--batch-size", "-2", "--epochs", "1", "--quiet"]) == 2
    assert "--batch-size" in one_error_line(capsys)
    assert not run_dir.exists()   # no kernels_initial.npz either


def test_a_stale_temporary_is_removed_by_the_next_run(grid_3x3, tmp_path, capsys):
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    stale = tmp_path / f".rep{TEMP_TAG}{proc.pid}@{HOST}.abcd1234"
    (stale / "figures").mkdir(parents=True)
    (stale / "figures" / "half.png").write_bytes(b"\x89PNG")
    assert main(["register", str(grid_3x3), "--out", str(tmp_path / "r.json"),
                 "--quiet"]) == 0
    assert temps(tmp_path) == []
    err = capsys.readouterr().err
    assert f"removed 1 stale temporary output(s) of interrupted runs in {tmp_path}" in err


# ---------------------------------------------------------------- the kill test

def _writing_started(folder: Path) -> bool:
    """A file exists inside one of the run's temporary folders: it is writing outputs."""
    return any(p.is_file() for t in folder.iterdir() if TEMP_TAG in t.name and t.is_dir()
               for p in t.rglob("*"))


def _run_and_kill(argv: list[str], folder: Path, sig: int) -> subprocess.CompletedProcess:
    proc = subprocess.Popen([*PSFKIT, *argv],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 300
    while not _writing_started(folder):
        assert proc.poll() is None, f"finished before it could be killed: {proc.stderr.read()}"
        assert time.monotonic() < deadline, "no temporary output appeared"
        time.sleep(0.005)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=120)   # also reaps it: its pid is then dead
    return subprocess.CompletedProcess(argv, proc.returncode, out, err)


KILLED = {
    "report": (["report", "{grid}", "--out", "{dir}/rep", "--quiet"], ["rep"]),
    "fit-eigen": (["fit-eigen", "{grid}", "--figures", "{dir}/figs", "--out", "{dir}/k.npz",
                   "--quiet"], ["figs", "k.npz"]),
}


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGKILL], ids=["SIGTERM", "SIGKILL"])
@pytest.mark.parametrize("command", list(KILLED))
def test_killed_while_writing_leaves_no_partial_output(grid_3x3, tmp_path, command, sig):
    template, finals = KILLED[command]
    argv = [a.format(grid=grid_3x3, dir=tmp_path) for a in template]
    killed = _run_and_kill(argv, tmp_path, sig)
    assert not any((tmp_path / name).exists() for name in finals)   # nothing partial appears
    if sig == signal.SIGTERM:
        assert killed.returncode == 128 + signal.SIGTERM
        assert killed.stderr.strip() == ("psfkit: interrupted (SIGTERM); unfinished outputs "
                                         "removed")
        assert "Traceback" not in killed.stderr
        assert temps(tmp_path) == []                # cleaned up on the way out
    else:
        assert killed.returncode == -signal.SIGKILL
        assert temps(tmp_path) != []                # cannot clean up: the next run will
    again = subprocess.run([*PSFKIT, *argv],
                           capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    assert temps(tmp_path) == []
    assert all((tmp_path / name).exists() for name in finals)
    if sig == signal.SIGKILL:
        assert "stale temporary output(s) of interrupted runs" in again.stderr
