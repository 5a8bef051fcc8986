"""Options of a learned-vs-measured comparison (:class:`CompareOptions`)."""

from __future__ import annotations

from dataclasses import dataclass, field

from psfkit.calibration.preprocess import PreprocessOptions
from psfkit.calibration.warp import FLOW_METHODS
from psfkit.errors import ConfigurationError
from psfkit.fitting.grid.options import EigenFitOptions


@dataclass(frozen=True)
class CompareOptions:
    """Options of :func:`compare_kernels`.

    Attributes
    ----------
    flow_method : str
        Dense-flow method (:func:`psfkit.calibration.warp.dense_flow`).
    smooth_px : float
        σ (px) of the masked Gaussian applied to every displacement map (flows on caustics are
        noisy off the bright lines).
    mask_level, mask_border, mask_dilate : float, int, int
        Caustic mask of the measured ``Kbase`` (:func:`psfkit.calibration.caustic.caustic_mask`).
    min_displacement_px : float
        A map whose RMS over the mask is below this counts as "no displacement" (NaN
        correlations).
    n_pca : int
        Measured PCA modes compared with (0: the number of kernels).
    warp_positions : {"axes", "all"}
        Warps from the outermost reliable positions on each kernel's axis, or from every
        reliable position solved jointly (research/compare/README.md).
    align : bool
        Register the learned ``Kbase`` to the measured one by a global sub-pixel shift first.
    fit : EigenFitOptions or None
        The measured fit's options (``None``: the learned file's basis and convention, no CV).
    """

    flow_method: str = "dis"
    smooth_px: float = 3.0
    mask_level: float = 0.02
    mask_border: int = 8
    mask_dilate: int = 3
    min_displacement_px: float = 0.02
    n_pca: int = 0
    warp_positions: str = "axes"
    align: bool = True
    fit: EigenFitOptions | None = None
    preprocess: PreprocessOptions = field(default_factory=PreprocessOptions)

    def __post_init__(self) -> None:
        if self.flow_method not in FLOW_METHODS:
            raise ConfigurationError(f"unknown flow method {self.flow_method!r} "
                                     f"(use {', '.join(FLOW_METHODS)})")
        if self.warp_positions not in ("all", "axes"):
            raise ConfigurationError(f"warp_positions must be 'all' or 'axes', got "
                                     f"{self.warp_positions!r}")
        if self.smooth_px < 0 or self.min_displacement_px < 0 or self.n_pca < 0:
            raise ConfigurationError("smooth_px, min_displacement_px and n_pca must be >= 0")
