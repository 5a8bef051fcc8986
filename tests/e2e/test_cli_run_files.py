"""The psfkit CLI sized for its users (issue 44, item 4): short ``--help``, ``--help-all``,
``--config RUN.toml`` run files.

- every psfkit command's ``--help`` shows at most 12 flags (-h, --help, --help-all aside), 50
  in all, and ``--help-all`` lists every flag the command takes; each help line speaks of its
  own command only;
- a setting from a run file gives the same kernel file / grid as the same flag on the command
  line, it is recorded with the outputs, and the command line overrides the file;
- a bad run file is one line on stderr naming the file (and the key), status 2, and nothing
  is written.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np
import pytest

from psfkit.cli import main
from psfkit.cli.help_all import is_advanced
from psfkit.cli.main import build_parser

pytestmark = pytest.mark.e2e


def _commands() -> dict[str, argparse.ArgumentParser]:
    """The psfkit commands that ``psfkit --help`` lists."""
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    listed = {choice.dest for choice in sub._choices_actions}
    return {name: parser for name, parser in sub.choices.items() if name in listed}


def _help(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as done:
        build_parser().parse_args(list(argv))
    assert done.value.code == 0
    return capsys.readouterr().out


def _flags(help_text: str) -> list[str]:
    """The flags of a help screen (first option of each line), -h and --help-all aside."""
    return [f for f in re.findall(r"^ {2}(-[-\w]+)", help_text, flags=re.M)
            if f not in ("-h", "--help-all")]


def test_every_command_shows_at_most_12_flags_and_help_all_every_one(capsys):
    commands = _commands()
    assert len(commands) == 7              # psfkit's (compare left for research/, issue 44)
    total = 0
    for name, parser in commands.items():
        short = _help(capsys, name, "--help")
        shown = _flags(short)
        total += len(shown)
        assert len(shown) <= 12, (name, shown)
        every = {a.option_strings[0] for a in parser._actions
                 if a.option_strings and a.option_strings[0] not in ("-h", "--help-all")
                 and (a.help != argparse.SUPPRESS or is_advanced(a))}
        advanced = {a.option_strings[0] for a in parser._actions if is_advanced(a)}
        assert set(shown) == every - advanced, name
        usage = short[:short.index("\n\n")]
        assert not any(re.search(rf"\[{re.escape(f)}\b", usage) for f in advanced), name
        # the description points to --help-all exactly where there is more to see
        assert ("--help-all lists the advanced flags" in parser.description) == bool(advanced)
        if advanced:   # --help-all lists every flag, the advanced ones under their groups
            assert set(_flags(_help(capsys, name, "--help-all"))) == every, name
            assert "--help-all" in short
    assert total <= 50, total


def test_each_help_line_describes_its_own_command(capsys):
    report = _help(capsys, "report", "--help-all")
    threads = report[report.index("--threads"):].split("\n  -")[0]
    assert "ekdun" not in threads and "make-dataset" not in threads
    pairs = _help(capsys, "fit-pairs", "--help")
    basis = pairs[pairs.index("--basis BASIS  "):].split("\n  -")[0]
    listed = re.search(r"one of ([^)]*)\)", " ".join(basis.split())).group(1)
    names = [n.strip() for n in listed.split(",")]
    assert names.count("si") == 1 and "fit-eigen" not in basis and "auto" not in names
    holdout = pairs[pairs.index("--holdout"):].split("\n  -")[0]
    assert "eval-model: the pairs" not in " ".join(holdout.split())
    eigen = _help(capsys, "fit-eigen", "--help")
    basis = " ".join(eigen[eigen.index("--basis BASIS  "):].split("\n  -")[0].split())
    assert "fit-pairs" not in basis and "auto" in basis
    # no shared flag's help explains what it means in another command
    from ekdun.cli.vocabulary import VOCABULARY  # psfkit's, extended by ekdun's
    from tests.helpers.cli import full_help

    elsewhere = re.compile(r"\b(fit-eigen|fit-pairs|eval-model|make-dataset|train)( only|:)|"
                           r"\bekdun\b|\(psfkit\)")
    for name, parser in _commands().items():
        for action in parser._actions:
            if set(action.option_strings) & set(VOCABULARY) and full_help(action):
                assert not elsewhere.search(full_help(action)), (name, full_help(action))


def _write(path: Path, text: str) -> Path:
    path.write_text(text, encoding="utf-8")
    return path


def _kernels(path: Path) -> np.ndarray:
    with np.load(path) as data:
        return np.array(data["kernels"])


def _provenance(path: Path) -> dict:
    from psfkit.forward.kernelfile import load_kernels

    return load_kernels(path).provenance


FIT_PAIRS_QUICK = ["--iterations", "20", "--projected-iterations", "5", "--quiet"]


def test_fit_pairs_settings_from_a_run_file_are_the_flags_and_are_recorded(tiny_data,
                                                                           tmp_path):
    pairs, _ = tiny_data
    run = _write(tmp_path / "run.toml", 'tikhonov = 0.01\nno_scale = true\nnonneg = false\n'
                                        'holdout = ["im0"]\n')
    flags, config, plain = (tmp_path / f"{n}.npz" for n in ("flags", "config", "plain"))
    assert main(["fit-pairs", str(pairs), "--out", str(flags), "--tikhonov", "0.01",
                 "--no-scale", "--no-nonneg", "--holdout", "im0", *FIT_PAIRS_QUICK]) == 0
    assert main(["fit-pairs", str(pairs), "--out", str(config), "--config", str(run),
                 *FIT_PAIRS_QUICK]) == 0
    assert main(["fit-pairs", str(pairs), "--out", str(plain), *FIT_PAIRS_QUICK]) == 0
    # the file's settings are the flags': the same numbers, and not the defaults' numbers
    assert np.array_equal(_kernels(config), _kernels(flags))
    assert not np.allclose(_kernels(config), _kernels(plain))
    recorded = _provenance(config)
    assert recorded["options"] == _provenance(flags)["options"]
    assert recorded["options"]["tikhonov"] == 0.01 and recorded["options"]["nonneg"] is False
    assert recorded["holdout"] == ["im0"]
    assert recorded["run_file"] == {
        "path": str(run.resolve()), "overridden": [],
        "settings": {"--tikhonov": 0.01, "--no-scale": True, "--nonneg": False,
                     "--holdout": ["im0"]}}
    assert "run_file" not in _provenance(flags)


def test_the_command_line_overrides_the_run_file(tiny_data, tmp_path):
    pairs, _ = tiny_data
    run = _write(tmp_path / "run.toml", "tikhonov = 0.01\nno-scale = true\n")
    out = tmp_path / "k.npz"
    assert main(["fit-pairs", str(pairs), "--out", str(out), "--config", str(run),
                 "--tikhonov=0.1", *FIT_PAIRS_QUICK]) == 0
    recorded = _provenance(out)
    assert recorded["options"]["tikhonov"] == 0.1 and recorded["options"]["fit_scale"] is False
    assert recorded["run_file"]["settings"] == {"--no-scale": True}
    assert recorded["run_file"]["overridden"] == ["--tikhonov"]
    # a repeatable flag given on the command line replaces the file's list
    from psfkit.cli.run_file import parse_args

    run = _write(tmp_path / "holdout.toml", 'holdout = ["im0", "im1"]\n')

    args = parse_args(build_parser(), ["fit-pairs", "P", "--out", "k.npz", "--config",
                                       str(run), "--holdout", "im2"])
    assert args.holdout == ["im2"] and args.run_file["overridden"] == ["--holdout"]


def test_ekdun_train_run_file_is_the_flags_and_is_in_the_checkpoint(tiny_data, tmp_path):
    """``ekdun train --config``: the file's settings train exactly as the same flags (same
    losses, same weights) and the checkpoint's metadata records them."""
    import torch

    from ekdun.cli import main as ekdun_main
    from ekdun.nets.checkpoint import load_checkpoint

    pairs, kernels = tiny_data
    run_file = _write(tmp_path / "train.toml", "lr = 0.005\nbatch-size = 4\niterations = 2\n")
    common = [str(pairs), "--kernels", str(kernels), "--epochs", "1", "--threads", "1",
              "--device", "cpu", "--quiet"]
    assert ekdun_main(["train", common[0], str(tmp_path / "flags"), *common[1:], "--lr",
                       "0.005", "--batch-size", "4", "--iterations", "2"]) == 0
    assert ekdun_main(["train", common[0], str(tmp_path / "config"), *common[1:], "--config",
                       str(run_file)]) == 0
    flags = load_checkpoint(tmp_path / "flags" / "checkpoint.pt")
    config = load_checkpoint(tmp_path / "config" / "checkpoint.pt")
    assert config["metadata"]["run_file"] == {
        "path": str(run_file.resolve()), "overridden": [],
        "settings": {"--lr": 0.005, "--batch-size": 4, "--iterations": 2}}
    assert "run_file" not in flags["metadata"]
    assert config["metadata"]["training"] == flags["metadata"]["training"]
    assert config["metadata"]["history"][0]["train_loss"] == \
        flags["metadata"]["history"][0]["train_loss"]
    for name, tensor in flags["model"].items():
        assert torch.equal(tensor, config["model"][name]), name


