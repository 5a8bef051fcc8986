r"""Weight maps of eigen-kernel forward models.

An eigen-kernel model writes the shift-variant PSF as a weighted sum of a few kernels,

.. math::

    h(u) = \Big(1 - \sum_{j\ge1}\varphi_j\Big) K_0 + \sum_{j\ge1} \varphi_j K_j,

with fixed weight functions :math:`\varphi_j` of normalized coordinates; all weights sum to 1.
The paper's basis (Eq. 7) is ``"paper"``: :math:`\varphi_v = \tfrac12\sin^2(\tfrac\pi2 v_n)`,
:math:`\varphi_h = \tfrac12\sin^2(\tfrac\pi2 u_n)`, kernels ``(base, v, h)``. Richer bases add
``odd`` (:math:`\tfrac12\sin(\tfrac\pi2 v_n)`, :math:`\tfrac12\sin(\tfrac\pi2 u_n)`: asymmetric
variation), ``cross`` (:math:`\tfrac12\sin(\tfrac\pi2 u_n)\sin(\tfrac\pi2 v_n)`:
diagonal astigmatism), or are ``poly:N`` (monomials :math:`u_n^a v_n^b`,
:math:`1 \le a+b \le N`); ``si`` has no terms (one kernel, weight 1).

Coordinates: ``u`` = column, ``v`` = row; :math:`u_n = (u-u_c)/(W'/2)`,
:math:`v_n = (v-v_c)/(H'/2)`, optical centre ``(v_c, u_c)`` defaulting to
``((H'-1)/2, (W'-1)/2)``.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from psfkit.errors import ConfigurationError

AxisFunction = Callable[[np.ndarray], np.ndarray]


def _half_sin2(x: np.ndarray) -> np.ndarray:
    return 0.5 * np.sin(0.5 * np.pi * x) ** 2


def _half_sin(x: np.ndarray) -> np.ndarray:
    return 0.5 * np.sin(0.5 * np.pi * x)


@dataclass(frozen=True)
class WeightTerm:
    """One correction weight ``φ(u, v) = s · f(u_n) · g(v_n)`` (``None`` stands for 1).

    The eigen-kernel fit uses the factors to sum the weights' products as matrix products.
    """

    name: str
    of_u: AxisFunction | None = None
    of_v: AxisFunction | None = None
    scale: float = 1.0

    def __call__(self, u_norm: np.ndarray, v_norm: np.ndarray) -> np.ndarray:
        fu, fv = self.factors(u_norm, v_norm)
        if fu is None:
            return np.ones_like(u_norm) if fv is None else fv
        return fu if fv is None else fu * fv

    def factors(self, u_norm: np.ndarray, v_norm: np.ndarray
                ) -> tuple[np.ndarray | None, np.ndarray | None]:
        """``(s·f(u), g(v))`` (``None`` where 1), on 1-D coordinates or broadcasting ones."""
        fu = self.of_u(u_norm) if self.of_u is not None else None
        fv = self.of_v(v_norm) if self.of_v is not None else None
        if self.scale != 1.0:
            fu = np.full_like(u_norm, self.scale, dtype=np.float64) if fu is None \
                else self.scale * fu
        return fu, fv


_GROUPS: dict[str, tuple[WeightTerm, ...]] = {
    "paper": (WeightTerm("v", of_v=_half_sin2), WeightTerm("h", of_u=_half_sin2)),
    "odd": (WeightTerm("v_odd", of_v=_half_sin), WeightTerm("h_odd", of_u=_half_sin)),
    "cross": (WeightTerm("hv", of_u=_half_sin, of_v=_half_sin, scale=2.0),),
}


def _power(exponent: int) -> AxisFunction | None:
    return None if exponent == 0 else (lambda x: x**exponent)


def _poly_terms(order: int) -> tuple[WeightTerm, ...]:
    terms = []
    for degree in range(1, order + 1):
        for a in range(degree, -1, -1):
            b = degree - a
            terms.append(WeightTerm(f"u{a}v{b}", of_u=_power(a), of_v=_power(b)))
    return tuple(terms)


@dataclass(frozen=True)
class WeightBasis:
    """A named set of weight functions ``φ_j(u_n, v_n)`` (the base kernel's weight is implied).

    Attributes
    ----------
    name : str
        Canonical name, e.g. ``"paper"`` or ``"paper+odd"``.
    terms : tuple of WeightTerm
        The correction terms.
    """

    name: str
    terms: tuple[WeightTerm, ...]

    @property
    def kernel_names(self) -> tuple[str, ...]:
        """``("base", <term names>...)``, the order of kernels in a kernel file."""
        return ("base", *(term.name for term in self.terms))

    @property
    def n_kernels(self) -> int:
        return 1 + len(self.terms)

    def evaluate(self, u_norm: np.ndarray, v_norm: np.ndarray) -> np.ndarray:
        """Weights of all kernels at normalized coordinates, ``(K, *broadcast shape)``.

        The first is the base weight ``1 − Σ φ_j``. Separable coordinates (``u`` ``(1, W)``, ``v``
        ``(H, 1)``) evaluate the 1-D terms on a row and a column only.
        """
        u_norm = np.asarray(u_norm, dtype=np.float64)
        v_norm = np.asarray(v_norm, dtype=np.float64)
        shape = np.broadcast_shapes(u_norm.shape, v_norm.shape)
        phis = [np.broadcast_to(term(u_norm, v_norm), shape) for term in self.terms]
        out = np.empty((1 + len(phis), *shape))
        out[0] = 1.0
        for k, phi in enumerate(phis, start=1):
            out[k] = phi
            out[0] -= phi
        return out

    def maps(self, sensor_shape: tuple[int, int],
             optical_center: tuple[float, float] | None = None,
             extent: tuple[int, int] | None = None) -> np.ndarray:
        """Weight maps on the ``(H', W')`` grid, ``(K, H', W')`` float64.

        Sensor side they multiply each kernel's image; source side the sensor-sized scene. With
        ``extent`` ``(H, W)`` the maps cover that larger centred grid (the padded scene's), each
        pixel outside the sensor taking the nearest sensor pixel's weights (the model is fitted on
        the sensor only, so the edge kernels continue rather than the periodic terms turning back).
        """
        u_norm, v_norm = separable_coordinates(sensor_shape, optical_center)
        maps = self.evaluate(u_norm, v_norm)                  # (K, H', W')
        if extent is None:
            return maps
        h, w = sensor_shape
        eh, ew = extent
        if eh < h or ew < w:
            raise ConfigurationError(f"extent {eh}x{ew} is smaller than the sensor {h}x{w}")
        top, left = (eh - h) // 2, (ew - w) // 2        # as psfkit.forward.geometry.centre_offset
        return np.pad(maps, ((0, 0), (top, eh - h - top), (left, ew - w - left)), mode="edge")


def separable_coordinates(sensor_shape: tuple[int, int],
                          optical_center: tuple[float, float] | None = None
                          ) -> tuple[np.ndarray, np.ndarray]:
    """Normalized coordinates ``(u_n, v_n)`` (±1 at the sensor edges) as a ``(1, W)`` row and an
    ``(H, 1)`` column; ``optical_center`` ``(v_c, u_c)`` defaults to the sensor centre."""
    h, w = sensor_shape
    v_c, u_c = optical_center if optical_center is not None else ((h - 1) / 2, (w - 1) / 2)
    return ((np.arange(w) - u_c) / (w / 2))[None, :], ((np.arange(h) - v_c) / (h / 2))[:, None]


_BASIS_RE = re.compile(r"^(si|poly:[1-9]|paper(\+odd)?(\+cross)?)$")


def get_basis(name: str) -> WeightBasis:
    """The :class:`WeightBasis` called ``name``: ``si``, ``paper``, ``paper+odd``, ``paper+cross``,
    ``paper+odd+cross`` or ``poly:N`` (N = 1..9)."""
    if not isinstance(name, str) or not _BASIS_RE.match(name):
        raise ConfigurationError(
            f"unknown weight basis {name!r} (use si, paper, paper+odd, paper+cross, "
            "paper+odd+cross or poly:N)")
    if name == "si":
        return WeightBasis("si", ())
    if name.startswith("poly:"):
        return WeightBasis(name, _poly_terms(int(name.split(":")[1])))
    terms: tuple[WeightTerm, ...] = ()
    for group in name.split("+"):
        terms += _GROUPS[group]
    return WeightBasis(name, terms)


BASIS_NAMES = ("si", "paper", "paper+odd", "paper+cross", "paper+odd+cross", "poly:1",
               "poly:2", "poly:3")
