"""Training: loss decreases, resume equals an uninterrupted run, DDP equals one process,
checkpoints never execute code, learned kernels export as psfkit kernel files."""

from __future__ import annotations

import os
import pickle
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from ekdun.cli import main as ekdun_main
from ekdun.data.pairs import PairsDataset
from ekdun.errors import CheckpointError
from ekdun.nets import build_model
from ekdun.nets.builder import (
    build_network,
    decode_overrides,
    encode_overrides,
    network_from_checkpoint,
)
from ekdun.nets.checkpoint import save_checkpoint
from ekdun.training import (
    TrainOptions,
    export_kernels,
    initial_kernels,
    load_checkpoint,
    train,
)
from psfkit.errors import ModelFileError, PsfkitError
from psfkit.forward.kernelfile import KernelModel, load_kernels, save_kernels

SENSOR = (16, 16)
SMALL = {"iterations": 2, "prior": {"widths": [4, 8]}}


def _options(epochs: int) -> TrainOptions:
    return TrainOptions(epochs=epochs, batch_size=4, lr=1e-3, progress=False, threads=1)


def test_training_reduces_loss_and_writes_the_run_folder(tiny_data, tmp_path):
    pairs, kernels = tiny_data
    result = train(tmp_path / "run", "ekdun", kernels, PairsDataset(pairs), "tiny", SMALL,
                   _options(4))
    losses = [h["train_loss"] for h in result["history"]]
    assert losses[-1] < losses[0]
    run = tmp_path / "run"
    assert {"checkpoint.pt", "log.csv", "kernels_initial.npz", "kernels_learned.npz"} <= {
        p.name for p in run.iterdir()}
    assert len((run / "log.csv").read_text().strip().splitlines()) == 5
    initial, learned = load_kernels(run / "kernels_initial.npz"), load_kernels(
        run / "kernels_learned.npz")
    assert learned.basis == initial.basis == "paper" and learned.sensor_shape == SENSOR
    assert learned.convention == initial.convention
    assert not np.array_equal(learned.kernels, initial.kernels)
    np.testing.assert_array_equal(initial.kernels, load_kernels(kernels).kernels)
    # export from the checkpoint (library and CLI) equals the run's kernels_learned.npz
    np.testing.assert_array_equal(export_kernels(run / "checkpoint.pt").kernels,
                                  learned.kernels)
    seed = initial_kernels(run / "checkpoint.pt")     # = kernels_initial.npz
    np.testing.assert_array_equal(seed.kernels, initial.kernels)
    assert seed.basis == "paper" and seed.sensor_shape == SENSOR
    assert ekdun_main(["export-kernels", str(run / "checkpoint.pt"), "--out",
                       str(tmp_path / "learned.npz")]) == 0
    np.testing.assert_array_equal(load_kernels(tmp_path / "learned.npz").kernels,
                                  learned.kernels)
    # a second run into the same folder must be explicit
    with pytest.raises(Exception, match="--resume"):
        train(run, "ekdun", kernels, PairsDataset(pairs), "tiny", SMALL, _options(4))


def test_resume_equals_an_uninterrupted_run(tiny_data, tmp_path):
    pairs, kernels = tiny_data
    data = PairsDataset(pairs)
    straight = train(tmp_path / "a", "ekdun", kernels, data, "tiny", SMALL, _options(4))
    train(tmp_path / "b", "ekdun", kernels, data, "tiny", SMALL, _options(2))
    # "killed" after epoch 2; something else disturbs the global RNGs meanwhile
    torch.manual_seed(123)
    np.random.seed(7)  # noqa: NPY002
    resumed = train(tmp_path / "b", "ekdun", kernels, data, "tiny", SMALL, _options(4),
                    resume=True)
    assert [h["epoch"] for h in resumed["history"]] == [1, 2, 3, 4]
    for (name, p), q in zip(straight["model"].state_dict().items(),
                            resumed["model"].state_dict().values(), strict=True):
        torch.testing.assert_close(p, q, rtol=0, atol=1e-6, msg=name)
    a = load_checkpoint(tmp_path / "a" / "checkpoint.pt")
    b = load_checkpoint(tmp_path / "b" / "checkpoint.pt")
    assert [h["train_loss"] for h in a["metadata"]["history"]] == pytest.approx(
        [h["train_loss"] for h in b["metadata"]["history"]], rel=1e-6)
    assert a["scheduler"]["last_epoch"] == b["scheduler"]["last_epoch"] == 4