def test_fit_eigen_run_file(grid_3x3, tmp_path):
    run = _write(tmp_path / "run.toml", 'folds = 3\ncv-bases = "none"\n'
                                        'shifts = "registered"\nout = "ignored.npz"\n')
    flags, config = tmp_path / "flags.npz", tmp_path / "config.npz"
    assert main(["fit-eigen", str(grid_3x3), "--out", str(flags), "--folds", "3",
                 "--cv-bases", "none", "--shifts", "registered", "--quiet"]) == 0
    # --out from the command line wins over the file's
    assert main(["fit-eigen", str(grid_3x3), "--config", str(run), "--out", str(config),
                 "--quiet"]) == 0
    assert not (tmp_path / "ignored.npz").exists()
    assert np.array_equal(_kernels(config), _kernels(flags))
    recorded = _provenance(config)["run_file"]
    assert recorded == {"path": str(run.resolve()), "overridden": ["--out"],
                        "settings": {"--folds": 3, "--cv-bases": "none",
                                     "--shifts": "registered"}}
    # the record changes no number, and older readers see one more provenance key only
    with np.load(config) as data:
        meta = json.loads(str(data["metadata"]))
    assert set(meta) == set(json.loads(str(np.load(flags)["metadata"])))


def test_simulate_grid_run_file_is_the_flags_and_is_in_the_manifest(tmp_path):
    run = _write(tmp_path / "bench.toml", 'rows = 2\ncols = 2\ndownsample = 16\n'
                                          'format = "npy"\nno-dark = true\nbackend = "numpy"\n'
                                          "gap_mm = 12.0\nout = \"" +
                 str(tmp_path / "config").replace("\\", "\\\\") + '"\n')
    assert main(["simulate-grid", "--out", str(tmp_path / "flags"), "--rows", "2", "--cols",
                 "2", "--downsample", "16", "--format", "npy", "--no-dark", "--backend",
                 "numpy", "--gap-mm", "12", "--quiet"]) == 0
    assert main(["simulate-grid", "--config", str(run), "--quiet"]) == 0
    a, b = tmp_path / "flags", tmp_path / "config"
    files = sorted(p.name for p in a.glob("*.npy"))
    assert len(files) == 4 and files == sorted(p.name for p in b.glob("*.npy"))
    for name in files:
        assert np.array_equal(np.load(a / name), np.load(b / name))
    manifest = json.loads((b / "manifest.json").read_text())
    recorded = manifest["simulation"]["run_file"]
    assert recorded["path"] == str(run.resolve())
    assert recorded["settings"]["--gap-mm"] == 12.0 and recorded["settings"]["--no-dark"]
    assert "run_file" not in json.loads((a / "manifest.json").read_text())["simulation"]
    from psfkit.io import read_grid

    assert read_grid(b).grid_shape == (2, 2)   # the grid reads as before


