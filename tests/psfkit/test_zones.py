"""Field zones (:mod:`psfkit.forward.zones`): three equal-area radial zones around the optical
centre,
one definition for psfkit (eval-model) and ekdun (eval)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from psfkit.errors import InvalidInputError
from psfkit.forward.zones import ZONE_NAMES, field_zones
from tests.helpers.weights import normalized_coordinates


@pytest.mark.parametrize("shape", [(67, 120), (270, 480), (64, 64), (31, 17), (5, 5), (1, 3)])
def test_zones_partition_the_sensor_into_three_equal_areas(shape):
    zones = field_zones(shape)
    masks = zones.masks()
    assert list(masks) == list(ZONE_NAMES)
    stacked = np.stack(list(masks.values()))
    assert np.all(stacked.sum(axis=0) == 1)                  # a partition: one zone a pixel
    counts = stacked.sum(axis=(1, 2))
    assert counts.max() - counts.min() <= 1                   # equal areas
    assert zones.describe()["pixels"] == counts.tolist()


@pytest.mark.parametrize("centre", [None, (20.0, 70.5), (0.0, 0.0)])
def test_zones_are_rings_of_growing_distance_from_the_optical_centre(centre):
    h, w = 67, 120
    zones = field_zones((h, w), centre)
    v_c, u_c = centre if centre is not None else ((h - 1) / 2, (w - 1) / 2)
    r = np.hypot(np.arange(h)[:, None] - v_c, np.arange(w)[None, :] - u_c)
    labels = zones.labels
    # every pixel of an inner zone is at most as far as every pixel of an outer one
    for inner, outer in ((0, 1), (1, 2)):
        assert r[labels == inner].max() <= r[labels == outer].min() + 1e-12
    r1, r2 = zones.radii
    assert r[labels == 0].max() == pytest.approx(r1) and r[labels == 1].max() == pytest.approx(r2)
    assert np.all(labels[r < r1] == 0) and np.all(labels[r > r2] == 2)


def test_centre_disc_has_the_radius_of_a_third_of_the_area():
    # where the centre disc fits on the sensor its radius is sqrt(A / (3 pi)) (up to a pixel)
    h, w = 270, 480
    r1 = field_zones((h, w)).radii[0]
    assert r1 == pytest.approx(math.sqrt(h * w / (3 * math.pi)), abs=1.0)


def test_default_centre_is_the_weight_maps_centre():
    # the optical centre the eigen-kernel weight maps are drawn around: u_n = v_n = 0 there
    h, w = 67, 120
    u_n, v_n = normalized_coordinates((h, w))
    zones = field_zones((h, w))
    v_c, u_c = zones.optical_center
    assert np.interp(v_c, np.arange(h), v_n[:, 0]) == pytest.approx(0.0)
    assert np.interp(u_c, np.arange(w), u_n[0]) == pytest.approx(0.0)


def test_cropped_zones_keep_each_pixels_zone():
    zones = field_zones((40, 50))
    inner = zones.cropped(5)
    assert np.array_equal(inner.labels, zones.labels[5:-5, 5:-5])


def test_too_small_a_sensor_is_refused():
    with pytest.raises(InvalidInputError, match="at least 3 pixels"):
        field_zones((1, 2))