def test_resume_of_a_copied_checkpoint_restores_the_seed_file(tiny_data, tmp_path):
    """A run folder brought back with its checkpoint alone (from a GPU machine) resumes, and
    its kernels_initial.npz is the run's own seed, also when this call names another file."""
    pairs, kernels = tiny_data
    data = PairsDataset(pairs)
    run = tmp_path / "run"
    train(run, "ekdun", kernels, data, "tiny", SMALL, _options(1))
    first = load_kernels(run / "kernels_initial.npz")
    for name in ("kernels_initial.npz", "kernels_learned.npz", "log.csv"):
        (run / name).unlink()
    other = tmp_path / "other.npz"
    model = load_kernels(kernels)
    save_kernels(other, replace(model, kernels=model.kernels * 1.5))
    train(run, "ekdun", other, data, "tiny", SMALL, _options(2), resume=True)
    np.testing.assert_array_equal(load_kernels(run / "kernels_initial.npz").kernels,
                                  first.kernels)
    np.testing.assert_array_equal(initial_kernels(run / "checkpoint.pt").kernels,
                                  first.kernels)
    assert (run / "kernels_learned.npz").is_file()


def test_ddp_two_processes_equal_one_process(tiny_data, tmp_path):
    # (a study's extra loss under DDP: tests/research/test_physics_loss.py)
    pairs, kernels = tiny_data
    common = [str(pairs), "--kernels", str(kernels), "--iterations", "2", "--epochs", "2",
              "--batch-size", "4", "--lr", "1e-3", "--threads", "1", "--quiet",
              "--device", "cpu"]
    # a rank that aborts leaves its Python stack in its log (faulthandler)
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONFAULTHANDLER": "1"}
    one = subprocess.run([sys.executable, "-m", "ekdun.cli", "train", *common[:1],
                          str(tmp_path / "one"), *common[1:]], env=env, capture_output=True,
                         text=True, timeout=300)
    assert one.returncode == 0, one.stderr
    logs = tmp_path / "rank_logs"              # each rank's own output, for a failure report
    two = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone",
                          "--nproc_per_node", "2", "--log-dir", str(logs), "--redirects", "3",
                          "-m", "ekdun.cli", "train", *common[:1],
                          str(tmp_path / "two"), *common[1:]], env=env, capture_output=True,
                         text=True, timeout=300)
    ranks = "".join(f"\n--- {f.relative_to(logs)}\n{f.read_text(errors='replace')[-1500:]}"
                    for f in sorted(logs.rglob("*.log")))
    assert two.returncode == 0, two.stderr[-1500:] + ranks
    a = load_checkpoint(tmp_path / "one" / "checkpoint.pt")
    b = load_checkpoint(tmp_path / "two" / "checkpoint.pt")
    assert b["metadata"]["world_size"] == 2 and a["metadata"]["world_size"] == 1
    for name, p in a["model"].items():
        torch.testing.assert_close(b["model"][name], p, rtol=1e-5, atol=1e-5, msg=name)


