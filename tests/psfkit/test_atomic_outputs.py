"""The output policy of psfkit.io.atomic: all-or-nothing commits, no silent replacement,
no-clobber renames, stale temporaries removed, error messages naming the user's path."""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

from psfkit.errors import InvalidInputError
from psfkit.io import atomic
from psfkit.io import temps as temp_names
from psfkit.io.atomic import (
    TEMP_TAG,
    OutputExistsError,
    OutputTransaction,
    atomic_directory,
    atomic_file,
    remove_stale_temps,
    rename_noreplace,
)


def temps(folder: Path) -> list[str]:
    return sorted(p.name for p in folder.rglob("*") if TEMP_TAG in p.name)


def owner(pid: int, host: str = temp_names.HOST) -> str:
    return f"{pid}@{host}"


def dead_pid() -> int:
    """The id of a process that has ended (and been reaped)."""
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def test_files_are_refused_without_overwrite_and_replaced_with_it(tmp_path):
    target = tmp_path / "k.json"
    with OutputTransaction() as out:
        out.file(target).write_text("first")
    assert target.read_text() == "first"
    with pytest.raises(OutputExistsError, match=r"k\.json: output file exists .*--overwrite"):
        with OutputTransaction() as out:
            out.file(target)
    with OutputTransaction(overwrite=True) as out:
        out.file(target).write_text("second")
    assert target.read_text() == "second"
    assert oct(target.stat().st_mode & 0o777) == oct(0o666 & ~atomic._UMASK)
    assert temps(tmp_path) == []


def test_folders_follow_the_same_policy(tmp_path):
    target = tmp_path / "rep"
    target.mkdir()   # an empty folder counts as absent
    with OutputTransaction() as out:
        (out.folder(target) / "a.txt").write_text("1")
    assert (target / "a.txt").read_text() == "1"
    with pytest.raises(OutputExistsError, match="not empty"):
        with OutputTransaction() as out:
            out.folder(target)
    with OutputTransaction(overwrite=True) as out:
        (out.folder(target) / "b.txt").write_text("2")
    assert sorted(p.name for p in target.iterdir()) == ["b.txt"]   # the old one is gone
    assert temps(tmp_path) == []


def test_wrong_kinds_are_refused_even_with_overwrite(tmp_path):
    (tmp_path / "dir").mkdir()
    (tmp_path / "file").write_text("x")
    with pytest.raises(InvalidInputError, match="is a directory"):
        OutputTransaction(overwrite=True).file(tmp_path / "dir")
    with pytest.raises(InvalidInputError, match="not a directory"):
        OutputTransaction(overwrite=True).folder(tmp_path / "file")
    with pytest.raises(InvalidInputError, match="not a directory"):
        OutputTransaction().file(tmp_path / "file" / "r.json")
    with pytest.raises(InvalidInputError, match="two outputs"):
        with OutputTransaction() as out:
            out.file(tmp_path / "same.npz")
            out.file(tmp_path / "same.npz")
    assert temps(tmp_path) == [] and not (tmp_path / "same.npz").exists()


def test_a_failure_leaves_nothing_not_even_the_parent_folders_it_made(tmp_path):
    with pytest.raises(RuntimeError):
        with OutputTransaction() as out:
            (out.folder(tmp_path / "new" / "deep" / "figs") / "f.png").write_text("x")
            out.file(tmp_path / "k.npz").write_text("y")
            assert len(temps(tmp_path)) == 2   # the folder and the kernel file
            raise RuntimeError("the fit failed")
    assert sorted(os.listdir(tmp_path)) == []


