"""closure_noise: the polarizer closure residual as a per-pixel measure of the AoP's noise."""

from __future__ import annotations

import numpy as np
import pytest

from pmvir.errors import ConfigError, DTypeError, ShapeError
from pmvir.polarization.demosaic import demosaic
from pmvir.polarization.layout import IMX250MYR, IMX250MZR, mosaic
from pmvir.polarization.noise import closure_noise
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
