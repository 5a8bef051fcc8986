"""Sensor model: Poisson–Gaussian statistics, black level, quantisation, saturation."""

import numpy as np
import pytest

from psfkit.errors import ConfigurationError
from psfkit.simulate.sensor import SensorModel, relative_illumination


def test_noise_statistics_are_poisson_gaussian():
    sensor = SensorModel(full_well_e=10000, read_noise_e=3.0, bit_depth=12, black_level_dn=64)
    rng = np.random.default_rng(0)
    for level_e in (50.0, 2000.0):
        frames = sensor.capture(np.full((1, 200, 200), level_e), rng).astype(np.float64)
        dn = frames / sensor.container_scale - sensor.black_level_dn
        e_per_dn = sensor.electrons_per_dn
        assert dn.mean() * e_per_dn == pytest.approx(level_e, rel=0.01)
        # variance in electrons = shot (level) + read² (+ quantisation step²/12)
        expected_var = level_e + 3.0**2 + e_per_dn**2 / 12
        assert dn.var() * e_per_dn**2 == pytest.approx(expected_var, rel=0.05)


def test_black_level_container_and_saturation():
    sensor = SensorModel(bit_depth=12, black_level_dn=64, read_noise_e=0.0)
    rng = np.random.default_rng(1)
    dark = sensor.capture(np.zeros((1, 10, 10)), rng)
    assert dark.dtype == np.uint16
    assert np.all(dark == 64 * 16)                     # MSB-aligned 12-bit data
    bright = sensor.capture(np.full((1, 10, 10), 3 * sensor.full_well_e), rng)
    assert np.all(bright == 4095 * 16)                 # clipped at full scale: 65520


def test_relative_illumination():
    assert relative_illumination(np.cos(np.deg2rad(30.0))) == pytest.approx(0.75**2)


def test_sensor_validation():
    with pytest.raises(ConfigurationError):
        SensorModel(bit_depth=20)
    with pytest.raises(ConfigurationError):
        SensorModel(quantum_efficiency=(1.5, 0.5, 0.5))


@pytest.mark.parametrize("frames", [1, 4, 16])
def test_mean_of_frames_divides_the_noise_variance_by_their_number(frames):
    """Averaging N independent captures: same mean, variance (shot + read + quantisation) / N;
    a pixel clipped in any one frame is reported saturated."""
    sensor = SensorModel(full_well_e=10000, read_noise_e=3.0, bit_depth=12, black_level_dn=64)
    rng = np.random.default_rng(frames)
    level_e = 300.0
    mean, saturated = sensor.capture_mean(np.full((1, 150, 150), level_e), rng, frames)
    assert mean.dtype == np.float32 and mean.shape == (1, 150, 150)
    assert not saturated.any()
    e_per_dn = sensor.electrons_per_dn
    dn = mean.astype(np.float64) / sensor.container_scale - sensor.black_level_dn
    assert dn.mean() * e_per_dn == pytest.approx(level_e, rel=0.01)
    expected_var = (level_e + 3.0**2 + e_per_dn**2 / 12) / frames
    assert dn.var() * e_per_dn**2 == pytest.approx(expected_var, rel=0.06)
    # about half the frames clip at full scale: flagged, and the mean is below full scale
    mean, saturated = sensor.capture_mean(np.full((1, 4, 4), sensor.full_well_e), rng, 16)
    assert saturated.all() and np.all(mean < 4095 * 16)


def test_mean_of_frames_refuses_a_non_positive_count():
    with pytest.raises(ConfigurationError, match="frames"):
        SensorModel().capture_mean(np.zeros((1, 2, 2)), np.random.default_rng(0), 0)
