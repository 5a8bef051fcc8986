"""Unrolled networks: shapes, parameter counts, schedules, update equations, training, export."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from ekdun.errors import ConfigurationError, TensorShapeError
from ekdun.nets import (
    EKDUN,
    PRESETS,
    UPDN,
    EKDUNConfig,
    LeADMMU,
    UNet,
    UNetConfig,
    build_model,
    count_parameters,
    parse_schedule,
)
from ekdun.nets.tv_admm_steps import finite_differences, finite_differences_adjoint
from ekdun.nets.updn import interleave_copies
from ekdun.physics import PreparedOperator, ShiftInvariantOperator
from psfkit.forward.convolution import crop
from psfkit.forward.kernelfile import KernelModel, save_kernels
from research.synthetic import caustic_psf

SENSOR = (32, 48)
DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])
SMALL_UNET = UNetConfig(widths=(4, 8))


@pytest.fixture(autouse=True)
def _one_intra_op_thread(torch_one_thread):
    """Tiny tensors: every test here runs with one torch thread (shared fixture)."""


def admm_estimate(model: LeADMMU, y: torch.Tensor) -> torch.Tensor:
    """The cropped ADMM iterate of ``model`` before its U-Net, ``(B, C, H', W')``."""
    state, _ = model.iterate(y)
    return crop(state["x"], model.physics.sensor_shape)


@pytest.fixture(scope="module")
def psf() -> np.ndarray:
    return caustic_psf(SENSOR, 3, seed=1)


def measurement(psf: np.ndarray, batch: int = 2, seed: int = 0) -> tuple[torch.Tensor,
                                                                          torch.Tensor]:
    """A scene in the middle of the field and its shift-invariant measurement."""
    gen = torch.Generator().manual_seed(seed)
    c, h, w = psf.shape
    x = torch.zeros(batch, c, h, w)
    x[..., h // 4:3 * h // 4, w // 4:3 * w // 4] = torch.rand(batch, c, h // 2, w // 2,
                                                             generator=gen)
    return x, ShiftInvariantOperator.from_psf(psf).A(x)


def unet_parameters(cin: int, cout: int, widths: tuple[int, ...]) -> int:
    """Parameter count of the U-Net spec: two 3×3 conv (+bias) per level and decoder level,
    2×2 transposed conv up, 1×1 head."""
    count, previous = 0, cin
    for w in widths:
        count += 9 * previous * w + w + 9 * w * w + w
        previous = w
    for lo, hi in itertools.pairwise(widths):
        count += 4 * hi * lo + lo                       # transposed convolution
        count += 9 * 2 * lo * lo + lo + 9 * lo * lo + lo  # decoder block on the concatenation
    return count + widths[0] * cout + cout


@pytest.mark.parametrize("name,overrides", [
    ("ekdun", {"schedule": "base"}), ("ekdun", {"schedule": "last-k"}),
    ("ekdun", {"schedule": "all"}), ("le-admm-u", {}), ("updn", {})])
def test_output_shapes_with_the_paper_architecture(psf, name, overrides):
    model = build_model(name, psf, "paper", **overrides)
    _, y = measurement(psf)
    out = model(y)
    assert out.shape == y.shape and out.dtype == y.dtype
    assert torch.isfinite(out).all()
    # each image of a batch is reconstructed on its own (no mixing across the batch), and the
    # output depends on the measurement
    with torch.no_grad():
        alone = torch.cat([model(y[i:i + 1]) for i in range(len(y))])
    torch.testing.assert_close(out.detach(), alone, rtol=1e-4, atol=1e-5 * float(alone.abs().max()))
    assert (out[0] - out[1]).abs().max() > 1e-3 * out.abs().max()


@pytest.mark.parametrize("name", ["ekdun", "le-admm-u", "updn"])
def test_mono_odd_sizes_and_float64(name):
    mono = caustic_psf((21, 27), 1, seed=2)
    model = build_model(name, mono, "paper", dtype=torch.float64).double()
    y = torch.rand(1, 1, 21, 27, dtype=torch.float64)
    out = model(y)
    assert out.shape == (1, 1, 21, 27) and out.dtype == torch.float64
    # the same network in float32 computes the same thing, to float32 precision
    single = build_model(name, mono, "paper")
    single.load_state_dict({k: v.float() if v.is_floating_point() else v
                            for k, v in model.state_dict().items()})
    with torch.no_grad():
        out32 = single(y.float()).double()
    scale = float(out.detach().abs().max())
    assert scale > 0 and float((out32 - out.detach()).abs().max()) < 1e-3 * scale


def test_parameter_counts_follow_the_layer_spec(psf):
    c, (h, w) = 3, SENSOR
    prior = unet_parameters(3, 3, (32, 64, 128))
    assert prior == 466_595
    ek = build_model("ekdun", psf, "paper")
    assert ek.parameter_count() == 3 * c * h * w + 3 * 10 + 10 * prior
    assert ek.parameter_breakdown()["priors"] == 10 * prior
    assert count_parameters(ek.priors[0]) == prior

    le = build_model("le-admm-u", psf, "paper")
    assert le.parameter_count() == 4 * 5 + unet_parameters(3, 3, (24, 64, 128, 256, 512))
    assert count_parameters(le, trainable_only=False) == le.parameter_count()  # PSF: buffer
    assert le.physics.kernels.requires_grad is False

    updn = build_model("updn", psf, "paper")
    width, n = 15, 5
    dual = (9 * 3 * width * 3 * width // n + 3 * width) + (3 * width * width + width)
    primal = (9 * 2 * width * 2 * width // n + 2 * width) + (2 * width * width + width)
    assert updn.parameter_count() == (width * h * w + 10 * (dual + primal)
                                      + unet_parameters(width, 3, (15, 30, 60, 120, 240)))
    # the paper preset keeps the paper's architecture; tiny is reduced for CPU benchmarks
    assert PRESETS["paper"].ekdun == EKDUNConfig()
    assert PRESETS["paper"].sensor_shape == (1080, 1440)
    assert PRESETS["tiny"].sensor_shape == (64, 64)


def test_unet_layout_identity_at_init_and_odd_sizes():
    net = UNet(3, 3, (32, 64, 128))
    assert [e[0].out_channels for e in net.encoders] == [32, 64, 128]
    assert [u.out_channels for u in net.upsamplers] == [32, 64]
    assert isinstance(net.upsamplers[0], torch.nn.ConvTranspose2d)
    x = torch.rand(2, 3, 13, 22)
    torch.testing.assert_close(net(x), x)           # zero-initialised residual: identity
    torch.nn.init.normal_(net.head.weight)
    out = net(x)
    assert out.shape == x.shape and (out - x).abs().max() > 1e-3
    with pytest.raises(ConfigurationError, match="needs in_channels >= out_channels"):
        UNet(1, 3)


def test_schedules():
    assert parse_schedule("base", 10) == (False, (False,) * 10)
    assert parse_schedule("last-k", 10, 2) == (False, (False,) * 8 + (True,) * 2)
    assert parse_schedule("last-3", 10) == (False, (False,) * 7 + (True,) * 3)
    assert parse_schedule("all", 10) == (True, (True,) * 10)
    with pytest.raises(ConfigurationError, match="unknown schedule 'first-2'"):
        parse_schedule("first-2", 10)
    with pytest.raises(ConfigurationError, match=r"N must be in \[0, 10\]"):
        parse_schedule("last-k", 10, 11)


@pytest.mark.parametrize("schedule,forward_log,adjoint_log,ffts", [
    ("base", [1] * 10, [1] * 11, (22, 21)),
    ("last-k", [1] * 8 + [3] * 2, [1] * 9 + [3] * 2, (26, 25)),
    ("all", [3] * 10, [3] * 11, (1 + 3 + 10 * 4, 1 + 10 * 4)),
])
def test_schedule_decides_which_model_each_iteration_calls(monkeypatch, fft_counter, psf,
                                                           schedule, forward_log, adjoint_log,
                                                           ffts):
    model = build_model("ekdun", psf, "paper", schedule=schedule,
                        prior=UNetConfig(widths=(4,)))
    _, y = measurement(psf, batch=1)
    calls: dict[str, list[int]] = {"A": [], "At": []}
    forward, adjoint = PreparedOperator.A, PreparedOperator.A_adjoint

    def logged_forward(self, x):
        calls["A"].append(self.n_kernels)
        return forward(self, x)

    def logged_adjoint(self, x):
        calls["At"].append(self.n_kernels)
        return adjoint(self, x)

    monkeypatch.setattr(PreparedOperator, "A", logged_forward)
    monkeypatch.setattr(PreparedOperator, "A_adjoint", logged_adjoint)
    fft_counter.take()
    model(y)
    assert calls["A"] == forward_log          # one A per iteration, in order
    assert calls["At"] == adjoint_log         # f⁰ = Aᵀy, then one Aᵀ per iteration
    # kernel spectra once per forward pass (one batched call), then 1+K / K+1 per A / Aᵀ
    assert fft_counter.take() == ffts


def test_initial_ekdun_is_gradient_descent_with_step_one_over_lipschitz(psf):
    model = build_model("ekdun", psf, "paper", dtype=torch.float64).double()
    x, _ = measurement(psf, batch=1)
    y = ShiftInvariantOperator.from_psf(psf, dtype=torch.float64).A(x.double())
    lipschitz = model.physics.lipschitz_bound()
    with torch.no_grad():
        base = model.physics.prepare_base()
        f = base.A_adjoint(y)
        residuals = [float((base.A(f) - y).norm())]
        for _ in range(10):
            f = f - base.A_adjoint(base.A(f) - y) / lipschitz
            residuals.append(float((base.A(f) - y).norm()))
        out = model(y)
    torch.testing.assert_close(out, f, rtol=1e-10, atol=1e-10)
    assert all(b < a for a, b in itertools.pairwise(residuals))
    assert np.exp(model.log_eps.detach().numpy()) == pytest.approx(1 / lipschitz)


def test_one_iteration_matches_eq5_and_eq6(psf):
    config = EKDUNConfig(iterations=1, schedule="all", prior=UNetConfig(widths=(4, 8)))
    model = build_model("ekdun", psf, "paper", config=config, dtype=torch.float64).double()
    with torch.no_grad():
        for p in model.priors.parameters():
            p.normal_(0, 0.1)
        model.log_eps.fill_(np.log(0.3))
        model.log_eta.fill_(np.log(0.7))
        model.kappa.fill_(0.9)
    y = torch.rand(1, 3, *SENSOR, dtype=torch.float64)
    op = model.physics.prepare()
    f0 = op.A_adjoint(y)
    d0 = torch.zeros_like(f0)
    g1 = model.priors[0](f0 - d0)
    eps, eta = 0.3, 0.7
    f1 = (1 - eps * eta) * f0 - eps * op.A_adjoint(op.A(f0)) + eps * op.A_adjoint(y) \
        + eps * eta * (g1 + d0)
    state, _ = model.iterate(y)
    torch.testing.assert_close(state["f"], f1, rtol=1e-10, atol=1e-12)
    torch.testing.assert_close(state["d"], d0 + 0.9 * (g1 - f1), rtol=1e-10, atol=1e-12)


def test_le_admm_pieces():
    x = torch.rand(2, 3, 6, 8, dtype=torch.float64)
    u = torch.rand(2, 2, 3, 6, 8, dtype=torch.float64)
    lhs = (finite_differences(x) * u).sum()
    assert float(lhs) == pytest.approx(float((x * finite_differences_adjoint(u)).sum()),
                                       rel=1e-12)
    mono = caustic_psf((16, 20), 1, seed=3)
    scene = torch.zeros(1, 1, 16, 20, dtype=torch.float64)
    scene[..., 4:12, 5:15] = 1.0
    y = ShiftInvariantOperator.from_psf(mono, dtype=torch.float64).A(scene)
    errors = []
    for iterations in (1, 5, 30):
        model = build_model("le-admm-u", mono, "paper", iterations=iterations,
                            dtype=torch.float64).double()
        with torch.no_grad():
            errors.append(float((admm_estimate(model, y) - scene).norm()))
    assert errors[0] > errors[1] > errors[2]           # more ADMM iterations, better estimate
    assert isinstance(model, LeADMMU) and model.physics.grid_shape == (32, 40)


def test_updn_interleaves_copies_and_starts_with_identical_psfs(psf):
    a = torch.arange(2 * 6 * 1 * 1, dtype=torch.float32).reshape(2, 6, 1, 1)
    b = -a
    mixed = interleave_copies(2, a, b)
    assert mixed[0, :, 0, 0].tolist() == [0, 1, 2, 0, -1, -2, 3, 4, 5, -3, -4, -5]
    model = build_model("updn", psf, "paper")
    assert isinstance(model, UPDN)
    psfs = model.physics.psfs
    assert psfs.shape == (5, 3, *SENSOR) and model.physics.channels == 15
    for n in range(5):
        torch.testing.assert_close(psfs[n], torch.as_tensor(psf))


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("name", ["ekdun", "le-admm-u", "updn"])
def test_a_few_adam_steps_reduce_the_loss(psf, name, device):
    torch.manual_seed(0)
    small = {"ekdun": {"prior": SMALL_UNET}, "le-admm-u": {"denoiser": SMALL_UNET},
             "updn": {"denoiser": SMALL_UNET}}[name]
    model = build_model(name, psf, "paper", **small).to(device)
    x, y = (t.to(device) for t in measurement(psf, batch=2))
    kernels_before = model.physics.kernels.detach().clone()
    optimiser = torch.optim.Adam(model.parameters(), lr=1e-3)
    losses = []
    for _ in range(6):
        optimiser.zero_grad()
        loss = torch.nn.functional.mse_loss(model(y), x)
        loss.backward()
        optimiser.step()
        losses.append(loss.item())
    with torch.no_grad():
        final = torch.nn.functional.mse_loss(model(y), x).item()
    assert final < losses[0]
    changed = not torch.equal(model.physics.kernels.detach(), kernels_before)
    assert changed == (name != "le-admm-u")       # Le-ADMM-U keeps the measured PSF fixed


@pytest.mark.parametrize("name,overrides", [
    ("ekdun", {"schedule": "last-k"}), ("ekdun", {"schedule": "base"}),
    ("le-admm-u", {}), ("updn", {})])
def test_exported_program_equals_eager(name, overrides):
    psf = caustic_psf((16, 24), 3, seed=4)
    model = build_model(name, psf, "paper", **overrides).eval()
    with torch.no_grad():                         # leave the identity initialisation
        for p in model.parameters():
            p.add_(0.01 * torch.randn_like(p))
    y = torch.rand(1, 3, 16, 24)
    exported = torch.export.export(model, (y,))
    y2 = torch.rand(1, 3, 16, 24)
    with torch.no_grad():
        torch.testing.assert_close(exported.module()(y2), model(y2), rtol=1e-5, atol=1e-6)


def test_build_model_from_a_kernel_file(tmp_path, psf):
    kernels = np.stack([psf, np.roll(psf, 1, axis=1), np.roll(psf, 1, axis=2)])
    path = save_kernels(tmp_path / "k.npz", KernelModel(kernels=kernels, sensor_shape=SENSOR))
    ek = build_model("ekdun", path, "paper")
    assert isinstance(ek, EKDUN) and ek.physics.kernel_names == ("base", "v", "h")
    np.testing.assert_array_equal(ek.physics.kernels.detach().numpy(), kernels)
    assert ek.physics.trainable
    le = build_model("le-admm-u", str(path), "paper")
    np.testing.assert_array_equal(le.physics.psf.numpy(), psf)      # the base kernel
    assert le(measurement(psf)[1]).shape == (2, 3, *SENSOR)


def test_model_errors(psf):
    model = build_model("ekdun", psf, "paper", prior=UNetConfig(widths=(4,)))
    with pytest.raises(TensorShapeError, match="measurement is 32x40 but the operator's "
                                               "sensor is 32x48"):
        model(torch.zeros(1, 3, 32, 40))
    with pytest.raises(TensorShapeError, match="1 channel"):
        model(torch.zeros(1, 1, *SENSOR))
    with pytest.raises(ConfigurationError, match="unknown model 'unet'"):
        build_model("unet", psf)
    with pytest.raises(ConfigurationError, match="unknown preset 'huge'"):
        build_model("ekdun", psf, "huge")
    with pytest.raises(ConfigurationError, match="unknown schedule"):
        build_model("ekdun", psf, schedule="sometimes")
    with pytest.raises(ConfigurationError, match=r"ekdun: .*no_such_field"):
        build_model("ekdun", psf, no_such_field=1)


@pytest.mark.parametrize("grid", ["sensor", "padded"])
def test_updn_primal_dual_blocks_ignore_autocast(psf, grid):
    """Issue 45: half precision compounded over UPDN's ten primal-dual updates (−8.6 dB
    untrained on an H100 under fp16). The blocks run in float32 under autocast, so the
    unrolled state is the same with and without it; only the U-Net sees half precision."""
    model = build_model("updn", psf, "tiny", primal_grid=grid).eval()
    y = torch.rand(2, 3, *SENSOR, generator=torch.Generator().manual_seed(0))
    with torch.no_grad():
        plain, _ = model.iterate(y)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            mixed, _ = model.iterate(y)
            out = model(y)
    for key in ("primal", "dual"):
        assert mixed[key].dtype == torch.float32
        torch.testing.assert_close(mixed[key], plain[key], rtol=1e-6, atol=1e-7)
    assert out.shape == (2, 3, *SENSOR) and bool(torch.isfinite(out).all())


def test_updn_primal_lives_on_the_padded_grid_with_exact_adjoints(psf):
    """The reference's primal grid (``primal_grid="padded"``): ``A p = crop(K ⊛ p)`` and
    ``Aᵀq = K ⋆ pad(q)`` on the physics' padded grid, an exact adjoint pair that equals the
    sensor-grid operator on scenes that vanish outside the sensor."""
    from psfkit.forward.convolution import pad

    assert build_model("updn", psf, "paper").config.primal_grid == "sensor"   # the default
    model = build_model("updn", psf, "paper", primal_grid="padded", dtype=torch.float64)
    y = torch.rand(2, 3, *SENSOR, dtype=torch.float64)
    context = model.prepare(y)
    grid = model.physics.grid_shape
    gen = torch.Generator().manual_seed(3)
    p = torch.randn(2, 15, *grid, dtype=torch.float64, generator=gen)
    q = torch.randn(2, 15, *SENSOR, dtype=torch.float64, generator=gen)
    with torch.no_grad():                        # the PSF copies are parameters
        lhs = float((context["A"](p) * q).sum())
        rhs = float((p * context["A_adjoint"](q)).sum())
    assert lhs == pytest.approx(rhs, rel=1e-12)
    x = torch.randn(2, 15, *SENSOR, dtype=torch.float64, generator=gen)
    torch.testing.assert_close(context["A"](pad(x, grid)), context["op"].A(x))
    torch.testing.assert_close(crop(context["A_adjoint"](q), SENSOR), context["op"].A_adjoint(q))
    # light outside the field of view reaches the sensor: the padded primal can explain it
    outside = torch.zeros(1, 15, *grid, dtype=torch.float64)
    outside[..., 0, 0] = 1.0
    with torch.no_grad():
        assert float(context["A"](outside).abs().sum()) > 0
    assert model.initial_state(y, context)["primal"].shape[-2:] == grid
    with torch.no_grad():
        assert model.float()(y.float()).shape == (2, 3, *SENSOR)
    with pytest.raises(ConfigurationError, match="primal_grid"):
        build_model("updn", psf, "paper", primal_grid="scene")

