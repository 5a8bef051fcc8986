"""Architecture configurations and the ``tiny`` / ``paper`` presets.

``paper`` uses the paper's architectures and training settings (Sec. 5.2): EK-DUN with 10
iterations and a 3-level U-Net prior (32 → 64 → 128 channels) per iteration, Le-ADMM-U with 5
iterations, UPDN with 10 iterations and 5 PSFs per colour; sensor 1080 × 1440; Adam with
learning rate 1e-4, ExponentialLR 0.95 per epoch, MSE loss.

``tiny`` is the CPU preset: a 64 × 64 sensor and reduced widths/iterations so that the whole
"three models + ablation" benchmark (``python -m research.benchmark_tiny``) trains and
evaluates on two CPU cores in about 20 minutes: EK-DUN with the paper's 10 iterations
(eigen-kernel model in the last 2) and U-Nets of widths (8, 16, 32); Le-ADMM-U with 5
iterations and a (8, 16, 32, 64) U-Net; UPDN with its authors' 10 iterations, 5 PSFs per
colour and a (15, 30, 60) U-Net; a larger learning rate (2e-3) for the few epochs. The sensor
size of a built model comes from its kernel file or PSF; the preset's ``sensor_shape`` is what
benchmarks and synthetic examples use.

Baseline denoisers (each choice against the authors' code: docs/baselines.md):

* Le-ADMM-U: a 5-level U-Net of widths ``(24, 64, 128, 256, 512)``, the encoder widths of
  Monakhova et al.'s U-Net, built from the shared block (two Conv-ReLU per level, transposed
  convolution up; their batch normalisation and bilinear upsampling are not reproduced).
* UPDN: a 5-level U-Net of widths ``(15, 30, 60, 120, 240)``, the ``init_features = 3·5``
  U-Net of Kingshott et al.'s colour model, input the 15 primal channels.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

from ekdun.errors import ConfigurationError


@dataclass(frozen=True)
class UNetConfig:
    """See :class:`ekdun.nets.unet.UNet`."""

    widths: tuple[int, ...] = (32, 64, 128)
    residual: bool = True
    zero_init_output: bool = True


@dataclass(frozen=True)
class EKDUNConfig:
    """EK-DUN (Eqs. 4–6 with the eigen-kernel model of Eq. 7).

    Attributes
    ----------
    iterations : int
        Unrolled iterations ``I`` (paper: 10).
    schedule : {"base", "last-k", "all"}
        Forward model per iteration: base kernel only; eigen-kernel model in the last
        ``eigen_last`` iterations; eigen-kernel model everywhere (also for ``f⁰ = Aᵀy``).
        ``"last-2"`` etc. are accepted as shorthand for ``"last-k"`` with that ``k``.
    eigen_last : int
        ``k`` of ``"last-k"`` (paper: 2).
    prior : UNetConfig
        Prior network ``P⁽ⁱ⁾`` of every iteration.
    basis : str
        Weight basis when the model is built from a single PSF (``Kv = Kh = Kbase = PSF``).
    step_scale : float
        Initial ``ε⁽ⁱ⁾ = step_scale / L`` with ``L = max |K̂|² ≈ ‖AᵀA‖``.
    penalty_scale : float
        Initial ``η⁽ⁱ⁾ = penalty_scale · L`` (so ``ε·η = step_scale·penalty_scale``).
    kappa_init : float
        Initial dual step ``κ⁽ⁱ⁾``.
    kernel_param : {"free", "physical", "flow"}
        How the trainable kernels are parameterised
        (:mod:`ekdun.physics.kernel_parameterisation`): free pixels (the paper's), non-negative
        on the seed's dilated caustic with its energy kept, ``Kbase`` warped by smooth
        learned displacement fields times per-channel gains, or free kernels in Fourier
        coordinates (the optimiser's steps per spatial frequency).
    kernel_support_dilate : int
        Dilation (px) of the seed's caustic support (``physical``, ``flow``).
    flow_grid : int
        Coarse displacement grid ``n × n`` of ``flow``.
    flow_residual : bool
        ``flow`` with a small trainable residual on the support.
    kernel_gain : bool
        ``physical`` with a learned per-channel gain of the correction kernels.
    """

    iterations: int = 10
    schedule: str = "last-k"
    eigen_last: int = 2
    prior: UNetConfig = field(default_factory=UNetConfig)
    basis: str = "paper"
    step_scale: float = 1.0
    penalty_scale: float = 0.5
    kappa_init: float = 1.0
    kernel_param: str = "free"
    kernel_support_dilate: int = 3
    flow_grid: int = 8
    flow_residual: bool = False
    kernel_gain: bool = False


@dataclass(frozen=True)
class LeADMMUConfig:
    """Le-ADMM-U (Monakhova et al. 2019): unrolled DiffuserCam ADMM, then a U-Net.

    Initial values are relative to ``L = max |K̂|²``: ``μ1 = mu1_init`` (data units),
    ``μ2 = mu2_scale·L`` (TV split), ``μ3 = mu3_scale·L`` (non-negativity split) and
    ``τ = tau_scale·μ2`` (so the TV soft threshold ``τ/μ2`` is ``tau_scale`` in scene units).
    """

    iterations: int = 5
    denoiser: UNetConfig = field(default_factory=lambda: UNetConfig(
        widths=(24, 64, 128, 256, 512)))
    mu1_init: float = 1.0
    mu2_scale: float = 0.25
    mu3_scale: float = 1.0
    tau_scale: float = 1e-2


@dataclass(frozen=True)
class UPDNConfig:
    """UPDN (Kingshott et al. 2022): unrolled primal-dual with learned PSFs, then a U-Net.

    ``copies`` PSFs per colour (paper: 5, i.e. 15 channels for RGB), each initialised from the
    measured PSF; ``hidden_factor`` scales the width of the 3×3 grouped convolutions of the
    primal and dual updates relative to their input (1 as in the reference code).
    ``primal_grid`` is where the primal lives: ``"sensor"`` (default) or ``"padded"`` (the
    reference's: the physics' scene grid, where light from outside the field of view has
    somewhere to be). On the varying bench, whose scenes have the sensor's size, both reach
    the same PSNR (docs/baselines.md) and the padded grid costs 1.15–1.5× the time.
    """

    iterations: int = 10
    copies: int = 5
    hidden_factor: int = 1
    primal_grid: str = "sensor"
    denoiser: UNetConfig = field(default_factory=lambda: UNetConfig(
        widths=(15, 30, 60, 120, 240)))


@dataclass(frozen=True)
class TrainingConfig:
    """Optimisation settings (paper, Sec. 5.2: MSE, Adam 1e-4, ExponentialLR 0.95 per epoch,
    200 epochs; the paper does not state the batch size, 4 is our choice).

    ``kernel_lr_scale`` multiplies the learning rate of the physics kernels (``Kbase, Kv,
    Kh``, UPDN's PSFs): their pixels are ~1e-4–1e-3 (each kernel sums to about 1), so a
    step of the network's learning rate would wipe them out in a few iterations.
    """

    epochs: int = 200
    batch_size: int = 4
    lr: float = 1e-4
    gamma: float = 0.95
    kernel_lr_scale: float = 1e-2
    physics_weight: float = 0.0


@dataclass(frozen=True)
class Preset:
    """Configurations of the three models and the sensor size they are meant for.

    ``recipes`` holds a network's own training settings, which replace those of
    ``training`` for it (no network is trained with another network's learning rate): its
    authors' where published, else the best of a learning-rate sweep at equal budget
    (docs/baselines.md).
    """

    name: str
    sensor_shape: tuple[int, int]
    channels: int = 3
    scene_padding: int = 2
    ekdun: EKDUNConfig = field(default_factory=EKDUNConfig)
    le_admm_u: LeADMMUConfig = field(default_factory=LeADMMUConfig)
    updn: UPDNConfig = field(default_factory=UPDNConfig)
    training: TrainingConfig = field(default_factory=TrainingConfig)
    recipes: dict[str, dict[str, float]] = field(default_factory=dict)

    def training_for(self, network: str) -> TrainingConfig:
        """The training settings of ``network``: ``training`` with its recipe."""
        return replace(self.training,
                       **self.recipes.get(network.lower().replace("_", "-"), {}))


PRESETS: dict[str, Preset] = {
    "tiny": Preset(
        "tiny", (64, 64),
        ekdun=EKDUNConfig(iterations=10, prior=UNetConfig(widths=(8, 16, 32))),
        le_admm_u=LeADMMUConfig(denoiser=UNetConfig(widths=(8, 16, 32, 64))),
        # UPDN: its authors' 10 iterations
        updn=UPDNConfig(denoiser=UNetConfig(widths=(15, 30, 60))),
        training=TrainingConfig(epochs=15, batch_size=4, lr=2e-3, gamma=0.95),
        # UPDN: the best of a learning-rate sweep on the 64² bench at this batch (8 epochs,
        # 3 seeds); EK-DUN's and Le-ADMM-U's best are the shared 2e-3 or tie with it
        # (research/notes/baselines-measurements.md)
        recipes={"updn": {"lr": 4e-3}}),
    # UPDN: its authors' Adam at 5e-4, constant (oliland/lensless-primal-dual)
    "paper": Preset("paper", (1080, 1440), recipes={"updn": {"lr": 5e-4, "gamma": 1.0}}),
}


def get_preset(preset: str | Preset) -> Preset:
    """The preset called ``preset`` (``"tiny"`` or ``"paper"``), or ``preset`` itself."""
    if isinstance(preset, Preset):
        return preset
    if preset not in PRESETS:
        raise ConfigurationError(f"unknown preset {preset!r} (use {', '.join(PRESETS)})")
    return PRESETS[preset]


def parse_schedule(schedule: str, iterations: int,
                   eigen_last: int = 2) -> tuple[bool, tuple[bool, ...]]:
    """Which forward model EK-DUN uses, as ``(eigen for f⁰, eigen for iteration i)``.

    Examples
    --------
    >>> parse_schedule("last-k", 4, 2)
    (False, (False, False, True, True))
    >>> parse_schedule("all", 2)
    (True, (True, True))
    """
    if iterations < 1:
        raise ConfigurationError(f"iterations must be >= 1, got {iterations}")
    given = schedule
    if schedule.startswith("last-") and schedule[5:].isdigit():
        eigen_last, schedule = int(schedule[5:]), "last-k"
    if schedule == "base":
        return False, (False,) * iterations
    if schedule == "all":
        return True, (True,) * iterations
    if schedule == "last-k":
        if not 0 <= eigen_last <= iterations:
            # named as the user wrote it (--schedule last-N), not as the config field
            raise ConfigurationError(f"schedule {given!r} (--schedule): N must be in "
                                     f"[0, {iterations}], the iterations")
        return False, (False,) * (iterations - eigen_last) + (True,) * eigen_last
    raise ConfigurationError(f"unknown schedule {schedule!r} (use base, last-k, last-N or all)")
