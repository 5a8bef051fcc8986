r"""Weight maps of eigen-kernel forward models.

An eigen-kernel model writes the shift-variant PSF as a weighted sum of a few kernels,

.. math::

    h(u) = \Big(1 - \sum_{j\ge1}\varphi_j\Big) K_0 + \sum_{j\ge1} \varphi_j K_j
         = K_0 + \sum_{j\ge1}\varphi_j\,(K_j - K_0),

with fixed weight functions :math:`\varphi_j` of normalized coordinates. The paper's model
(EK-DUN, Eq. 7) is the basis ``"paper"``: :math:`\varphi_v = W_v = \tfrac12\sin^2(\tfrac\pi2
v_\mathrm{norm})`, :math:`\varphi_h = W_h = \tfrac12\sin^2(\tfrac\pi2 u_\mathrm{norm})`, kernels
``(base, v, h)``. The weights of all kernels sum to 1 at every pixel.

Richer bases add terms (``get_basis`` parses ``"paper+odd+cross"``, ``"poly:3"``, ...):

``odd``
    :math:`\tfrac12\sin(\tfrac\pi2 v_n)`, :math:`\tfrac12\sin(\tfrac\pi2 u_n)`: variation that
    differs between the two sides of the axis (sin² is even and cannot see it).
``cross``
    :math:`\tfrac12\sin(\tfrac\pi2 u_n)\sin(\tfrac\pi2 v_n)`: the diagonal component of
    tangential astigmatism, whose stretch tensor at azimuth φ has a ``sin φ cos φ`` part.
``poly:N``
    all monomials :math:`u_n^a v_n^b`, :math:`1 \le a+b \le N` (a generic Taylor basis).
``si``
    no terms: the shift-invariant model (one kernel, weight 1).

Coordinates (``docs/architecture.md``): ``u`` = column, ``v`` = row of the sensor grid
``(H', W')``; :math:`u_n = (u-u_c)/(W'/2)`, :math:`v_n = (v-v_c)/(H'/2)`, optical centre
``(v_c, u_c)`` defaulting to ``((H'-1)/2, (W'-1)/2)``.
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
    """One correction weight, a product of a function of ``u_n`` and one of ``v_n``:
    ``φ(u, v) = s · f(u) · g(v)`` (``None`` stands for 1).

    Every weight of the bases here is such a product; the eigen-kernel fit uses the factors
    to sum the weights' products over a grid as matrix products (:mod:`psfkit.fitting.grid.eigen`).
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
        """``(s·f(u), g(v))`` (``None`` where the factor is 1); on 1-D coordinate arrays for
        the factors themselves, or on broadcasting ones for their product (``__call__``)."""
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
        The correction terms (kernel name and separable weight ``φ``).
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

        The first entry is the base weight ``1 − Σ φ_j``; all entries sum to 1. Pass
        separable coordinates (``u`` of shape ``(1, W)``, ``v`` of shape ``(H, 1)``) to evaluate
        the one-dimensional terms on a row and a column only.
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

        With the sensor-side convention they multiply each kernel's image on the sensor; with
        the source-side one they multiply the scene, whose array has the sensor's size and
        coordinates (``y = crop(K * pad(x))``).

        With ``extent`` ``(H, W)`` (at least the sensor's size) the maps cover that larger grid
        centred on the sensor, as the padded scene grid is (:func:`psfkit.forward.convolution.pad`),
        and outside the sensor each pixel takes the weights of the nearest sensor pixel: the
        model is fitted on the sensor-sized field only, so the edge kernels continue beyond it
        rather than the periodic ``sin²`` terms turning back towards the base kernel. A
        source-side model of a scene on the whole padded grid (light from outside the view)
        needs them.
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
    """Normalized coordinates ``(u_n, v_n)``, reaching ±1 at the sensor edges, as a ``(1, W)``
    row and a ``(H, 1)`` column, for cheap evaluation of separable weights.

    ``optical_center`` is ``(v_c, u_c)`` in sensor pixels; default the sensor centre."""
    h, w = sensor_shape
    v_c, u_c = optical_center if optical_center is not None else ((h - 1) / 2, (w - 1) / 2)
    return ((np.arange(w) - u_c) / (w / 2))[None, :], ((np.arange(h) - v_c) / (h / 2))[:, None]


_BASIS_RE = re.compile(r"^(si|poly:[1-9]|paper(\+odd)?(\+cross)?)$")


def get_basis(name: str) -> WeightBasis:
    """The :class:`WeightBasis` called ``name``.

    Accepted names: ``si``, ``paper``, ``paper+odd``, ``paper+cross``, ``paper+odd+cross``,
    ``poly:N`` (N = 1..9).
    """
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
