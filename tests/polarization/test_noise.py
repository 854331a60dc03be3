"""closure_noise: the polarizer closure residual as a per-pixel measure of the AoP's noise."""

from __future__ import annotations

import numpy as np
import pytest

from pmvir.errors import ConfigError, DTypeError, ShapeError
from pmvir.polarization.demosaic import demosaic
from pmvir.polarization.layout import IMX250MYR, IMX250MZR, mosaic
from pmvir.polarization.noise import DOP_NOISE_GAIN, closure_noise, unbiased_dop
from pmvir.polarization.stokes import colour_mean_stokes, intensities_from_polarization

H, W = 96, 128


def _field(aop: float = 0.6, dop: float = 0.3, s0: float = 0.5) -> np.ndarray:
    """(H, W, 4, 3) polarizer intensities of a uniform polarized field."""
    s = np.full((H, W, 3), s0, np.float32)
    return intensities_from_polarization(s, np.full((H, W), aop, np.float32), np.full((H, W), dop, np.float32))


@pytest.mark.parametrize("layout", [IMX250MYR, IMX250MZR])
def test_closure_noise_measures_the_sample_noise_relative_to_s0(layout) -> None:
    """Independent noise of standard deviation sigma on each sample gives a closure residual of
    2 sigma, so the noise reads 2 sigma / s0 whatever the field's own polarization."""
    rng = np.random.default_rng(0)
    clean = _field()[..., : layout.channels]
    for dop, sigma in ((0.0, 0.01), (0.3, 0.01), (0.6, 0.02)):
        m = mosaic(np.ascontiguousarray(_field(dop=dop)[..., : layout.channels]), layout)
        noisy = (m + rng.normal(0.0, sigma, m.shape)).astype(np.float32)
        noise = closure_noise(noisy, layout)
        assert np.nanmedian(noise) == pytest.approx(2.0 * sigma / 0.5, rel=0.08)
    assert float(closure_noise(mosaic(np.ascontiguousarray(clean), layout), layout).max()) < 1e-6


