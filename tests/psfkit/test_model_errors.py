"""Where, and on which pairs, a forward model fails (:mod:`psfkit.fitting.pairs.model_errors`):
errors by
field zone and residual maps against hand computations, and the fitted/held-out roles."""

from __future__ import annotations

import numpy as np
import pytest

from psfkit.errors import InvalidInputError
from psfkit.fitting.pairs.fit import relative_errors
from psfkit.fitting.pairs.model_errors import (
    FITTED,
    HELD_OUT,
    pair_roles,
    residual_map,
    zone_errors,
)
from psfkit.forward.zones import field_zones


def _edge_error_case(seed: int = 0):
    """Predictions that are exact except at the edge zone, where the measurements differ."""
    rng = np.random.default_rng(seed)
    shape = (12, 18)
    zones = field_zones(shape)
    prediction = rng.random((3, 2, *shape)) + 0.5
    measurements = prediction.copy()
    edge = zones.labels == 2
    measurements[..., edge] += 0.3 * rng.standard_normal((3, 2, int(edge.sum())))
    return prediction, measurements, zones, edge


def test_zone_errors_match_a_hand_computation_with_the_error_at_the_edge():
    p, y, zones, edge = _edge_error_case()
    scale = relative_errors(p, y)["scale"]
    errors = zone_errors(p, y, zones, scale)
    # raw: zero where the prediction is exact, the edge's own relative error at the edge
    assert np.all(errors["raw"][:, :2] == 0)
    for i in range(3):
        by_hand = np.linalg.norm((p[i] - y[i])[:, edge]) / np.linalg.norm(y[i][:, edge])
        assert errors["raw"][i, 2] == pytest.approx(by_hand, rel=1e-12)
        assert by_hand > 0.05
        # scaled: the pair's whole-sensor best scale s = <p, y> / <p, p>, zone by zone
        s = np.sum(p[i] * y[i]) / np.sum(p[i] * p[i])
        for z in range(3):
            inside = zones.labels == z
            expected = (np.linalg.norm((s * p[i] - y[i])[:, inside])
                        / np.linalg.norm(y[i][:, inside]))
            assert errors["scaled"][i, z] == pytest.approx(expected, rel=1e-10)


def test_residual_map_is_zero_off_the_edge_and_pools_to_the_relative_error():
    p, y, zones, edge = _edge_error_case(1)
    scale = np.ones(3)
    m = residual_map(p, y, scale)
    assert m.shape == zones.shape and m.dtype == np.float32
    assert np.all(m[~edge] == 0) and np.all(m[edge] > 0)
    # by hand: per-pixel RMS over pairs and channels over the measurements' RMS
    by_hand = np.sqrt(np.mean((p - y) ** 2, axis=(0, 1))) / np.sqrt(np.mean(y ** 2))
    np.testing.assert_allclose(m, by_hand, rtol=1e-6)
    # its mean square is the pooled squared relative error
    pooled = np.sum((p - y) ** 2) / np.sum(y ** 2)
    assert np.mean(m.astype(np.float64) ** 2) == pytest.approx(pooled, rel=1e-5)


def test_roles_from_the_kernel_files_record(tmp_path):
    names = ("im1", "im2", "im3")
    record = {"pairs": str(tmp_path), "names": ["im1", "im3"]}
    assert pair_roles(record, tmp_path, names) == (FITTED, HELD_OUT, FITTED)
    # --holdout may confirm the record, not contradict it
    assert pair_roles(record, tmp_path, names, ["im2"]) == (FITTED, HELD_OUT, FITTED)
    with pytest.raises(InvalidInputError, match="records it as fitted"):
        pair_roles(record, tmp_path, names, ["im1"])
    with pytest.raises(InvalidInputError, match="no pair named im9"):
        pair_roles(record, tmp_path, names, ["im9"])


def test_roles_of_a_model_not_fitted_on_this_folder(tmp_path):
    names = ("im1", "im2")
    other = {"pairs": str(tmp_path / "elsewhere"), "names": ["im1", "im2"]}
    # fitted elsewhere, or on a PSF grid: none of these pairs was seen
    assert pair_roles(other, tmp_path, names) == (HELD_OUT, HELD_OUT)
    assert pair_roles({"grid": "g"}, tmp_path, names) == (HELD_OUT, HELD_OUT)
    # --holdout declares the split where the file records none (the others were fitted)
    assert pair_roles({}, tmp_path, names, ["im2.npy"]) == (FITTED, HELD_OUT)
