"""The shared sensor step: Stokes -> polarizer intensities -> mosaic -> noise -> 12-bit samples."""

from __future__ import annotations

import numpy as np
import pytest

from pmvir.errors import ConfigError
from pmvir.polarization.layout import IMX250MYR
from pmvir.polarization.stokes import aop_from_stokes, colour_mean_stokes, dop_from_stokes
from pmvir.synth.sensor import SensorModel, capture_mosaic, stokes_to_intensities


def _field(h: int, w: int, s0: float, dop: float, aop: float) -> np.ndarray:
    st = np.zeros((h, w, 3, 3), dtype=np.float32)
    st[..., 0] = s0
    st[..., 1] = s0 * dop * np.cos(2 * aop)
    st[..., 2] = s0 * dop * np.sin(2 * aop)
    return st


@pytest.mark.parametrize("aop_deg", [0.0, 30.0, 90.0, 150.0])
def test_intensities_follow_malus_and_invert_to_the_spec_quantities(aop_deg: float) -> None:
    st = _field(4, 4, 0.8, 0.3, np.radians(aop_deg))
    i = stokes_to_intensities(st)
    assert i.shape == (4, 4, 4, 3) and i.dtype == np.float32
    theta = np.radians([0, 45, 90, 135])
    expect = 0.8 / 2 * (1 + 0.3 * np.cos(2 * (theta - np.radians(aop_deg))))
    np.testing.assert_allclose(i[0, 0, :, 1], expect, rtol=1e-6)
    # The decoder's formulas (spec section 2) give back what was put in.
    s = colour_mean_stokes(i)
    assert np.degrees(aop_from_stokes(s)[0, 0]) == pytest.approx(aop_deg % 180, abs=1e-3)
    assert dop_from_stokes(s)[0, 0] == pytest.approx(0.3, abs=1e-6)
    assert i.mean(axis=2)[0, 0, 0] == pytest.approx(0.8 / 2, rel=1e-6)  # I_int = s0 / 2


def test_noise_free_samples_are_quantized_signal_with_black_level() -> None:
    sensor = SensorModel(black_level=64, full_well=0.0, read_noise=0.0)
    st = _field(8, 8, 0.5, 0.0, 0.0)
    samples = capture_mosaic(st, gain=1.2, sensor=sensor, rng=np.random.default_rng(0))
    assert samples.dtype == np.uint16
    expect = round(64 + 0.5 / 2 * 1.2 * (4095 - 64))
    assert np.all(samples == expect)


def test_clipping_at_white_and_zero() -> None:
    sensor = SensorModel(black_level=64, full_well=0.0, read_noise=0.05)
    st = _field(32, 32, 4.0, 0.0, 0.0)
    assert np.all(capture_mosaic(st, gain=1.0, sensor=sensor, rng=np.random.default_rng(0)) == 4095)
    dark = capture_mosaic(
        _field(32, 32, 0.0, 0.0, 0.0), gain=1.0, sensor=sensor, rng=np.random.default_rng(0)
    )
    assert dark.min() == 0 and dark.max() < 4095


def test_noise_statistics_match_shot_and_read_noise() -> None:
    full_well, read = 5000.0, 0.002
    sensor = SensorModel(black_level=64, full_well=full_well, read_noise=read)
    x = 0.3  # signal, full-scale units
    samples = capture_mosaic(
        _field(256, 256, 2 * x, 0.0, 0.0), gain=1.0, sensor=sensor, rng=np.random.default_rng(1)
    )
    v = (samples.astype(np.float64) - 64) / (4095 - 64)
    expect_sd = np.sqrt(x / full_well + read**2 + (1 / 4031) ** 2 / 12)
    assert v.mean() == pytest.approx(x, abs=2e-4)
    assert v.std() == pytest.approx(expect_sd, rel=0.03)


def test_mosaic_keeps_each_pixels_angle_and_colour() -> None:
    """A red-only field polarized at 0 degrees: only R pixels under the 0/45/135 polarizers see light."""
    st = np.zeros((8, 8, 3, 3), dtype=np.float32)
    st[..., 0, 0] = 1.0
    st[..., 0, 1] = 1.0  # fully polarized at 0 degrees
    samples = capture_mosaic(
        st,
        gain=1.0,
        sensor=SensorModel(black_level=0, full_well=0, read_noise=0),
        rng=np.random.default_rng(0),
    )
    colour = IMX250MYR.colour_map(8, 8)
    angle = IMX250MYR.angle_map(8, 8)  # index into (0, 45, 90, 135)
    lit = samples > 0
    assert np.all(colour[lit] == 0)
    assert np.all(samples[(colour == 0) & (angle == 0)] == 4095)  # I0 = s0 = 1: full scale
    assert np.all(samples[(colour == 0) & (angle == 2)] == 0)  # crossed polarizer
    assert np.all(samples[(colour == 0) & (angle == 1)] == round(0.5 * 4095))


def test_bad_sensor_settings_raise_config_error() -> None:
    with pytest.raises(ConfigError, match="black_level"):
        SensorModel(black_level=5000)
    with pytest.raises(ConfigError, match="full_well"):
        SensorModel(full_well=-1)
    with pytest.raises(ConfigError, match="gain"):
        capture_mosaic(_field(4, 4, 1, 0, 0), gain=0.0, sensor=SensorModel(), rng=np.random.default_rng(0))
