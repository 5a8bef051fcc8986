r"""Uncertainty and significance of fitted field quantities.

Every quantity fitted over the field is an :class:`Estimate`: value, 1σ, the value without the
effect (*null*) and the p-value of a test of the model with the effect against the one without:

    **significant** ⇔ the estimate is determined, ``|value − null| > Z·σ``, and the test's
    p-value is below ``α(Z) = 2·(1 − Φ(Z))`` (the two-sided normal tail of ``Z``).

``Z`` = :data:`Z_SIGNIFICANT` was calibrated on the virtual bench's field-free camera
(``research/significance.py``). An estimate the data cannot give (too few positions, singular
design, non-finite or absurd value) is *not determined* and never shown as a bare number.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import special

#: ``Z`` of the significance rule (module docstring).
Z_SIGNIFICANT = 3.0


def alpha(z: float = Z_SIGNIFICANT) -> float:
    """Two-sided normal tail ``2·(1 − Φ(z))``: the largest p-value a significant effect's test
    may have."""
    return math.erfc(z / math.sqrt(2.0))


@dataclass(frozen=True)
class Estimate:
    """A fitted quantity with its 1σ uncertainty and the verdict of the significance rule.

    Attributes
    ----------
    value, sigma : float
        The estimate and its 1σ uncertainty (same unit).
    null : float
        The value without the effect.
    p_value : float
        Of the test with vs without the effect (NaN: none was possible).
    reason : str
        Why the estimate is not determined ("" when it is).
    """

    value: float
    sigma: float
    null: float = 0.0
    p_value: float = math.nan
    reason: str = ""

    @property
    def determined(self) -> bool:
        return not self.reason

    @property
    def z(self) -> float:
        """``|value − null| / σ`` (NaN when not determined)."""
        if not self.determined:
            return math.nan
        return abs(self.value - self.null) / self.sigma if self.sigma > 0 else math.inf

    @property
    def significant(self) -> bool:
        return bool(self.determined and self.z > Z_SIGNIFICANT
                    and math.isfinite(self.p_value) and self.p_value < alpha())

    @property
    def status(self) -> str:
        """``"significant"``, ``"not significant"`` or ``"not determined"``."""
        if not self.determined:
            return "not determined"
        return "significant" if self.significant else "not significant"

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready; a quantity that is not determined has ``value`` and ``sigma`` null."""
        out: dict[str, Any] = {
            "value": self.value if self.determined else None,
            "sigma": self.sigma if self.determined else None,
            "null": self.null, "z": self.z if self.determined else None,
            "p_value": self.p_value if math.isfinite(self.p_value) else None,
            "significant": self.significant, "status": self.status}
        if self.reason:
            out["reason"] = self.reason
        return out

    def number(self, fmt: str = ".3g", unit: str = "") -> str:
        """``value ± sigma`` (with ``unit``), or ``not determined``."""
        if not self.determined:
            return "not determined"
        unit = f" {unit}" if unit else ""
        return f"{format(self.value, fmt)} ± {format(self.sigma, fmt)}{unit}"

    def text(self, fmt: str = ".3g", unit: str = "") -> str:
        """For people: ``4.00 ± 0.05``; ``not detected (0.3 ± 1.2)``; ``not determined
        (reason)``. Never a bare number, never ``nan``."""
        if not self.determined:
            return f"not determined ({self.reason})"
        number = self.number(fmt, unit)
        return number if self.significant else f"not detected ({number})"


def undetermined(reason: str, null: float = 0.0) -> Estimate:
    """An :class:`Estimate` the data cannot give (``reason`` says why)."""
    return Estimate(math.nan, math.nan, null, math.nan, reason)


def checked(value: float, sigma: float, null: float = 0.0, p_value: float = math.nan,
            limit: float = math.inf) -> Estimate:
    """An :class:`Estimate`, not determined when ``value`` or ``sigma`` is not finite, σ is
    not positive, or ``|value|`` exceeds ``limit``."""
    value, sigma = float(value), float(sigma)
    if not (math.isfinite(value) and math.isfinite(sigma)) or sigma <= 0:
        return undetermined("the fit leaves it undetermined (infinite or zero uncertainty)",
                            null)
    if abs(value) > limit:
        return undetermined(f"the fitted value {value:.3g} is outside the plausible range "
                            f"±{limit:g}", null)
    return Estimate(value, sigma, null, float(p_value))


def f_test(rss_null: float, rss_full: float, extra_parameters: int, residual_dof: int
           ) -> float:
    """p-value of the F-test of a least-squares model against the nested model without its
    ``extra_parameters`` (``residual_dof``: observations minus the full model's parameters);
    NaN when the test is not possible."""
    if extra_parameters < 1 or residual_dof < 1 or not (rss_null >= 0 and rss_full >= 0):
        return math.nan
    if rss_full <= 0:
        return 0.0 if rss_null > 0 else 1.0
    f = max(rss_null - rss_full, 0.0) / extra_parameters / (rss_full / residual_dof)
    # the F distribution's tail (scipy.stats costs 0.4 s of start-up per command)
    return float(special.betainc(residual_dof / 2.0, extra_parameters / 2.0,
                                 residual_dof / (residual_dof + extra_parameters * f)))


def t_test(mean: float, sem: float, dof: int) -> float:
    """Two-sided p-value of Student's t-test of ``mean / sem`` with ``dof`` degrees of
    freedom (NaN when not possible)."""
    if dof < 1 or not sem > 0:
        return math.nan
    t2 = (mean / sem) ** 2
    return float(special.betainc(dof / 2.0, 0.5, dof / (dof + t2)))


def weighted_lstsq(design: np.ndarray, values: np.ndarray, weights: np.ndarray
                   ) -> tuple[np.ndarray, np.ndarray, float, int]:
    """Weighted least squares with the residual-scaled covariance of the coefficients.

    Parameters
    ----------
    design : numpy.ndarray
        ``(N, P)``.
    values : numpy.ndarray
        ``(N,)`` or ``(N, D)`` (``D`` outputs sharing the design and the noise level).
    weights : numpy.ndarray
        ``(N,)`` relative weights (scale-free).

    Returns
    -------
    coef : numpy.ndarray
        ``(P,)`` or ``(P, D)``.
    covariance : numpy.ndarray
        ``(P, P)``: ``s² (Xᵀ W X)⁻¹``, ``s²`` the weighted residual variance pooled over the
        outputs (``inf`` without residual degrees of freedom).
    rss : float
        Weighted residual sum of squares, all outputs.
    dof : int
        Residual degrees of freedom, all outputs.
    """
    sw = np.sqrt(weights)[:, None]
    x = design * sw
    y = values * (sw if values.ndim == 2 else sw[:, 0])
    coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    resid = y - x @ coef
    outputs = 1 if values.ndim == 1 else values.shape[1]
    dof = outputs * (len(values) - design.shape[1])
    rss = float(np.sum(resid**2))
    s2 = rss / dof if dof > 0 else math.inf
    covariance = s2 * np.linalg.pinv(x.T @ x)
    return coef, covariance, rss, dof
