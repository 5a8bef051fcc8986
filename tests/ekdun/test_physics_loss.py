"""--physics-weight: the measurement-consistency term (issue 24 item 1).

Checked against truth: its closed-form scale against a brute-force 1-D minimisation, its
gradient against finite differences, zero (with zero gradient) at the kernels that made the
pairs, and in training it pulls the kernels towards those that made the pairs.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy.optimize import minimize_scalar

from ekdun.cli import main as ekdun_main
from ekdun.data.pairs import PairsDataset
from ekdun.errors import ConfigurationError
from ekdun.nets.builder import build_network
from ekdun.physics.operators import EigenKernelOperator
from ekdun.training import TrainOptions, load_checkpoint, train
from ekdun.training.physics_loss import PhysicsObjective, measurement_consistency
from psfkit.forward.convolution import kernel_spectra
from psfkit.forward.kernelfile import load_kernels, save_kernels

SMALL = {"iterations": 2, "prior": {"widths": [4, 8]}}


def test_consistency_uses_the_best_scale_per_pair():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(3, 2, 5, 4))
    y = 0.7 * p + 0.1 * rng.normal(size=p.shape)
    value = measurement_consistency(torch.as_tensor(p), torch.as_tensor(y)).item()
    expected = []
    for pb, yb in zip(p, y, strict=True):
        best = minimize_scalar(lambda s, pb=pb, yb=yb: np.sum((s * pb - yb) ** 2),
                               bracket=(0, 2), tol=1e-12)
        expected.append(best.fun / np.sum(yb ** 2))
    assert value == pytest.approx(np.mean(expected), rel=1e-8)
    # any positive scale of the prediction is as consistent: the per-pair scale absorbs it
    scaled = measurement_consistency(torch.as_tensor(3.0 * p), torch.as_tensor(y)).item()
    assert scaled == pytest.approx(value, rel=1e-10)
    assert measurement_consistency(torch.as_tensor(p), torch.as_tensor(2.5 * p)).item() \
        < 1e-20


def test_consistency_gradient_matches_finite_differences():
    rng = np.random.default_rng(1)
    kernels = torch.as_tensor(rng.random((3, 1, 5, 5)), dtype=torch.float64)
    op = EigenKernelOperator.from_basis(kernels, "paper", (8, 8), convention="source",
                                        dtype=torch.float64)
    x = torch.as_tensor(rng.random((2, 1, 8, 8)))
    y = torch.as_tensor(rng.random((2, 1, 8, 8)))
    k = kernels.clone().requires_grad_(True)

    def objective(k):
        return measurement_consistency(op.prepare(kernel_spectra(k, op.grid_shape)).A(x), y)

    assert torch.autograd.gradcheck(objective, (k,), eps=1e-6, atol=1e-7)


def test_zero_with_zero_gradient_at_the_kernels_that_made_the_pairs(tiny_data):
    pairs, kernel_file = tiny_data
    truth = load_kernels(kernel_file)
    data = PairsDataset(pairs)
    x = torch.stack([data[i][0] for i in range(len(data))])
    y = torch.stack([data[i][1] for i in range(len(data))])
    values = {}
    for name, seed in (("truth", truth), ("one-psf", replace(
            truth, kernels=np.repeat(truth.kernels[:1], 3, axis=0)))):
        net = build_network("ekdun", seed, "tiny", SMALL)
        objective = PhysicsObjective(net)
        _, value = objective(y, x)
        (grad,) = torch.autograd.grad(value, net.physics.kernels)
        values[name] = (value.item(), grad.norm().item())
    assert values["truth"][0] < 1e-10
    assert values["one-psf"][0] > 1e-4
    assert values["truth"][1] < 1e-3 * values["one-psf"][1]


def _difference_error(learned: np.ndarray, truth: np.ndarray) -> float:
    d_learned, d_truth = learned[1:] - learned[:1], truth[1:] - truth[:1]
    return float(np.linalg.norm(d_learned - d_truth) / np.linalg.norm(d_truth))


def test_training_with_the_physics_term_moves_the_kernels_towards_truth(tiny_data, tmp_path):
    pairs, kernel_file = tiny_data
    truth = load_kernels(kernel_file)
    one = save_kernels(tmp_path / "one.npz", replace(
        truth, kernels=np.repeat(truth.kernels[:1], 3, axis=0)))
    data = PairsDataset(pairs)
    errors, runs = {}, {}
    for weight in (0.0, 10.0):
        options = TrainOptions(epochs=6, batch_size=4, lr=1e-3, kernel_lr_scale=0.3,
                               physics_weight=weight, progress=False, threads=1)
        run = tmp_path / f"w{weight:g}"
        runs[weight] = train(run, "ekdun", one, data, "tiny", SMALL, options)
        errors[weight] = _difference_error(load_kernels(run / "kernels_learned.npz").kernels,
                                           truth.kernels)
    # From Kv = Kh = Kbase (error 1 exactly) the consistency term brings Kv - Kbase and
    # Kh - Kbase closer to the truth (measured 0.86); the reconstruction loss alone drives
    # them away from it (measured 2.97): it does not determine them.
    assert errors[10.0] < 0.95
    assert errors[0.0] > errors[10.0] + 0.5
    history = runs[10.0]["history"]
    assert history[-1]["physics_loss"] < 0.5 * history[0]["physics_loss"]
    meta = load_checkpoint(tmp_path / "w10" / "checkpoint.pt")["metadata"]
    assert meta["training"]["physics_weight"] == 10.0
    header = (tmp_path / "w10" / "log.csv").read_text().splitlines()[0]
    assert header.endswith(",physics_loss")
    assert "physics_loss" not in (tmp_path / "w0" / "log.csv").read_text()


def test_physics_weight_is_refused_where_it_cannot_apply(tiny_data, tmp_path, capsys):
    pairs, kernel_file = tiny_data
    with pytest.raises(ConfigurationError, match="--network ekdun"):
        train(tmp_path / "u", "updn", kernel_file, PairsDataset(pairs), "tiny", {},
              TrainOptions(epochs=1, physics_weight=1.0, progress=False))
    assert not (tmp_path / "u").exists()        # refused before anything was written
    with pytest.raises(ConfigurationError, match="--physics-weight"):
        train(tmp_path / "n", "ekdun", kernel_file, PairsDataset(pairs), "tiny", SMALL,
              TrainOptions(epochs=1, physics_weight=-1.0, progress=False))
    code = ekdun_main(["train", str(pairs), str(tmp_path / "c"), "--kernels",
                       str(kernel_file), "--physics-weight", "-1", "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--physics-weight" in err[0]
