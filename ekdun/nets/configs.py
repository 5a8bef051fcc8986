"""Architecture configurations and the ``tiny`` / ``paper`` presets.

``paper``: the paper's architectures and training (Sec. 5.2; sensor 1080 x 1440, Adam 1e-4,
ExponentialLR 0.95 per epoch, MSE). ``tiny``: a 64 x 64 CPU preset with reduced widths, so that
``python -m research.benchmark_tiny`` runs on two CPU cores in about 20 minutes. A built
model's sensor size comes from its kernel file or PSF. The baseline U-Nets follow their
authors' encoder widths (docs/baselines.md).
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
        Where the eigen-kernel model is used (:func:`parse_schedule`; ``"last-2"`` etc. too).
    eigen_last : int
        ``k`` of ``"last-k"`` (paper: 2).
    prior : UNetConfig
        Prior network ``P⁽ⁱ⁾`` of every iteration.
    basis : str
        Weight basis when the model is built from a single PSF.
    step_scale, penalty_scale : float
        Initial ``ε⁽ⁱ⁾ = step_scale / L`` and ``η⁽ⁱ⁾ = penalty_scale · L``, ``L = max |K̂|²``.
    kappa_init : float
        Initial dual step ``κ⁽ⁱ⁾``.
    """

    iterations: int = 10
    schedule: str = "last-k"
    eigen_last: int = 2
    prior: UNetConfig = field(default_factory=UNetConfig)
    basis: str = "paper"
    step_scale: float = 1.0
    penalty_scale: float = 0.5
    kappa_init: float = 1.0


@dataclass(frozen=True)
class LeADMMUConfig:
    """Le-ADMM-U (Monakhova et al. 2019): unrolled DiffuserCam ADMM, then a U-Net. Initial
    ``μ1 = mu1_init``, ``μ2 = mu2_scale·L``, ``μ3 = mu3_scale·L``, ``τ = tau_scale·μ2``
    (``L = max |K̂|²``)."""

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

    ``copies`` PSFs per colour (paper: 5), each initialised from the measured PSF;
    ``hidden_factor`` scales the width of the 3×3 grouped convolutions of the updates;
    ``primal_grid`` is ``"sensor"`` or ``"padded"`` (the reference's scene grid; same PSNR on
    the varying bench at 1.15–1.5× the time, docs/baselines.md).
    """

    iterations: int = 10
    copies: int = 5
    hidden_factor: int = 1
    primal_grid: str = "sensor"
    denoiser: UNetConfig = field(default_factory=lambda: UNetConfig(
        widths=(15, 30, 60, 120, 240)))


@dataclass(frozen=True)
class TrainingConfig:
    """Optimisation settings (paper, Sec. 5.2; the batch size 4 is our choice).

    ``kernel_lr_scale`` multiplies the learning rate of the physics kernels, whose pixels are
    ~1e-4–1e-3: the network's rate would wipe them out in a few steps.
    """

    epochs: int = 200
    batch_size: int = 4
    lr: float = 1e-4
    gamma: float = 0.95
    kernel_lr_scale: float = 1e-2


@dataclass(frozen=True)
class Preset:
    """Configurations of the three models and the sensor size they are meant for.

    ``recipes``: a network's own training settings, replacing ``training``'s for it (its
    authors' where published, else the best of a sweep; docs/baselines.md).
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
    """Where EK-DUN uses the eigen-kernel model: ``(for f⁰, for each iteration)``.

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
