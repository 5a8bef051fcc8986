"""Options of the pairs fit (:func:`psfkit.fitting.pairs.fit.fit_pairs`), without torch (so
``psfkit fit-pairs --help`` does not import it).
"""

from __future__ import annotations

from dataclasses import dataclass

from psfkit.errors import ConfigurationError
from psfkit.forward.geometry import CONVENTIONS
from psfkit.forward.weights import get_basis

SUPPORTS = ("none", "auto", "mask")
#: Projected Newton-CG (the non-negative solve): most steps, CG iterations per step, and the
#: default tolerance of the relative KKT (natural) residual
#: (:func:`psfkit.fitting.pairs.constraints.projected_newton`; ``PairFitOptions.tolerance``).
#: 1e-6: the predictions of the pairs then lie within 3e-5 of the measurement's norm from
#: those of a 1e-10 solve, in about 40 % of the steps; what still moves are kernel directions
#: the pairs barely see (research/notes/forward-model-studies.md).
NEWTON_ITERATIONS = 100
NEWTON_CG_ITERATIONS = 20
NEWTON_TOLERANCE = 1e-6


@dataclass(frozen=True)
class PairFitOptions:
    """Options of :func:`fit_pairs`.

    Attributes
    ----------
    basis : str
        ``"si"`` (one shift-invariant PSF) or an eigen-kernel basis.
    convention : {"auto", "sensor", "source"}
        Where the weights live; ``"auto"``: the one predicting held-out pairs better
        (:func:`~psfkit.fitting.pairs.regularisation.convention_record`; source unless sensor
        wins by more than ``TIE`` and one standard error).
    tikhonov : float or None
        ``λ`` relative to the mean scene power; ``None``: chosen by held-out error (for
        eigen-kernels after ``difference``, a conditioning ridge of at most 0.01:
        :data:`~psfkit.fitting.pairs.regularisation.CONDITIONING_PATH`).
    difference : float or None
        ``μ`` (pull of the corrections towards the base kernel), relative likewise; ``None``:
        chosen by held-out error for eigen-kernels.
    iterations : int, optional
        Most CG iterations of the final solve (a cap; default 2000).
    scale_iterations : int
        Most CG iterations of each scale-estimating round (each solved to ``tolerance`` too).
    tolerance : float
        Relative residual of the normal equations to stop at; for non-negative kernels, the
        relative KKT residual (its float32 start solved to ``START_TOLERANCE``).
    fit_scale : bool
        Estimate one scale per pair (per-image normalised ground truth).
    rounds : int
        Kernel solves in all when scales are fitted.
    scene_padding : int
        Convolution grid as a multiple of the sensor size.
    seed_with_si : bool
        Start an eigen-kernel fit from a shift-invariant fit (only a warm start).
    nonneg : bool
        Non-negative kernels, by projected Newton-CG from the unconstrained solution.
    support : {"none", "auto", "mask"}
        Kernels zero outside a footprint: ``"auto"`` from the unconstrained base kernel
        (:func:`~psfkit.fitting.pairs.constraints.auto_support`), ``"mask"`` the given mask.
    support_threshold : float
        ``"auto"`` support: fraction of the smoothed ``|K|``'s maximum kept.
    projected_iterations : int, optional
        Most Newton steps of the non-negative solve.
    """

    basis: str = "si"
    convention: str = "auto"
    tikhonov: float | None = None
    difference: float | None = None
    iterations: int | None = None
    scale_iterations: int = 2000
    tolerance: float = NEWTON_TOLERANCE
    fit_scale: bool = True
    rounds: int = 3
    scene_padding: int = 2
    seed_with_si: bool = False
    nonneg: bool = True
    support: str = "none"
    support_threshold: float = 0.1
    projected_iterations: int | None = None

    @property
    def solver(self) -> str:
        """The final solve: ``"newton"`` for non-negativity, else ``"cg"`` (restricted to a support
        if any)."""
        return "newton" if self.nonneg else "cg"

    @property
    def automatic(self) -> tuple[str, ...]:
        """The weights chosen by held-out error, in order, each unless given: one PSF's ridge;
        eigen-kernels' difference prior, then their ridge (without one, the kernel directions
        the pairs barely see are left to where the non-negative solve stops, and it spends
        most of its steps on them: research/notes/forward-model-studies.md)."""
        if self.conditioning_ridge:
            return tuple(p for p, w in (("difference", self.difference),
                                        ("tikhonov", self.tikhonov)) if w is None)
        return ("tikhonov",) if self.tikhonov is None else ()

    @property
    def conditioning_ridge(self) -> str | None:
        """The weight that only conditions the solve, chosen on ``CONDITIONING_PATH``:
        eigen-kernels' ridge (one PSF's ridge is its prior)."""
        return "tikhonov" if get_basis(self.basis).n_kernels > 1 else None

    def weights(self) -> dict[str, float]:
        """The relative weights as given (0 where neither given nor chosen automatically)."""
        return {"tikhonov": self.tikhonov or 0.0, "difference": self.difference or 0.0}

    @property
    def constrained(self) -> bool:
        """Whether the final solve has a constraint (non-negativity or a support)."""
        return self.nonneg or self.support != "none"

    @property
    def final_iterations(self) -> int:
        return self.iterations if self.iterations is not None else 2000

    @property
    def final_projected_iterations(self) -> int:
        return NEWTON_ITERATIONS if self.projected_iterations is None else self.projected_iterations

    def __post_init__(self) -> None:
        # every message names the flag of psfkit fit-pairs (the ranges of FLAGS in
        # psfkit.io.validation), never a Python field
        try:
            get_basis(self.basis)
        except ConfigurationError as exc:
            raise ConfigurationError(f"--basis: {exc}") from None
        if self.convention not in (*CONVENTIONS, "auto"):
            raise ConfigurationError(f"--convention must be one of {', '.join(CONVENTIONS)}, "
                                     f"auto, got {self.convention!r}")
        if (self.tikhonov or 0.0) < 0 or (self.difference or 0.0) < 0:
            raise ConfigurationError("--tikhonov and --difference must be >= 0")
        if self.final_iterations < 1:
            raise ConfigurationError(f"--iterations must be >= 1, got {self.iterations}")
        if self.scale_iterations < 1 or self.rounds < 1 or self.scene_padding < 2:
            raise ConfigurationError("PairFitOptions: scale_iterations and rounds must be >= 1, "
                                     "scene_padding >= 2 (no flag sets them)")
        if self.support not in SUPPORTS:
            raise ConfigurationError(f"--support must be one of {', '.join(SUPPORTS)}, got "
                                     f"{self.support!r}")
        if not 0 <= self.support_threshold < 1:
            raise ConfigurationError(f"--support-threshold must be in [0, 1), got "
                                     f"{self.support_threshold}")
        if self.final_projected_iterations < 1:
            raise ConfigurationError(f"--projected-iterations must be >= 1, got "
                                     f"{self.projected_iterations}")
