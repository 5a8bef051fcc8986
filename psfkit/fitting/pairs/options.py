"""Options of the pairs fit (:func:`psfkit.fitting.pairs.fit.fit_pairs`), without torch.

Kept apart from the solver so that ``psfkit fit-pairs --help`` (whose defaults come from here)
does not import torch.
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
        ``"si"`` (one shift-invariant PSF) or an eigen-kernel basis (``"paper"``, ...).
    convention : {"auto", "sensor", "source"}
        Where the weights of an eigen-kernel model live. ``"auto"`` (default): the one that
        predicts held-out pairs better, each at its own chosen regularisation, on the folds
        that choose it (:func:`psfkit.fitting.pairs.regularisation.convention_record`; the
        sensor side of Eq. 7 unless the source side is better by more than ``TIE``).
    tikhonov : float or None
        ``λ`` relative to the mean scene power (the mean over frequencies of the summed power
        of the scene spectra the kernels see). ``None`` (default): chosen by held-out error
        for a single PSF (``si``, :mod:`psfkit.fitting.pairs.regularisation`), 0 for
        eigen-kernels (whose difference prior is chosen instead). A ridge shrinks the kernels'
        spectra where the scenes carry little power and so biases them (at 1e-2, 46 % kernel
        error on noise-free pairs), so it is chosen only where the held-out pairs ask for it.
    difference : float or None
        ``μ`` (pull of the correction kernels towards the base kernel), relative likewise.
        ``None`` (default): chosen by held-out error for eigen-kernels (7 DLMD pairs do not
        determine ``Kv − Kbase`` and ``Kh − Kbase`` without it; hundreds of pairs do, and
        then it only biases them); irrelevant for ``si``.
    iterations : int, optional
        Most conjugate-gradient iterations of the final solve (scales fixed), which otherwise
        stops at ``tolerance``; default 2000 (a cap, not an early stop: the fit records its
        relative residual and whether it converged).
    scale_iterations : int
        Most conjugate-gradient iterations of each earlier round that re-estimates the scales
        (each round is solved to ``tolerance`` too: scales fitted to loosely solved kernels
        are off by a percent, and the next warm-started round then has nothing to do).
    tolerance : float
        Stop when the relative residual of the normal equations falls below this (default
        ``NEWTON_TOLERANCE``, 1e-6, in the float64 working precision); for non-negative
        kernels (projected Newton), the relative KKT residual of the non-negative solve, whose
        start (the unconstrained kernels and the scales) is then solved in float32 to
        :data:`psfkit.fitting.pairs.regularisation.FOLD_TOLERANCE` only.
    fit_scale : bool
        Estimate one scale per pair (per-image normalised ground truth).
    rounds : int
        Kernel solves in all when scales are fitted (``rounds − 1`` scale updates).
    scene_padding : int
        Convolution grid as a multiple of the sensor size.
    seed_with_si : bool
        Start an eigen-kernel fit from a shift-invariant fit (every kernel = the PSF, and its
        scales). Only a warm start: the solve runs to ``tolerance`` from any start, so it is
        off by default.
    nonneg : bool
        Constrain the kernels to be non-negative (a measured PSF is): the final solve is then
        projected Newton-CG (:func:`psfkit.fitting.pairs.constraints.projected_newton`), warm
        started from the unconstrained conjugate-gradient solution.
    support : {"none", "auto", "mask"}
        Kernels are zero outside a footprint: ``"auto"`` derives it from the unconstrained base
        kernel (the SI fit for ``si``; :func:`~psfkit.fitting.pairs.constraints.auto_support`),
        ``"mask"`` takes the mask passed to :func:`~psfkit.fitting.pairs.fit.fit_pairs`.
    support_threshold : float
        ``"auto"`` support: fraction of the smoothed ``|K|``'s maximum kept.
    projected_iterations : int, optional
        Most Newton steps of the non-negative solve (default ``NEWTON_ITERATIONS``).

    One solver per problem (:attr:`solver`): conjugate gradients on the normal equations for the
    unconstrained kernels (restricted to the support, an exact solve, when there is one without
    non-negativity), and projected Newton-CG
    (:func:`psfkit.fitting.pairs.constraints.projected_newton`) to a KKT residual of
    ``tolerance`` for non-negativity (with or without a support): the non-negative least squares
    itself.
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
        """The final solve: ``"newton"`` for non-negativity (with or without a support),
        ``"cg"`` (conjugate gradients, restricted to the support if any) otherwise."""
        return "newton" if self.nonneg else "cg"

    @property
    def automatic(self) -> tuple[str, ...]:
        """The weights chosen by held-out error (:mod:`psfkit.fitting.pairs.regularisation`): the
        difference prior of eigen-kernels, the ridge of one PSF, each unless given."""
        if get_basis(self.basis).n_kernels > 1:
            return ("difference",) if self.difference is None else ()
        return ("tikhonov",) if self.tikhonov is None else ()

    def weights(self) -> dict[str, float]:
        """The relative weights as given, a weight not chosen automatically and not given
        being 0 (:attr:`automatic` replaces the others)."""
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
        if self.projected_iterations is not None:
            return self.projected_iterations
        return NEWTON_ITERATIONS

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
