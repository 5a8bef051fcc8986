"""Where did a kernel change go? Gain, pedestal, displacement and the rest (:func:`split_change`).

The change ``Δ = L − I`` of a kernel (learned ``L`` against a reference ``I``, initial or
measured) is split, in this order, into

1. **gain** ``G = γ·I·S``, ``γ = Σ_S L / Σ_S I − 1``: the energy change on the caustic;
2. **pedestal** ``P = (Δ − G)·(1 − S)``: outside the support ``S`` (the measured kernels'
   dilated caustic), e.g. the floor that Adam grows on near-zero pixels;
3. **displacement** ``D = α·S·(1 + γ)·(warp(I, F) − I)``, ``F`` the dense flow from ``I`` to
   ``L``, ``α ∈ [0, 1]`` its least-squares amount;
4. **other** ``O = S·(Δ − G) − D`` (new spots, changed shapes).

``G + P + D + O = Δ`` exactly; each part's *fraction* is its L1 norm ``Σ|part|`` over the sum
of the four. ``outside_mass_fraction``: the share of ``Σ|L|`` outside ``S``.
"""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from psfkit.calibration.preprocess import luminance
from psfkit.calibration.warp import dense_flow
from psfkit.errors import InvalidInputError

#: Parts of a kernel change, in the order they are taken off.
PARTS = ("gain", "pedestal", "displacement", "other")


def _warp(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``image(x − F(x))``: ``image`` moved by the flow ``F`` ``(2, H, W)`` = (u, v) px."""
    h, w = image.shape
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    return cv2.remap(image.astype(np.float32), xx - flow[0], yy - flow[1], cv2.INTER_CUBIC,
                     borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)


def split_change(learned: np.ndarray, reference: np.ndarray, support: np.ndarray,
                 flow_method: str = "dis", smooth_px: float = 1.0) -> dict[str, Any]:
    """Split the change ``learned − reference`` of one kernel (see the module docstring).

    Parameters
    ----------
    learned, reference : numpy.ndarray
        ``(C, H, W)`` or ``(H, W)`` kernels on one grid (split on luminance).
    support : numpy.ndarray
        ``(H, W)`` bool caustic support of the measured kernels.
    flow_method : str
        Dense-flow method (:func:`psfkit.calibration.warp.dense_flow`).
    smooth_px : float
        Gaussian σ (px) applied to the flow before warping (0: none).

    Returns
    -------
    dict
        ``gain`` (γ), ``total_gain`` (``ΣL/ΣI − 1``), ``fractions`` (part → share),
        ``change_rel`` (``‖Δ‖₁ / ‖I‖₁``), ``pedestal_fraction``, ``outside_mass_fraction``,
        ``flow_rms_px`` (on the support).
    """
    lum_l = luminance(learned) if np.ndim(learned) == 3 else np.asarray(learned, np.float32)
    lum_i = luminance(reference) if np.ndim(reference) == 3 else np.asarray(reference,
                                                                            np.float32)
    if lum_l.shape != lum_i.shape or support.shape != lum_i.shape:
        raise InvalidInputError("split_change needs two kernels and a support of one shape")
    lum_l = lum_l.astype(np.float64)
    lum_i = lum_i.astype(np.float64)
    s = support.astype(np.float64)
    total_i = float(lum_i.sum())
    if total_i <= 0:
        raise InvalidInputError("split_change: the reference kernel has no energy")
    total_gain = float(lum_l.sum()) / total_i - 1.0
    on_i = float((lum_i * s).sum())
    gamma = float((lum_l * s).sum()) / on_i - 1.0 if on_i > 0 else total_gain
    delta = lum_l - lum_i
    gain = gamma * lum_i * s
    rest = delta - gain
    pedestal = rest * (1.0 - s)
    inside = rest * s
    ref32 = np.clip(lum_i, 0, None).astype(np.float32)
    oth32 = np.clip(lum_l / (1.0 + gamma) if gamma > -1 else lum_l, 0, None).astype(np.float32)
    flow = dense_flow(ref32, oth32, flow_method)
    if smooth_px > 0:
        flow = np.stack([cv2.GaussianBlur(f, (0, 0), smooth_px) for f in flow])
    moved = s * (1.0 + gamma) * (_warp(ref32, flow).astype(np.float64) - lum_i)
    # least-squares amount of the flow's change in the inside change, in [0, 1]: a flow that
    # DIS finds in noise (or in a pure pedestal) explains nothing and is not counted
    norm = float(np.sum(moved ** 2))
    alpha = float(np.clip(np.sum(moved * inside) / norm, 0.0, 1.0)) if norm > 0 else 0.0
    displacement = alpha * moved
    other = inside - displacement
    energies = {name: float(np.sum(np.abs(part))) for name, part in
                zip(PARTS, (gain, pedestal, displacement, other), strict=True)}
    total = sum(energies.values())
    fractions = {k: (v / total if total > 0 else 0.0) for k, v in energies.items()}
    mass = float(np.abs(lum_l).sum())
    return {
        "gain": gamma,
        "total_gain": total_gain,
        "fractions": fractions,
        "change_rel": float(np.abs(delta).sum() / max(float(np.abs(lum_i).sum()), 1e-30)),
        "pedestal_fraction": fractions["pedestal"],
        "outside_mass_fraction": float(np.abs(lum_l)[~support].sum()) / mass if mass else 0.0,
        "flow_rms_px": float(np.sqrt(np.mean(np.sum(flow[:, support] ** 2, axis=0))))
        if support.any() else 0.0,
    }


def split_kernel_changes(learned: np.ndarray, reference: np.ndarray, support: np.ndarray,
                         names: tuple[str, ...], flow_method: str = "dis"
                         ) -> dict[str, dict[str, Any]]:
    """:func:`split_change` for every kernel of ``(K, C, H, W)`` sets; keyed by ``names``,
    plus ``"all"``: the kernels' pedestal fraction and outside mass fraction pooled."""
    if learned.shape != reference.shape or len(names) != len(learned):
        raise InvalidInputError("split_kernel_changes needs two kernel sets of one shape")
    out = {name: split_change(lk, rk, support, flow_method)
           for name, lk, rk in zip(names, learned, reference, strict=True)}
    lum_l = np.stack([luminance(k) for k in learned]).astype(np.float64)
    lum_i = np.stack([luminance(k) for k in reference]).astype(np.float64)
    delta = np.abs(lum_l - lum_i)
    out_energy = float(delta[:, ~support].sum())
    change = float(delta.sum())
    mass = float(np.abs(lum_l).sum())
    out["all"] = {"pedestal_share_of_change": out_energy / change if change > 0 else 0.0,
                  "outside_mass_fraction": float(np.abs(lum_l)[:, ~support].sum()) / mass
                  if mass else 0.0}
    return out
