"""The guided demosaicing method: exactness, what it shares across colours, accuracy on texture."""

from __future__ import annotations

import numpy as np
import pytest

from pmvir.polarization.demosaic import demosaic
from pmvir.polarization.guided import GUIDED_WEIGHT_K, guided_polarization
from pmvir.polarization.layout import IMX250MYR, IMX250MZR, MosaicLayout, mosaic
from pmvir.polarization.stokes import intensities_from_polarization, polarization_images

LAYOUTS = {
    "IMX250MYR": IMX250MYR,
    "IMX250MZR": IMX250MZR,
    "GBRG-rotated": MosaicLayout(polarizer_block=((0, 45), (135, 90)), bayer="GBRG"),
    "mono-rotated": MosaicLayout(polarizer_block=((45, 90), (0, 135)), bayer=None),
}
MARGIN = 24  # well beyond the guided reach (9 px) from the border
INNER = (slice(MARGIN, -MARGIN), slice(MARGIN, -MARGIN))


def _field(h: int, w: int, c: int, *, linear: bool) -> np.ndarray:
    """Per-colour intensity (constant or a different ramp per colour), one polarization for all colours."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    s0 = np.empty((h, w, c), dtype=np.float32)
    for k in range(c):
        ramp = (0.004 * (k + 1) * (x - w / 2) - 0.003 * (y - h / 2)) if linear else 0.0
        s0[..., k] = 0.6 + 0.1 * k + ramp
    aop = np.full((h, w), np.deg2rad(35.0), dtype=np.float32)
    dop = np.full((h, w), 0.3, dtype=np.float32)
    return intensities_from_polarization(s0, aop, dop)


@pytest.mark.parametrize("linear", [False, True], ids=["constant", "linear"])
@pytest.mark.parametrize("name", list(LAYOUTS))
def test_fields_with_one_polarization_come_back_exactly(name: str, linear: bool) -> None:
    """Constant and linear intensity (per colour) under one polarization: every channel exact."""
    layout = LAYOUTS[name]
    truth = _field(96, 128, layout.channels, linear=linear)
    out = demosaic(mosaic(truth, layout), layout, method="guided")
    assert out.shape == truth.shape and out.dtype == np.float32
    np.testing.assert_allclose(out[INNER], truth[INNER], atol=2e-6)


def test_constant_field_with_colour_dependent_polarization_keeps_the_colour_mean_exactly() -> None:
    """Arbitrary constants per channel: the colour means (what AoP/DoP use) and each colour's I_int exact."""
    h, w = 64, 96
    values = np.arange(12, dtype=np.float32).reshape(4, 3) * 0.05 + 0.1
    truth = np.broadcast_to(values, (h, w, 4, 3)).astype(np.float32)
    out = demosaic(mosaic(truth, IMX250MYR), IMX250MYR, method="guided")
    np.testing.assert_allclose(out[INNER].mean(axis=-1), truth[INNER].mean(axis=-1), atol=2e-6)
    np.testing.assert_allclose(out[INNER].mean(axis=-2), truth[INNER].mean(axis=-2), atol=2e-6)


def _independent_ramps() -> np.ndarray:
    """(96, 128, 4, 3) float32: an unrelated ramp in each of the 12 channels (no physical polarization)."""
    y, x = np.mgrid[0:96, 0:128].astype(np.float64)
    truth = np.empty((96, 128, 4, 3), dtype=np.float32)
    for a in range(4):
        for k in range(3):
            truth[:, :, a, k] = 0.5 + 0.001 * (a + 1) * (x - 64) - 0.0008 * (k + 1) * (y - 48) + 0.01 * a
    return truth


def test_linear_ramps_per_channel_come_back_to_second_order() -> None:
    """Independent ramps in all 12 channels: the colour-mean intensities within 1e-3 (second-order terms)."""
    truth = _independent_ramps()
    out = demosaic(mosaic(truth, IMX250MYR), IMX250MYR, method="guided")
    np.testing.assert_allclose(out[INNER].mean(axis=-1), truth[INNER].mean(axis=-1), atol=1e-3)
    # the intensity of every colour (mean over the angles) is the bilinear one: exact
    np.testing.assert_allclose(out[INNER].mean(axis=-2), truth[INNER].mean(axis=-2), atol=2e-6)


def test_dark_windows_get_no_polarization() -> None:
    raw = np.zeros((32, 48), dtype=np.float32)
    out = demosaic(raw, IMX250MYR, method="guided")
    assert np.all(np.isfinite(out)) and not out.any()


def test_bad_planes_raise_value_error() -> None:
    with pytest.raises(ValueError, match="planes"):
        guided_polarization(np.zeros((3, 3, 8, 8), dtype=np.float32))
    with pytest.raises(ValueError, match="even"):
        guided_polarization(np.zeros((4, 1, 9, 8), dtype=np.float32))
    with pytest.raises(ValueError, match="radius"):
        guided_polarization(np.zeros((4, 1, 8, 8), dtype=np.float32), radius=0)


