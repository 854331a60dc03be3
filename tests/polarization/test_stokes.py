"""Stokes / AoP / DoP / I_int / I_min (spec section 2), and synthetic round trips through the mosaic."""

from __future__ import annotations

import numpy as np
import pytest

from pmvir.polarization.demosaic import demosaic
from pmvir.polarization.layout import IMX250MYR, IMX250MZR, MosaicLayout, layout_from_sensor, mosaic
from pmvir.polarization.stokes import (
    aop_from_stokes,
    colour_mean_stokes,
    dop_from_stokes,
    intensities_from_polarization,
    mean_intensity,
    polarization_images,
    stokes_from_intensities,
    unpolarized_intensity,
    valid_pixels,
)

MARGIN = 8


def _aop_error_deg(a: np.ndarray, b: np.ndarray | float) -> np.ndarray:
    """Angular difference modulo pi, degrees."""
    return np.degrees(np.abs(np.angle(np.exp(2j * (np.asarray(a, dtype=np.float64) - b)))) / 2)


def test_stokes_formulas_are_the_spec_ones() -> None:
    i = np.array([0.8, 0.5, 0.2, 0.3], dtype=np.float32)
    s = stokes_from_intensities(i)
    assert s.dtype == np.float32
    np.testing.assert_allclose(s, [(0.8 + 0.5 + 0.2 + 0.3) / 2, 0.8 - 0.2, 0.5 - 0.3], rtol=1e-6)


def test_forward_model_inverts_exactly() -> None:
    rng = np.random.default_rng(0)
    s0 = rng.uniform(0.1, 1.0, (5, 7, 3)).astype(np.float32)
    aop = rng.uniform(0, np.pi, (5, 7)).astype(np.float32)
    dop = rng.uniform(0, 1, (5, 7)).astype(np.float32)
    ints = intensities_from_polarization(s0, aop, dop)
    assert ints.shape == (5, 7, 4, 3) and ints.dtype == np.float32
    st = colour_mean_stokes(ints)
    np.testing.assert_allclose(st[..., 0], s0.mean(axis=2), rtol=1e-5)
    assert _aop_error_deg(aop_from_stokes(st), aop).max() < 1e-3
    np.testing.assert_allclose(dop_from_stokes(st), dop, atol=1e-5)
    np.testing.assert_allclose(mean_intensity(ints), s0 / 2, rtol=1e-5)


def test_aop_is_in_zero_to_pi_and_follows_the_spec_sense() -> None:
    # s1 > 0, s2 = 0: 0; s1 = 0, s2 > 0: 45 deg; s1 < 0: 90 deg; s2 < 0: 135 deg
    st = np.array([[1, 1, 0], [1, 0, 1], [1, -1, 0], [1, 0, -1]], dtype=np.float32)
    np.testing.assert_allclose(np.degrees(aop_from_stokes(st)), [0, 45, 90, 135], atol=1e-4)
    # a tiny negative angle must not round onto pi
    tiny = aop_from_stokes(np.array([[1, 1, -1e-9], [1, 1, -1e-30]], dtype=np.float32))
    assert ((tiny >= 0) & (tiny < np.pi)).all()
    rng = np.random.default_rng(1)
    many = aop_from_stokes(rng.normal(size=(1000, 3)).astype(np.float32))
    assert many.dtype == np.float32 and (many >= 0).all() and (many < np.float32(np.pi)).all()


def test_dop_is_clipped_and_finite_at_zero_intensity() -> None:
    st = np.array([[1.0, 0.3, 0.4], [0.1, 0.3, 0.4], [0.0, 0.1, 0.0], [-0.1, 0.0, 0.0]], dtype=np.float32)
    rho = dop_from_stokes(st)
    np.testing.assert_allclose(rho, [0.5, 1.0, 1.0, 0.0], atol=1e-6)
    assert np.isfinite(rho).all() and rho.dtype == np.float32


def test_i_min_is_one_minus_dop_times_i_int() -> None:
    i_int = np.full((2, 3, 3), 0.6, dtype=np.float32)
    dop = np.array([[0.0, 0.5, 1.0], [0.25, 0.1, 0.9]], dtype=np.float32)
    np.testing.assert_allclose(unpolarized_intensity(i_int, dop), (1 - dop)[..., None] * i_int, rtol=1e-6)


def test_polarization_images_match_the_reference_functions() -> None:
    rng = np.random.default_rng(2)
    ints = rng.uniform(0.0, 1.0, (12, 16, 4, 3)).astype(np.float32)
    for given in (ints, demosaic(mosaic(ints, IMX250MYR), IMX250MYR)):  # contiguous and planar
        p = polarization_images(given, noise_floor=0.01)
        st = colour_mean_stokes(np.ascontiguousarray(given))
        i_int = mean_intensity(np.ascontiguousarray(given))
        dop = dop_from_stokes(st)
        np.testing.assert_allclose(p.i_int, i_int, rtol=1e-5, atol=1e-7)
        np.testing.assert_allclose(p.dop, dop, rtol=1e-4, atol=1e-6)
        assert _aop_error_deg(p.aop, aop_from_stokes(st)).max() < 1e-3
        np.testing.assert_allclose(p.i_min, unpolarized_intensity(i_int, dop), rtol=1e-4, atol=1e-6)
        for arr, shape, dtype in ((p.i_int, (12, 16, 3), np.float32), (p.i_min, (12, 16, 3), np.float32),
                                  (p.aop, (12, 16), np.float32), (p.dop, (12, 16), np.float32),
                                  (p.valid, (12, 16), np.bool_)):
            assert arr.shape == shape and arr.dtype == dtype