def test_closure_noise_follows_where_the_aop_is_noisy() -> None:
    """Three times the noise on the right half: the measured noise is three times higher there, and
    so is the decoded AoP's error; DoP / noise ranks the pixels by AoP error where DoP alone cannot."""
    rng = np.random.default_rng(1)
    m = mosaic(_field(aop=0.6, dop=0.2), IMX250MYR)
    sigma = np.where(np.arange(W)[None, :] < W // 2, 0.004, 0.012)
    noisy = (m + rng.normal(0.0, 1.0, m.shape) * sigma).astype(np.float32)
    noise = closure_noise(noisy, IMX250MYR)
    stokes = colour_mean_stokes(np.ascontiguousarray(demosaic(noisy, IMX250MYR)))
    aop = 0.5 * np.arctan2(stokes[..., 2], stokes[..., 1])
    err = np.abs((aop - 0.6 + np.pi / 2) % np.pi - np.pi / 2)
    left, right = np.s_[8:-8, 8 : W // 2 - 8], np.s_[8:-8, W // 2 + 8 : -8]
    assert np.median(noise[right]) / np.median(noise[left]) == pytest.approx(3.0, rel=0.15)
    assert np.sqrt((err[right] ** 2).mean()) / np.sqrt((err[left] ** 2).mean()) == pytest.approx(3.0, rel=0.2)


def test_closure_noise_counts_only_valid_blocks() -> None:
    """A bright, unpolarized background next to a dim object: with the object's mask as ``valid``
    the edge's residual does not leak into the object's noise; pixels far from any valid block are
    NaN (unmeasured)."""
    field = _field(dop=0.2, s0=0.2)
    field[:, W // 2 :] = _field(dop=0.0, s0=0.9)[:, W // 2 :]
    m = mosaic(field, IMX250MYR)
    m[::3, W // 2 - 1 :: 7] += 0.3  # a rough background texture, including the column at the edge
    valid = np.zeros((H, W), bool)
    valid[:, : W // 2 - 2] = True
    noise = closure_noise(m, IMX250MYR, valid=valid)
    assert float(np.nanmax(noise[:, : W // 2 - 2])) < 1e-6
    assert np.isnan(noise[:, -8:]).all()
    leaky = closure_noise(m, IMX250MYR)
    assert float(leaky[:, W // 2 - 4].min()) > 0.01


def test_closure_noise_refuses_bad_input() -> None:
    m = np.zeros((H, W), np.float32)
    with pytest.raises(DTypeError, match="float32"):
        closure_noise(m.astype(np.float64), IMX250MYR)
    with pytest.raises(ShapeError, match="mosaic"):
        closure_noise(m[None], IMX250MYR)
    with pytest.raises(ConfigError, match="multiple of 4"):
        closure_noise(m[:, :-2], IMX250MYR)
    with pytest.raises(ShapeError, match="valid"):
        closure_noise(m, IMX250MYR, valid=np.ones((H, W - 4), bool))
    with pytest.raises(ConfigError, match="sigma_px"):
        closure_noise(m, IMX250MYR, sigma_px=0.0)


def _noisy_decode(method: str, *, dop: float, s0: float, full_well: float, read_noise: float, seed: int,
                  layout=IMX250MYR):
    """Decoded DoP and closure noise of a uniform field read out with shot and read noise."""
    from pmvir.config import DecodeOptions
    from pmvir.decode import decode_frame

    rng = np.random.default_rng(seed)
    h = w = 256
    s = np.full((h, w, 3), s0, np.float32) * np.array([0.9, 1.0, 0.7], np.float32)
    ints = intensities_from_polarization(s, np.full((h, w), 0.4, np.float32), np.full((h, w), dop, np.float32))
    clean = mosaic(np.ascontiguousarray(ints[..., : layout.channels]), layout)
    m = (rng.poisson(clean * full_well) / full_well + rng.normal(0.0, read_noise, clean.shape)).astype(np.float32)
    d = decode_frame(m, layout, options=DecodeOptions(demosaic=method))
    inner = (slice(16, -16), slice(16, -16))
    return d.dop[inner], closure_noise(m, layout)[inner]


@pytest.mark.parametrize(("method", "channels"), sorted(DOP_NOISE_GAIN))
def test_dop_noise_gain_is_the_methods_noise_power_on_an_unpolarized_field(method: str, channels: int) -> None:
    """E[DoP^2] / E[closure noise^2] of an unpolarized field is the method's constant, whatever the
    level and the noise (within 10 %)."""
    layout = IMX250MYR if channels == 3 else IMX250MZR
    for s0, full_well, read_noise in ((0.08, 10500.0, 0.001), (0.3, 3000.0, 0.003)):
        dop, noise = _noisy_decode(method, dop=0.0, s0=s0, full_well=full_well, read_noise=read_noise, seed=3,
                                   layout=layout)
        gain = float((dop**2).mean() / (noise**2).mean())
        assert gain == pytest.approx(DOP_NOISE_GAIN[method, channels], rel=0.1)


@pytest.mark.parametrize(("method", "s0", "read_noise"), [("bilinear", 0.05, 0.003), ("guided", 0.02, 0.006)])
def test_unbiased_dop_removes_the_noise_bias(method: str, s0: float, read_noise: float) -> None:
    """Decoded DoP of a weakly polarized noisy field reads high; the unbiased estimate takes most of
    the bias out (not all: clamping at 0 where the noise outweighs the signal keeps some)."""
    true = 0.05
    dop, noise = _noisy_decode(method, dop=true, s0=s0, full_well=3000.0, read_noise=read_noise, seed=4)
    fixed = unbiased_dop(dop, noise, method=method)
    bias = float(dop.mean()) - true
    assert bias > 0.2 * true  # the noise is a visible share of the DoP
    assert abs(float(fixed.mean()) - true) < 0.4 * bias
    assert fixed.dtype == np.float32 and (fixed >= 0).all() and (fixed <= dop + 1e-7).all()


def test_unbiased_dop_refuses_bad_input() -> None:
    dop = np.zeros((4, 4), np.float32)
    with pytest.raises(ConfigError, match="unknown demosaicing method"):
        unbiased_dop(dop, dop, method="nearest")
    with pytest.raises(ShapeError, match="noise"):
        unbiased_dop(dop, np.zeros((4, 5), np.float32), method="guided")


def test_decode_frame_unbiased_dop_option() -> None:
    """``DecodeOptions(dop_estimator="unbiased")`` gives unbiased_dop of the plain DoP with the frame's
    closure noise, and I_min from it; the AoP, I_int and validity stay the plain decoding's."""
    from pmvir.config import DecodeOptions
    from pmvir.decode import decode_frame

    rng = np.random.default_rng(5)
    m = mosaic(np.ascontiguousarray(_field(dop=0.05, s0=0.06)), IMX250MYR)
    m = (m + rng.normal(0.0, 0.004, m.shape)).astype(np.float32)
    plain = decode_frame(m, IMX250MYR)
    fixed = decode_frame(m, IMX250MYR, options=DecodeOptions(dop_estimator="unbiased"))
    assert DecodeOptions().dop_estimator == "plain"
    expect = unbiased_dop(plain.dop, closure_noise(m, IMX250MYR, valid=plain.valid), method="guided")
    np.testing.assert_array_equal(fixed.dop, expect)
    np.testing.assert_allclose(fixed.i_min, (1.0 - fixed.dop)[..., None] * fixed.i_int, rtol=1e-6)
    for key in ("aop", "i_int", "valid"):
        np.testing.assert_array_equal(getattr(fixed, key), getattr(plain, key))
    assert float(fixed.dop.mean()) < float(plain.dop.mean())