def _textured_capture(seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 12-bit IMX250MYR frame of a textured surface with smooth polarization; (raw, aop, dop)."""
    h, w = 192, 256
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    albedo = 0.35 + 0.25 * (np.sin(0.9 * x + 0.3 * y) > 0) + 0.2 * rng.random((h, w), dtype=np.float32)
    albedo += 0.2 * (((x // 11) + (y // 7)) % 2)
    s0 = np.stack([0.8 * albedo, albedo, 0.6 * albedo], axis=-1).astype(np.float32)
    aop = np.mod(np.deg2rad(20 + 60 * x / w + 15 * np.sin(y / 40)), np.pi).astype(np.float32)
    dop = (0.15 + 0.1 * np.cos(x / 60) * np.sin(y / 50)).astype(np.float32)
    signal = mosaic(intensities_from_polarization(s0 * 0.6, aop, dop), IMX250MYR)
    electrons = rng.poisson(np.clip(signal, 0, None) * 10_000.0) / 10_000.0
    raw = np.clip(np.rint(electrons * 4095), 0, 4095).astype(np.float32) / 4095
    return raw.astype(np.float32), aop, dop


def _errors(intensities: np.ndarray, aop: np.ndarray, dop: np.ndarray) -> tuple[float, float]:
    """(DoP-weighted AoP error in degrees, mean DoP error) against the true field, 24 px from the border."""
    p = polarization_images(intensities, noise_floor=0.0)
    d_aop = np.degrees(np.abs(np.angle(np.exp(2j * (p.aop - aop)))) / 2)[INNER]
    weight = dop[INNER]
    return float((weight * d_aop).sum() / weight.sum()), float(np.abs(p.dop - dop)[INNER].mean())


def test_guided_beats_bilinear_on_a_noisy_textured_frame() -> None:
    """DoP-weighted AoP error and DoP error against the true field: guided <= 0.75x bilinear."""
    raw, aop, dop = _textured_capture(seed=4)
    errors = {m: _errors(demosaic(raw, IMX250MYR, method=m), aop, dop) for m in ("bilinear", "guided")}
    (bil_aop, bil_dop), (gui_aop, gui_dop) = errors["bilinear"], errors["guided"]
    assert gui_aop <= 0.75 * bil_aop, errors
    assert gui_dop <= 0.75 * bil_dop, errors


def test_guided_beats_polanalyser_on_a_noisy_textured_frame() -> None:
    """Same frame through polanalyser's bilinear COLOR_PolarRGB: guided AoP error <= 0.75x, DoP <= 0.8x."""
    pa = pytest.importorskip("polanalyser")
    raw, aop, dop = _textured_capture(seed=5)
    raw16 = np.rint(raw * 4095).astype(np.uint16)
    theirs = np.stack([im[..., ::-1] for im in pa.demosaicing(raw16, pa.COLOR_PolarRGB)], axis=2)
    errors = [
        _errors(demosaic(raw, IMX250MYR, method="guided"), aop, dop),
        _errors(theirs.astype(np.float32) / 4095, aop, dop),
    ]
    (ours_aop, ours_dop), (pa_aop, pa_dop) = errors
    assert ours_aop <= 0.75 * pa_aop, errors
    assert ours_dop <= 0.8 * pa_dop, errors


def test_fit_error_weights_keep_a_polarization_edge_sharper() -> None:
    """Two regions of equal, textured intensity and different AoP, with shot noise: near the boundary the
    windows that straddle it lose weight, so the AoP error there halves (measured 2.4 -> 1.1 degrees) and
    stays the same away from it (0.62 degrees both)."""
    h, w = 128, 128
    rng = np.random.default_rng(2)
    _, x = np.mgrid[0:h, 0:w].astype(np.float32)
    albedo = 0.5 + 0.2 * rng.random((h, w), dtype=np.float32)
    s0 = np.repeat(albedo[..., None], 3, axis=2) * np.float32(0.6)
    aop = np.where(x < 64, np.deg2rad(20.0), np.deg2rad(110.0)).astype(np.float32)
    dop = np.full((h, w), 0.3, np.float32)
    signal = mosaic(intensities_from_polarization(s0, aop, dop), IMX250MYR)
    raw = (rng.poisson(np.clip(signal, 0, None) * 10_000.0) / 10_000.0).astype(np.float32)
    near = (slice(MARGIN, -MARGIN), slice(56, 72))
    far = (slice(MARGIN, -MARGIN), np.r_[MARGIN:44, 84:w - MARGIN])
    errors = {}
    for weight_k in (None, GUIDED_WEIGHT_K):
        planes = demosaic(raw, IMX250MYR, method="bilinear").transpose(2, 3, 0, 1).copy()
        guided_polarization(planes, weight_k=weight_k)
        p = polarization_images(planes.transpose(2, 3, 0, 1), noise_floor=0.0)
        err = np.degrees(np.abs(np.angle(np.exp(2j * (p.aop - aop)))) / 2)
        errors[weight_k] = (float(err[near].mean()), float(err[far].mean()))
    (plain_near, plain_far), (weighted_near, weighted_far) = errors[None], errors[GUIDED_WEIGHT_K]
    assert weighted_near < 0.6 * plain_near, errors
    assert weighted_far < 1.05 * plain_far, errors