def test_noise_floor_invalidates_dark_pixels() -> None:
    s0 = np.array([[0.0, 0.019, 0.02, 0.021, 0.5]], dtype=np.float32)  # mean intensity s0/2
    np.testing.assert_array_equal(valid_pixels(s0, noise_floor=0.01), [[False, False, False, True, True]])
    invalid = np.array([[False, False, False, False, True]])
    np.testing.assert_array_equal(
        valid_pixels(s0, noise_floor=0.01, invalid=invalid), [[False, False, False, True, False]]
    )


def test_invalid_mask_of_wrong_size_raises_value_error() -> None:
    with pytest.raises(ValueError, match="does not match"):
        valid_pixels(np.ones((2, 2), dtype=np.float32), noise_floor=0.0, invalid=np.zeros((3, 2), bool))


def test_intensities_of_wrong_shape_raise_value_error() -> None:
    with pytest.raises(ValueError, match=r"\(H, W, 4, C\)"):
        polarization_images(np.zeros((4, 4, 3, 3), dtype=np.float32), noise_floor=0.0)


def test_stokes_of_wrong_shape_raise_value_error() -> None:
    with pytest.raises(ValueError, match=r"\(\.\.\., 4\)"):
        stokes_from_intensities(np.zeros((3, 3), dtype=np.float32))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        aop_from_stokes(np.zeros((3, 4), dtype=np.float32))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3\)"):
        dop_from_stokes(np.zeros((3, 4), dtype=np.float32))


def _field(h: int, w: int, channels: int, aop_deg: float, dop: float, *, textured: bool):
    """s0 smooth (or textured on the right half), aop/dop smoothly varying around the given values."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    base = 0.5 + 0.15 * np.sin(x / 29) * np.cos(y / 37)
    if textured:
        rng = np.random.default_rng(4)
        tex = 0.25 * (np.sin(1.1 * x + 0.7 * y) > 0) + 0.25 * rng.random((h, w))
        base = np.where(x >= w // 2, 0.4 * base + tex, base)
    gains = [0.8, 1.0, 0.6][:channels] if channels == 3 else [1.0]
    s0 = np.stack([g * base for g in gains], axis=-1).astype(np.float32)
    aop = np.full((h, w), np.deg2rad(aop_deg), np.float32) + np.float32(np.deg2rad(3.0)) * np.sin(y / 41)
    rho = np.clip(dop + 0.03 * np.cos(x / 53), 0, 1).astype(np.float32)
    return s0, np.mod(aop, np.pi).astype(np.float32), rho


@pytest.mark.parametrize("layout", [IMX250MYR, IMX250MZR], ids=["rgb", "mono"])
@pytest.mark.parametrize("textured", [False, True], ids=["smooth", "textured"])
@pytest.mark.parametrize(
    ("aop_deg", "dop"), [(0.0, 0.1), (30.0, 0.5), (45.0, 0.9), (100.0, 0.3), (170.0, 0.05)]
)
@pytest.mark.parametrize("method", ["bilinear", "edge-aware"])
def test_round_trip_recovers_aop_and_dop(layout: MosaicLayout, textured: bool, aop_deg: float, dop: float,
                                         method: str) -> None:
    h, w = 64, 96
    s0, aop, rho = _field(h, w, layout.channels, aop_deg, dop, textured=textured)
    raw = mosaic(intensities_from_polarization(s0, aop, rho), layout)
    p = polarization_images(demosaic(raw, layout, method=method), noise_floor=0.01)
    # smooth region away from the border (and from the texture by more than the footprint)
    region = (slice(MARGIN, -MARGIN), slice(MARGIN, w // 2 - MARGIN))
    assert _aop_error_deg(p.aop, aop)[region].max() < 1.0
    assert np.abs(p.dop - rho)[region].max() < 0.01
    assert p.valid[region].all()
    np.testing.assert_allclose(p.i_int[region], (s0 / 2)[region], rtol=2e-3)  # I_int = s0 / 2


def test_field_at_plus_45_degrees_reads_45_not_135() -> None:
    h, w = 32, 32
    s0 = np.full((h, w, 3), 0.6, np.float32)
    ints = intensities_from_polarization(s0, np.full((h, w), np.deg2rad(45), np.float32),
                                         np.full((h, w), 0.5, np.float32))
    # the pixel labelled 45 sees the most light, the one labelled 135 the least
    assert ints[0, 0, 1, 0] > ints[0, 0, 0, 0] > ints[0, 0, 3, 0]
    p = polarization_images(demosaic(mosaic(ints, IMX250MYR), IMX250MYR), noise_floor=0.01)
    np.testing.assert_allclose(np.degrees(p.aop[MARGIN:-MARGIN, MARGIN:-MARGIN]), 45.0, atol=1e-3)


@pytest.mark.parametrize("aop_deg", [20.0, 45.0, 120.0])
def test_cw_declared_capture_gives_the_mirrored_angle(aop_deg: float) -> None:
    h, w = 32, 32
    s0 = np.full((h, w, 3), 0.6, np.float32)
    ints = intensities_from_polarization(s0, np.full((h, w), np.deg2rad(aop_deg), np.float32),
                                         np.full((h, w), 0.4, np.float32))
    raw = mosaic(ints, IMX250MYR)  # the same raw frame, read with the labels declared clockwise
    cw = layout_from_sensor("IMX250MYR", aop_reference="cw")
    p = polarization_images(demosaic(raw, cw), noise_floor=0.01)
    got = p.aop[MARGIN:-MARGIN, MARGIN:-MARGIN]
    assert _aop_error_deg(got, np.deg2rad(180.0 - aop_deg)).max() < 1e-3