def test_demo_takes_a_run_file(tmp_path):
    from psfkit.cli.run_file import parse_args

    run = _write(tmp_path / "demo.toml", "seed = 3\npeak-fraction = 0.5\nmono = true\n")
    args = parse_args(build_parser(), ["demo", "--config", str(run)])
    assert (args.seed, args.peak_fraction, args.mono) == (3, 0.5, True)
    assert args.run_file["settings"] == {"--seed": 3, "--peak-fraction": 0.5, "--mono": True}


BAD_RUN_FILES = [
    ("unknown.toml", "tikhonv = 0.1\n", "unknown key 'tikhonv'"),
    ("positional.toml", 'pairs = "x"\n', "key 'pairs' is an argument"),
    ("value.toml", 'tikhonov = "much"\n', "key 'tikhonov': argument --tikhonov"),
    ("range.toml", "iterations = -4\n", "key 'iterations': argument --iterations"),
    ("choice.toml", 'convention = "both"\n', "key 'convention': argument --convention"),
    ("switch.toml", 'no-scale = "yes"\n', "key 'no-scale' is a switch"),
    ("boolean.toml", "tikhonov = true\n", "key 'tikhonov' takes a value"),
    ("table.toml", "[solver]\ntikhonov = 0.1\n", "key 'solver' is a table"),
    ("twice.toml", "no-scale = true\nno_scale = true\n", "set the same flag"),
    ("nested.toml", 'config = "other.toml"\n', "unknown key 'config'"),
    ("help.toml", "help = true\n", "unknown key 'help'"),
    ("alias.toml", 'model = "ek"\n', "unknown key 'model'"),
    ("malformed.toml", "tikhonov = [\n", "not valid TOML"),
    ("binary.toml", None, "not TOML"),
    ("missing.toml", "", "cannot read the run file"),
    ("deep.toml", "a = " + "[" * 100_000 + "]" * 100_000 + "\n", "nested too deeply"),
    ("huge.toml", "#" * (1 << 20) + "\n", "larger than"),
]


@pytest.mark.parametrize(("name", "text", "says"), BAD_RUN_FILES,
                         ids=[n.split(".")[0] for n, _, _ in BAD_RUN_FILES])
def test_a_bad_run_file_is_one_line_and_writes_nothing(tmp_path, capsys, name, text, says):
    path = tmp_path / name
    if text is None:
        path.write_bytes(b"\xff\xfe\x00tikhonov")
    elif name != "missing.toml":
        path.write_text(text, encoding="utf-8")
    out = tmp_path / "k.npz"
    assert main(["fit-pairs", str(tmp_path), "--out", str(out), "--config", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith(f"psfkit: error: {path}: ") and says in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ([name] if path.exists() else [])


def test_a_run_file_folder_is_one_line(tmp_path, capsys):
    assert main(["simulate-grid", "--config", str(tmp_path), "--out",
                 str(tmp_path / "g")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path) in err[0] and "run file" in err[0], err
    assert not (tmp_path / "g").exists()
