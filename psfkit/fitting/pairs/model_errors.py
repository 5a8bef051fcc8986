"""Where, and on which pairs, a forward model fails (``psfkit eval-model``): its relative errors
``‖y_i − s_i p_i‖/‖y_i‖`` (``s_i`` 1 or the best per pair) per field zone and per pixel, and
which pairs it was fitted on.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from psfkit.errors import InvalidInputError
from psfkit.forward.zones import ZONE_NAMES, FieldZones
from psfkit.io.pairs import parse_names

FITTED, HELD_OUT = "fitted", "held out"


def _flat_pairs(a: np.ndarray) -> np.ndarray:
    """``(N, C, H, W)`` → ``(N, C, H*W)`` float64."""
    return a.reshape(a.shape[0], a.shape[1], -1).astype(np.float64)


def zone_errors(prediction: np.ndarray, measurements: np.ndarray, zones: FieldZones,
                scale: np.ndarray) -> dict[str, np.ndarray]:
    """Relative prediction errors of each pair in each field zone.

    Parameters
    ----------
    prediction, measurements : numpy.ndarray
        ``(N, C, H, W)``: ``A x_i`` and ``y_i``.
    zones : FieldZones
        Zones of the ``(H, W)`` sensor.
    scale : numpy.ndarray
        ``(N,)`` best per-pair scales.

    Returns
    -------
    dict
        ``raw`` and ``scaled``, each ``(N, 3)`` in ``ZONE_NAMES`` order: ``‖(y − s p)_z‖ / ‖y_z‖``;
        not finite where the zone's measurement is zero.
    """
    if prediction.shape != measurements.shape or prediction.shape[-2:] != zones.shape:
        raise InvalidInputError(f"predictions {prediction.shape}, measurements "
                                f"{measurements.shape} and zones {zones.shape} disagree")
    p, y = _flat_pairs(prediction), _flat_pairs(measurements)
    labels = zones.labels.ravel()
    s = np.asarray(scale, dtype=np.float64)[:, None, None]
    out = {"raw": np.empty((len(p), len(ZONE_NAMES))),
           "scaled": np.empty((len(p), len(ZONE_NAMES)))}
    for z in range(len(ZONE_NAMES)):
        inside = labels == z
        yz, pz = y[..., inside], p[..., inside]
        norm = np.sqrt(np.sum(yz * yz, axis=(1, 2)))
        with np.errstate(invalid="ignore", divide="ignore"):
            out["raw"][:, z] = np.sqrt(np.sum((pz - yz) ** 2, axis=(1, 2))) / norm
            out["scaled"][:, z] = np.sqrt(np.sum((s * pz - yz) ** 2, axis=(1, 2))) / norm
    return out


def residual_map(prediction: np.ndarray, measurements: np.ndarray,
                 scale: np.ndarray) -> np.ndarray:
    """Per-pixel RMS of the scaled residual over pairs and channels, relative to the measurements'
    RMS over all of them; ``(H, W)`` float32 (its mean square is ``Σ‖r‖²/Σ‖y‖²``).

    ``prediction``, ``measurements`` ``(N, C, H, W)``, ``scale`` ``(N,)`` best per-pair scales.
    """
    s = np.asarray(scale, dtype=np.float64)[:, None, None, None]
    r = s * prediction.astype(np.float64) - measurements.astype(np.float64)
    y_rms = np.sqrt(np.mean(measurements.astype(np.float64) ** 2))
    if not y_rms > 0:
        raise InvalidInputError("the measurements are all zero: no residual map")
    return (np.sqrt(np.mean(r * r, axis=(0, 1))) / y_rms).astype(np.float32)


def _recorded_split(provenance: Mapping[str, Any], root: str | os.PathLike
                    ) -> frozenset[str] | None:
    """The names the model was fitted on, when its record is of the folder ``root``."""
    folder, names = provenance.get("pairs"), provenance.get("names")
    if not isinstance(folder, str) or not isinstance(names, list):
        return None
    if Path(folder).resolve() != Path(root).resolve():
        return None
    return frozenset(str(n) for n in names)


def pair_roles(provenance: Mapping[str, Any], root: str | os.PathLike,
               names: Sequence[str], holdout: Iterable[str] = (),
               where: str = "kernel file") -> tuple[str, ...]:
    """:data:`FITTED` or :data:`HELD_OUT` for each pair ``names`` of the folder ``root``.

    A kernel file recording a fit on this folder says which (``holdout`` may only confirm it);
    otherwise all are held out unless ``holdout`` names the held-out ones (the others fitted).

    Raises
    ------
    InvalidInputError
        ``holdout`` names a pair not in ``names``, or one the file records as fitted.
    """
    held = parse_names(holdout)
    unknown = [n for n in held if n not in names]
    if unknown:
        raise InvalidInputError(f"{root}: no pair named {', '.join(unknown)} to hold out "
                                f"(pairs: {', '.join(names[:8])}"
                                + (", ..." if len(names) > 8 else "") + ")")
    fitted = _recorded_split(provenance, root)
    if fitted is not None:
        contradicted = [n for n in held if n in fitted]
        if contradicted:
            raise InvalidInputError(f"--holdout {','.join(contradicted)}: {where} records "
                                    f"{'it' if len(contradicted) == 1 else 'them'} as fitted "
                                    f"(it was fitted on {len(fitted)} pairs of {root})")
        return tuple(FITTED if n in fitted else HELD_OUT for n in names)
    if held:
        return tuple(HELD_OUT if n in held else FITTED for n in names)
    return tuple(HELD_OUT for _ in names)