def test_a_bad_second_output_is_refused_before_any_work(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(InvalidInputError, match="not a directory"):
        with OutputTransaction() as out:
            out.folder(tmp_path / "figs")
            out.file(tmp_path / "file" / "k.npz")
    assert sorted(os.listdir(tmp_path)) == ["file"]


def test_commit_time_recheck_refuses_a_folder_created_meanwhile(tmp_path):
    kernels, figures = tmp_path / "k.npz", tmp_path / "figs"
    with pytest.raises(OutputExistsError, match="figs"):
        with OutputTransaction() as out:
            out.file(kernels).write_text("kernels")
            (out.folder(figures) / "fig.png").write_text("new")
            figures.mkdir()                               # another run, between start and
            (figures / "theirs.png").write_text("theirs")  # commit
    assert (figures / "theirs.png").read_text() == "theirs"
    assert sorted(p.name for p in figures.iterdir()) == ["theirs.png"]
    assert not kernels.exists()   # all or nothing
    assert temps(tmp_path) == []


def test_the_rename_itself_cannot_clobber(tmp_path, monkeypatch):
    # skip the re-check to reach the rename, as if the other run won the race after it
    monkeypatch.setattr(atomic, "check_output", lambda path, kind, overwrite: Path(path))
    file_target, folder_target = tmp_path / "r.json", tmp_path / "rep"
    with pytest.raises(OutputExistsError, match="created meanwhile"):
        with OutputTransaction() as out:
            out.file(file_target).write_text("ours")
            file_target.write_text("theirs")
    assert file_target.read_text() == "theirs"
    with pytest.raises(OutputExistsError, match="created meanwhile"):
        with OutputTransaction() as out:
            (out.folder(folder_target) / "a").write_text("ours")
            folder_target.mkdir()
            (folder_target / "b").write_text("theirs")
    assert sorted(os.listdir(folder_target)) == ["b"]
    assert temps(tmp_path) == []


@pytest.mark.parametrize("renameat2", [True, False])
def test_rename_noreplace_with_and_without_renameat2(tmp_path, monkeypatch, renameat2):
    if not renameat2:
        monkeypatch.setattr(atomic, "_renameat2", None)
    src, dst = tmp_path / "src", tmp_path / "dst"
    src.write_text("new")
    dst.write_text("old")
    with pytest.raises(FileExistsError):
        rename_noreplace(src, dst)
    assert dst.read_text() == "old" and src.read_text() == "new"
    dst.unlink()
    rename_noreplace(src, dst)
    assert dst.read_text() == "new" and not src.exists()


def test_a_failed_commit_rolls_back_replaced_outputs(tmp_path, monkeypatch):
    folder, file = tmp_path / "rep", tmp_path / "a.json"
    folder.mkdir()
    (folder / "old").write_text("old rep")
    file.write_text("old a")

    def failing(self):
        raise OSError(5, "Input/output error")   # e.g. the disk went away

    monkeypatch.setattr(atomic._Output, "_commit_file", failing)
    with pytest.raises(InvalidInputError, match=r"a\.json: cannot write here"):
        with OutputTransaction(overwrite=True) as out:
            (out.folder(folder) / "new").write_text("new rep")   # committed first ...
            out.file(file).write_text("new a")                  # ... then this one fails
    assert sorted(os.listdir(folder)) == ["old"]   # the replaced folder is back
    assert file.read_text() == "old a"
    assert temps(tmp_path) == []


def test_a_replaced_file_is_restored_when_a_later_output_fails(tmp_path, monkeypatch):
    file, folder = tmp_path / "a.json", tmp_path / "rep"
    file.write_text("old a")

    def failing(self):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(atomic._Output, "_commit_folder", failing)
    with pytest.raises(InvalidInputError, match="rep: cannot write here"):
        with OutputTransaction(overwrite=True) as out:
            out.file(file).write_text("new a")
            out.folder(folder)
    assert file.read_text() == "old a" and not folder.exists()
    assert temps(tmp_path) == []


def test_stale_temporaries_are_recognised_and_removed(tmp_path, capsys):
    pid = dead_pid()
    stale_file = tmp_path / f".k{TEMP_TAG}{owner(pid)}.abc123.npz"
    stale_dir = tmp_path / f".rep{TEMP_TAG}{owner(pid)}.def456"
    old_dir = tmp_path / f".figs{TEMP_TAG}{owner(1)}.ghi789"   # pid 1 lives, but 2 days old
    live = tmp_path / f".x{TEMP_TAG}{owner(os.getpid())}.jkl012"   # a run in progress
    elsewhere = tmp_path / f".y{TEMP_TAG}{owner(pid, 'abcdef')}.mno345"   # another machine
    stale_file.write_bytes(b"")
    (stale_dir / "figures").mkdir(parents=True)
    old_dir.mkdir()
    live.mkdir()
    elsewhere.mkdir()
    two_days_ago = time.time() - 2 * 86400
    os.utime(old_dir, (two_days_ago, two_days_ago))
    (tmp_path / "user.npz").write_bytes(b"")                # not ours: kept
    removed = remove_stale_temps(tmp_path)
    assert sorted(p.name for p in removed) == sorted([stale_file.name, stale_dir.name,
                                                      old_dir.name])
    assert sorted(os.listdir(tmp_path)) == sorted([live.name, elsewhere.name, "user.npz"])
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "removed 3 stale temporary output(s)" in err[0]


def test_a_new_output_cleans_its_folder_first(tmp_path, monkeypatch, capsys):
    monkeypatch.setattr(temp_names, "_CLEANED", set())
    stale = tmp_path / f".k{TEMP_TAG}{owner(dead_pid())}.abc123.npz"
    stale.write_bytes(b"")
    with atomic_file(tmp_path / "k.npz") as tmp:
        tmp.write_text("ok")
    assert sorted(os.listdir(tmp_path)) == ["k.npz"]
    assert "stale" in capsys.readouterr().err


def test_unwritable_outputs_are_named_by_the_users_path(tmp_path, monkeypatch):
    def refuse(*args, dir=None, **kwargs):
        raise PermissionError(13, "Permission denied",
                              str(Path(dir) / f".k{TEMP_TAG}{owner(123)}.xyz.npz"))

    monkeypatch.setattr(tempfile, "mkstemp", refuse)
    with pytest.raises(InvalidInputError) as info:
        OutputTransaction().file(tmp_path / "k.npz")
    assert str(info.value) == f"{tmp_path / 'k.npz'}: cannot write here (Permission denied)"


def test_write_errors_inside_a_temporary_name_the_users_path(tmp_path):
    target = tmp_path / "rep"
    with pytest.raises(InvalidInputError) as info:
        with OutputTransaction() as out:
            folder = out.folder(target)
            raise OSError(28, "No space left on device", str(folder / "figures" / "a.png"))
    assert str(info.value) == f"{target}: cannot write here (No space left on device)"
    assert temps(tmp_path) == []


def test_single_output_helpers_keep_their_defaults(tmp_path):
    target = tmp_path / "log.csv"
    for text in ("1", "2"):   # library files rewritten in place (a log every epoch)
        with atomic_file(target) as tmp:
            assert tmp.suffix == ".csv" and TEMP_TAG in tmp.name
            tmp.write_text(text)
    assert target.read_text() == "2"
    with pytest.raises(OutputExistsError):
        with atomic_file(target, overwrite=False):
            pass
    with atomic_directory(tmp_path / "d") as tmp:
        (tmp / "x").write_text("x")
    with pytest.raises(OutputExistsError):
        with atomic_directory(tmp_path / "d"):
            pass
    assert temps(tmp_path) == []


def test_write_json_is_plain_json_and_all_or_nothing(tmp_path):
    import json
    import math

    import numpy as np

    from psfkit.io.jsonable import write_json

    target = tmp_path / "results.json"
    write_json(target, {"psnr": np.float32(24.5), "ncc": math.nan, "shape": (2, 3)})
    assert json.loads(target.read_text(encoding="utf-8")) == {"psnr": 24.5, "ncc": None,
                                                              "shape": [2, 3]}
    before = target.read_text(encoding="utf-8")
    with pytest.raises(TypeError):       # not JSON: the earlier file stays whole
        write_json(target, {"runs": [object()]})
    assert target.read_text(encoding="utf-8") == before
    assert temps(tmp_path) == []
