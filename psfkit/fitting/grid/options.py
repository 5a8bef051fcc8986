"""The options of ``psfkit fit-eigen`` (:class:`EigenFitOptions`), checked as they are made;
every message names the command's flag.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from psfkit.calibration.alignment import MIN_QUALITY
from psfkit.calibration.preprocess import PreprocessOptions
from psfkit.choices import CV_BASES, SHIFT_MODES
from psfkit.errors import ConfigurationError
from psfkit.fitting.grid.eigen import DEFAULT_RIDGE
from psfkit.forward.kernelfile import CONVENTIONS
from psfkit.forward.weights import get_basis

#: ``EigenFitOptions.basis`` (``psfkit fit-eigen --basis auto``): the verdict's model.
AUTO = "auto"


@dataclass(frozen=True)
class EigenFitOptions:
    """Options of :func:`psfkit.fitting.grid.fit.fit_eigen_grid`.

    Attributes
    ----------
    basis : str
        Weight basis of the fitted model, or ``"auto"``: basis *and* convention of the verdict,
        after cross-validating every basis of :data:`psfkit.choices.CV_BASES_ALL`.
    convention : {"sensor", "source", "auto"}
        Convention fitted at full resolution and written (``"auto"``: both, the one with the lower
        cross-validated error written); both are always compared on the working copy.
    gain_compensate : bool
        Divide every PSF by its gain before fitting (kernels then describe shape only).
    cv_bases : tuple of str
        Bases compared by leave-positions-out cross-validation (empty: no CV).
    folds : int
        Cross-validation groups of positions.
    working_size : int
        Longest side (px) of the working copy used for CV, residuals and PCA.
    ridge : float
        Weight of the prior pulling correction kernels towards the base kernel.
    min_quality : float
        Positions registering below this quality (NCC) are excluded.
    strict : bool
        A position failing a quality check ends the fit.
    shifts : {"affine", "registered"}
        Where each PSF is placed: ``"affine"`` at the affine field-to-shift map of the reliable
        positions (the forward model's geometry: distortion and deformation stay in the kernels),
        ``"registered"`` at its own registered shift.
    """

    basis: str = "paper"
    convention: str = "sensor"
    gain_compensate: bool = False
    cv_bases: tuple[str, ...] = CV_BASES
    folds: int = 9
    working_size: int = 256
    ridge: float = DEFAULT_RIDGE
    upsample: int = 100
    preprocess: PreprocessOptions = field(default_factory=PreprocessOptions)
    min_quality: float = MIN_QUALITY
    strict: bool = False
    shifts: str = "affine"

    def __post_init__(self) -> None:
        # every message names the flag of psfkit fit-eigen, never a Python field
        basis = () if self.basis == AUTO else (self.basis,)
        for flag_name, names in (("--basis", basis), ("--cv-bases", self.cv_bases)):
            for name in names:
                try:
                    get_basis(name)
                except ConfigurationError as exc:
                    raise ConfigurationError(f"{flag_name}: {exc}") from None
        if self.convention not in (*CONVENTIONS, "auto"):
            raise ConfigurationError(f"--convention must be one of {', '.join(CONVENTIONS)} "
                                     f"or auto, got {self.convention!r}")
        if self.shifts not in SHIFT_MODES:
            raise ConfigurationError(f"--shifts must be one of {', '.join(SHIFT_MODES)}, got "
                                     f"{self.shifts!r}")
        if self.folds < 2:
            raise ConfigurationError(f"--folds must be >= 2, got {self.folds}")
        if self.working_size < 32:
            raise ConfigurationError("EigenFitOptions: working_size must be >= 32 (no flag "
                                     "sets it)")
