"""Terminal lines of fitted field quantities and of the verdict.

Every fitted field quantity is printed with its 1σ uncertainty and what the significance rule
(:mod:`psfkit.numerics.significance`) says of it: ``4.00 ± 0.05``, ``not detected (0.3 ± 1.2)`` or
``not determined (why)``; never a bare number, never ``nan``.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from psfkit.calibration.gain import GainFit
    from psfkit.calibration.shift_map import ShiftMapFit
    from psfkit.calibration.warp import GrowthFit
    from psfkit.characterization.results import GridCharacterization
    from psfkit.fitting.verdict import Verdict


def shift_map_line(fit: ShiftMapFit) -> str:
    """``shift map: magnification …, rotation …, offset …, non-linear distortion …``."""
    est = fit.estimates
    return (f"shift map: magnification {est['magnification'].text('.6g')} px per "
            f"{fit.field_units}, rotation {est['rotation_deg'].text('.4g', 'deg')} "
            f"(180 = inverted image), offset ({fit.offset[0]:+.3f}, {fit.offset[1]:+.3f}) px, "
            f"distortion beyond the affine map {fit.distortion.text('.3g', 'px rms')}, "
            f"residual {fit.rms_residual:.3f} px rms")


def gain_line(fit: GainFit) -> str:
    """``vignetting: gain = A cos^n(theta), n = …`` (gains include source brightness)."""
    return (f"vignetting: gain = A cos^n(theta), n = {fit.estimate.text('.3g')} (gains are "
            "energy ratios to the centre capture: they include any difference in source "
            "brightness)")


def growth_line(growth: GrowthFit | None) -> str:
    """``warp residual growth: …`` (its exponent only where the growth is significant)."""
    if growth is None:
        return "warp residual growth: not determined (fewer than four positions)"
    if not growth.significant:
        return f"warp residual growth above the floor: {growth.growth.text('.3g', 'px at 10 deg')}"
    return (f"warp residual grows as theta^p, p = {growth.exponent_estimate.text('.3g')}, "
            f"{growth.growth.text('.3g', 'px')} at 10 deg over a {growth.floor:.3f} px floor")


def astigmatism_line(result: GridCharacterization) -> str:
    """``tangential/sagittal ratio: …`` against geometric optics."""
    if result.astigmatism is None:
        return "tangential/sagittal ratio: not determined (no position far enough off axis)"
    anis = result.warp_anisotropy or {}
    geometric = anis.get("median_geometric")
    versus = f" (geometric optics {geometric:.2f})" if geometric is not None else ""
    return (f"tangential/sagittal ratio: {result.astigmatism.text('.3g')}{versus}, "
            f"{anis.get('positions', 0)} positions; 1 = no astigmatism")


def print_verdict(verdict: Verdict) -> None:
    """The verdict in plain words and its evidence, as the report's opening."""
    print(f"verdict: {verdict.sentence()}")
    evidence = verdict.evidence
    floor = evidence.get("noise_floor")
    if floor is not None:
        print(f"  noise floor (held-out error of {floor['model']}): "
              f"{pm(floor['error'], floor['sigma'])} over {evidence.get('positions', 0)} "
              "held-out positions")
    test = evidence.get("field_test")
    if test is not None:
        model = evidence["field_models"][test["model"]]
        print(f"  best field model {test['model']}: held-out error "
              f"{pm(model['error'], model['sigma'])}; reduction of the relative squared error "
              f"per position {verdict.field_test.text('.2g')}, p = "
              f"{_p(verdict.field_test.p_value)}")


def pm(value: float, sigma: float, fmt: str = ".4f") -> str:
    """``value ± sigma`` (``(± n/a)`` when σ is not finite: fewer than two positions)."""
    if not math.isfinite(value):
        return "n/a"
    if math.isfinite(sigma):
        return f"{format(value, fmt)} ± {format(sigma, fmt)}"
    return f"{format(value, fmt)} (± n/a)"


def _p(value: float) -> str:
    return f"{value:.2g}" if math.isfinite(value) else "n/a"