_GLOO_THREADS_AFTER_TRAINING = """
import os, sys
from ekdun.data.pairs import PairsDataset
from ekdun.training import TrainOptions, train
pairs, kernels, run, report = sys.argv[1:5]
train(run, "ekdun", kernels, PairsDataset(pairs), "tiny", {"iterations": 2},
      TrainOptions(epochs=1, batch_size=4, progress=False, threads=1, device="cpu"))
import torch.distributed as dist
names = [open(f"/proc/self/task/{t}/comm").read().strip() for t in os.listdir("/proc/self/task")]
# a file per rank: the ranks' prints share one pipe and can interleave
with open(f"{report}.{os.environ['RANK']}", "w") as fh:
    fh.write(f"{dist.is_initialized()} {sorted(n for n in names if 'gloo' in n)}")
"""


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="needs Linux /proc")
def test_ddp_training_ends_its_process_group_before_exit(tiny_data, tmp_path):
    """After ``train`` under torchrun the gloo group is gone, threads included, on every rank.

    DDP's constructor imports ``torch.distributed.nn``, whose defaults hold the group; the
    group then outlived ``destroy_process_group`` and its threads ended in interpreter shutdown,
    the likeliest place of a rank-1 abort seen twice in CI ("terminate called without an active
    exception"). Without the fix both ranks report their gloo threads still running."""
    pairs, kernels = tiny_data
    script = tmp_path / "train_then_list_threads.py"
    script.write_text(_GLOO_THREADS_AFTER_TRAINING)
    done = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone",
                           "--nproc_per_node", "2", str(script), str(pairs), str(kernels),
                           str(tmp_path / "run"), str(tmp_path / "gloo_threads")],
                          env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONFAULTHANDLER": "1"},
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    # per rank: is a group still initialised, and which gloo threads are still running
    assert [(tmp_path / f"gloo_threads.{rank}").read_text() for rank in (0, 1)] == \
        ["False []", "False []"]


class _Evil:
    def __init__(self, marker: str) -> None:
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


@pytest.mark.filterwarnings("ignore:Detected pickle protocol:UserWarning")
def test_checkpoints_never_execute_code(tmp_path, capsys):
    marker = tmp_path / "pwned"
    evil = tmp_path / "evil.pt"
    torch.save({"format": "ekdun-checkpoint", "payload": _Evil(str(marker))}, evil)
    with pytest.raises(CheckpointError, match="refused to load"):
        load_checkpoint(evil)
    assert not marker.exists()
    raw = tmp_path / "raw.pt"
    raw.write_bytes(pickle.dumps(_Evil(str(marker))))
    with pytest.raises(CheckpointError, match=str(raw)):       # refused, whatever the reason
        load_checkpoint(raw)
    assert not marker.exists()
    # the CLI turns it into one line and writes nothing
    out = tmp_path / "learned.npz"
    assert ekdun_main(["export-kernels", str(evil), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("ekdun: error:") and "refused" in err[0]
    assert not marker.exists() and not out.exists()
    # foreign but harmless torch file, and garbage bytes
    torch.save({"weights": torch.zeros(3)}, tmp_path / "foreign.pt")
    with pytest.raises(CheckpointError, match="not an ekdun-checkpoint"):
        load_checkpoint(tmp_path / "foreign.pt")
    (tmp_path / "garbage.pt").write_bytes(b"\x00garbage" * 10)
    with pytest.raises(CheckpointError, match="not a readable checkpoint"):
        load_checkpoint(tmp_path / "garbage.pt")


# The kernel metadata as checkpoints stored it before KernelModel.to_metadata wrote it: no
# format, version, kernel_names or kernel_origin. Such checkpoints must keep loading.
OLD_KERNEL_METADATA = {"basis": "paper", "convention": "sensor", "sensor_shape": list(SENSOR),
                       "channels": ["R", "G", "B"], "optical_center": None, "scene_padding": 2,
                       "normalization": "unspecified", "provenance": {}}


def _old_checkpoint(path, kernels, state_dict, kernel_metadata=OLD_KERNEL_METADATA):
    return save_checkpoint(path, {
        "metadata": {"model": "ekdun", "preset": "tiny", "overrides": encode_overrides(SMALL),
                     "sensor_shape": list(SENSOR), "kernel_metadata": kernel_metadata,
                     "epoch": 3},
        "model": state_dict, "initial_kernels": torch.as_tensor(kernels)})


def test_checkpoints_with_the_older_kernel_metadata_still_load(tiny_data, tmp_path):
    _, kernels = tiny_data
    seed = load_kernels(kernels)
    trained = build_network("ekdun", seed, "tiny", SMALL)
    with torch.no_grad():                                # "learned": differs from the seed
        trained.physics.kernels.mul_(1.5)
    path = _old_checkpoint(tmp_path / "old.pt", seed.kernels, trained.state_dict())
    model, _ = network_from_checkpoint(path)
    for name, value in trained.state_dict().items():
        torch.testing.assert_close(model.state_dict()[name], value, rtol=0, atol=0, msg=name)
    assert model.seed_kernels is not None
    assert model.seed_kernels.to_metadata() == seed.to_metadata()
    np.testing.assert_array_equal(model.seed_kernels.kernels, seed.kernels)
    before = initial_kernels(path)
    np.testing.assert_array_equal(before.kernels, seed.kernels)
    learned = export_kernels(path)
    np.testing.assert_array_equal(learned.kernels, 1.5 * seed.kernels)
    assert (learned.basis, learned.sensor_shape, learned.provenance["epoch"]) == (
        "paper", SENSOR, 3)
    # a checkpoint whose seed breaks the kernel-file contract is refused, naming the problem
    nan = np.full_like(seed.kernels, np.nan)
    bad = _old_checkpoint(tmp_path / "nan.pt", nan, trained.state_dict())
    with pytest.raises(CheckpointError, match=r"initial_kernels.* NaN/Inf"):
        network_from_checkpoint(bad)
    with pytest.raises(CheckpointError, match=r"initial_kernels.* NaN/Inf"):
        initial_kernels(bad)
    lens = _old_checkpoint(tmp_path / "lens.pt", seed.kernels, trained.state_dict(),
                           {**OLD_KERNEL_METADATA, "convention": "lens"})
    with pytest.raises(CheckpointError, match="convention must be 'sensor' or 'source'"):
        network_from_checkpoint(lens)


def test_seed_kernels_is_a_declared_attribute(tiny_data):
    _, kernels = tiny_data
    seed = load_kernels(kernels)
    direct = build_model("ekdun", seed, "tiny", **decode_overrides(SMALL))
    assert direct.seed_kernels is None                   # built directly
    exported = export_kernels(direct)                    # geometry from the physics then
    np.testing.assert_array_equal(exported.kernels, seed.kernels)
    assert (exported.basis, exported.sensor_shape, exported.normalization) == (
        "paper", SENSOR, "learned (initialised from: unknown)")
    model = build_network("ekdun", seed, "tiny", SMALL)
    assert model.seed_kernels is seed
    # from a PSF: the seed is the PSF repeated as the basis' kernels, with the PSF's geometry
    psf_seed = KernelModel.shift_invariant(seed.kernels[0], normalization="PSF")
    from_psf = build_network("ekdun", psf_seed, "tiny", SMALL)
    assert from_psf.seed_kernels is not None and from_psf.seed_kernels.basis == "paper"
    np.testing.assert_array_equal(from_psf.seed_kernels.kernels,
                                  np.stack([seed.kernels[0]] * 3))
    assert build_network("le-admm-u", psf_seed, "tiny", {}).seed_kernels is psf_seed
    seed.kernels[0, 0, 0, 0] = np.nan                    # changed in place after loading
    with pytest.raises(ModelFileError, match=r"^seed kernels: kernels contain NaN/Inf"):
        model.set_seed_kernels(seed)
    assert issubclass(CheckpointError, PsfkitError)      # the CLIs print it as one line


class _DeviceTensor:
    """A tensor as ``torch.load(map_location="cuda")`` returns it, seen from the host: it
    must be copied with ``.cpu()`` before ``.numpy()`` / ``.tolist()`` (torch raises
    ``TypeError`` on a CUDA tensor's ``.numpy()``)."""

    def __init__(self, tensor: torch.Tensor) -> None:
        self._tensor = tensor

    def cpu(self) -> torch.Tensor:
        return self._tensor

    def numpy(self):
        raise TypeError("can't convert cuda:0 device type tensor to numpy")

    def tolist(self):
        raise TypeError("device tensor read without .cpu()")


def test_rng_state_restores_from_a_checkpoint_loaded_onto_the_gpu():
    """--resume on CUDA loads the checkpoint with map_location=cuda: the RNG tensors arrive
    on the device (this failed on an H200 with "can't convert cuda:0 device type tensor to
    numpy" before set_rng_state read them through .cpu())."""
    import random

    from ekdun.training.rng import rng_state, set_rng_state

    state = rng_state()
    expected = (np.random.random(3), random.random(), torch.rand(3))  # noqa: NPY002
    on_device = {k: _DeviceTensor(v) if isinstance(v, torch.Tensor) else v
                 for k, v in state.items()}
    set_rng_state(on_device)
    got = (np.random.random(3), random.random(), torch.rand(3))  # noqa: NPY002
    np.testing.assert_array_equal(got[0], expected[0])
    assert got[1] == expected[1]
    torch.testing.assert_close(got[2], expected[2], rtol=0, atol=0)


@pytest.mark.parametrize("network", ["le-admm-u", "updn", "ekdun"])
def test_each_network_trains_with_its_own_recipe(tiny_data, tmp_path, network):
    """A preset's recipe for a network replaces the preset's shared settings for it (its
    learning rate is the one the first epoch runs at); a learning rate given replaces both."""
    from ekdun.nets.configs import get_preset

    pairs, kernels = tiny_data
    small = {"ekdun": SMALL, "le-admm-u": {"iterations": 2, "denoiser": {"widths": [4, 8]}},
             "updn": {"iterations": 2, "denoiser": {"widths": [4, 8]}}}[network]
    preset = get_preset("tiny")
    expected = preset.recipes.get(network, {}).get("lr", preset.training.lr)
    for given, lr in ((None, expected), (3e-4, 3e-4)):
        options = TrainOptions(epochs=1, batch_size=4, lr=given, progress=False, threads=1)
        run = tmp_path / f"run-{given}"
        train(run, network, kernels, PairsDataset(pairs), "tiny", small, options)
        first = (run / "log.csv").read_text().splitlines()[1].split(",")
        assert float(first[2]) == pytest.approx(lr, rel=1e-12), (network, given)
    assert preset.training_for(network.replace("-", "_")) == preset.training_for(network)


def test_a_tiny_updn_checkpoint_of_five_iterations_still_loads(tiny_data, tmp_path):
    """``tiny`` UPDN had 5 iterations before it took its authors' 10; its checkpoints record
    no override, and load with the iterations their weights hold, giving the same output."""
    _, kernels = tiny_data
    seed = load_kernels(kernels)
    torch.manual_seed(0)
    old = build_network("updn", seed, "tiny", {"iterations": 5})
    path = save_checkpoint(tmp_path / "updn5.pt", {
        "metadata": {"model": "updn", "preset": "tiny", "overrides": {},
                     "sensor_shape": list(SENSOR), "kernel_metadata": seed.to_metadata(),
                     "epoch": 1},
        "model": old.state_dict(), "initial_kernels": torch.as_tensor(seed.kernels)})
    model, _ = network_from_checkpoint(path)
    assert model.iterations == 5 and build_network("updn", seed, "tiny").iterations == 10
    y = torch.rand(1, 3, *SENSOR)
    with torch.no_grad():
        torch.testing.assert_close(model(y), old(y), rtol=0, atol=0)
