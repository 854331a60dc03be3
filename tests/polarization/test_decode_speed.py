"""The fast decoding paths equal straightforward reference implementations (up to float rounding).

The references below compute ``guided_polarization`` and ``polarization_images``
plainly (whole-plane OpenCV calls, no strips, no shared intermediates).
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pmvir.config import DecodeOptions
from pmvir.decode import decode_frame
from pmvir.polarization.demosaic import demosaic, saturation_footprint
from pmvir.polarization.guided import GUIDED_RADIUS, GUIDED_TAU, GUIDED_WEIGHT_K, guided_polarization
from pmvir.polarization.layout import IMX250MYR, IMX250MZR, MosaicLayout, mosaic
from pmvir.polarization.stokes import (
    DOP_EPS,
    intensities_from_polarization,
    polarization_images,
    valid_pixels,
)

_EPS = 1e-6
_WEIGHT_FLOOR_MIN = 1e-7


def _reference_guided(planes: np.ndarray, *, weight_k: float | None = GUIDED_WEIGHT_K,
                      tiny_floor: bool = False) -> None:
    """``guided_polarization`` computed plainly: whole planes, upsampled coefficients at full resolution.

    With ``tiny_floor``, the weights' floor is 1e-20 instead of the dark threshold (see below).
    """
    n_col, h, w = planes.shape[1:]
    size = (2 * GUIDED_RADIUS + 1, 2 * GUIDED_RADIUS + 1)
    half = (w // 2, h // 2)

    def box(x: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(x, -1, size, borderType=cv2.BORDER_REPLICATE)

    def up(x: np.ndarray) -> np.ndarray:
        return cv2.resize(x, (w, h), interpolation=cv2.INTER_LINEAR)

    def half_colour_sum(angle_planes: np.ndarray) -> np.ndarray:
        total = cv2.resize(angle_planes[0], half, interpolation=cv2.INTER_AREA)
        for plane in angle_planes[1:]:
            cv2.add(total, cv2.resize(plane, half, interpolation=cv2.INTER_AREA), dst=total)
        return total

    quads = [half_colour_sum(planes[k]) for k in range(4)]
    gh = cv2.add(cv2.add(quads[0], quads[2]), cv2.add(quads[1], quads[3]))
    mean_g = box(gh)
    var_g = cv2.subtract(box(cv2.multiply(gh, gh)), cv2.multiply(mean_g, mean_g))
    eps = cv2.multiply(mean_g, mean_g, scale=GUIDED_TAU * GUIDED_TAU)
    floor = 2.0 * n_col * _EPS
    _, lit = cv2.threshold(mean_g, floor, 1.0, cv2.THRESH_BINARY)
    inv_mean_g = cv2.divide(lit, cv2.max(mean_g, floor))
    np.maximum(var_g, 0.0, out=var_g)
    den = cv2.add(var_g, eps)
    inv_den = np.reciprocal(np.maximum(den, np.float32(1e-30), out=den))
    fits = []
    mse = np.zeros_like(gh)
    for plus, minus in ((0, 2), (1, 3)):
        sh = cv2.subtract(quads[plus], quads[minus])
        mean_s = box(sh)
        cov = cv2.subtract(box(cv2.multiply(gh, sh)), cv2.multiply(mean_g, mean_s))
        q = cv2.multiply(mean_s, inv_mean_g)
        a = cv2.multiply(cv2.multiply(cv2.add(cov, cv2.multiply(eps, q)), inv_den), lit)
        b = cv2.subtract(cv2.multiply(mean_s, lit), cv2.multiply(a, mean_g))
        fits.append((a, b))
        if weight_k is not None:
            var_s = cv2.subtract(box(cv2.multiply(sh, sh)), cv2.multiply(mean_s, mean_s))
            cv2.add(mse, cv2.subtract(var_s, cv2.multiply(a, cov, scale=2.0)), dst=mse)
            cv2.add(mse, cv2.multiply(cv2.multiply(a, a), var_g), dst=mse)
    coeffs = []
    if weight_k is None:
        for a, b in fits:
            coeffs.append((up(box(a)), up(cv2.multiply(box(b), 1.0 / n_col))))
    else:
        per_intensity = cv2.multiply(mse, inv_mean_g)[::2, ::2][lit[::2, ::2] > 0]
        typical = float(np.median(per_intensity)) if per_intensity.size else 0.0
        # the floor's intensity is at least the dark threshold (a floor of 1e-20 gives dark windows
        # weights of 1e20, which break the box sums below them, see
        # test_a_dark_area_does_not_change_the_polarization_beyond_the_reach)
        floor_img = np.maximum(mean_g, np.float32(1e-20 if tiny_floor else floor))
        floor_img *= np.float32(max(weight_k * typical, _WEIGHT_FLOOR_MIN))
        weight = cv2.divide(1.0, cv2.max(mse, floor_img))
        inv_weight_sum = cv2.divide(1.0, box(weight))
        for a, b in fits:
            coeffs.append((up(cv2.multiply(box(cv2.multiply(a, weight)), inv_weight_sum)),
                           up(cv2.multiply(box(cv2.multiply(b, weight)), inv_weight_sum, scale=1.0 / n_col))))
    for c in range(n_col):
        i0, i45, i90, i135 = (planes[k, c] for k in range(4))
        pair_sum = (i0 + i90, i45 + i135)
        g = pair_sum[0] + pair_sum[1]
        for (plus, minus), total, (a_full, b_full) in zip(((i0, i90), (i45, i135)), pair_sum, coeffs, strict=True):
            s_new = a_full * g + b_full
            plus[...] = 0.5 * total + 0.5 * s_new
            minus[...] = total - plus


def _reference_polarization_images(intensities: np.ndarray, *, noise_floor: float,
                                   invalid: np.ndarray | None) -> dict[str, np.ndarray]:
    """``polarization_images`` computed plainly, in float64 numpy: the spec's formulas on the colour means."""
    i = intensities.astype(np.float64)
    i_int = i.mean(axis=2)
    means = i.mean(axis=3)
    s0 = means.sum(axis=2) / 2
    s1, s2 = means[..., 0] - means[..., 2], means[..., 1] - means[..., 3]
    aop = np.mod(0.5 * np.arctan2(s2, s1), np.pi)
    dop = np.clip(np.hypot(s1, s2) / np.maximum(s0, DOP_EPS), 0.0, 1.0)
    return {"i_int": i_int, "i_min": (1 - dop)[..., None] * i_int, "aop": aop, "dop": dop,
            "valid": valid_pixels(s0.astype(np.float32), noise_floor=noise_floor, invalid=invalid)}


def _noisy_frame(layout: MosaicLayout, h: int, w: int, seed: int) -> np.ndarray:
    """A 12-bit textured frame with shot noise, a dark corner and a few saturated samples; normalized."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    albedo = 0.3 + 0.3 * (np.sin(0.9 * x + 0.3 * y) > 0) + 0.3 * rng.random((h, w), dtype=np.float32)
    albedo[: h // 5, : w // 5] = 0.0  # dark: no polarization there
    s0 = np.stack([0.8 * albedo, albedo, 0.6 * albedo][: layout.channels], axis=-1).astype(np.float32)
    aop = np.mod(np.deg2rad(20 + 120 * x / w + 25 * np.sin(y / 15)), np.pi).astype(np.float32)
    dop = (0.2 + 0.15 * np.cos(x / 20) * np.sin(y / 17)).astype(np.float32)
    clean = mosaic(intensities_from_polarization(s0, aop, dop), layout)
    raw = np.clip(np.rint(rng.poisson(np.clip(clean, 0, None) * 10_000.0) / 10_000.0 * 4095), 0, 4095)
    if h >= 64:
        raw.flat[rng.integers(0, raw.size, 5)] = 4095
    return (raw / 4095).astype(np.float32)


CASES = {  # heights not a multiple of the strip height, and one below it
    "colour 200x264": (IMX250MYR, 200, 264),
    "mono 138x160": (IMX250MZR, 138, 160),
    "colour 24x40": (IMX250MYR, 24, 40),
}


@pytest.mark.parametrize("weight_k", [GUIDED_WEIGHT_K, None], ids=["weighted", "plain"])
@pytest.mark.parametrize("case", list(CASES))
def test_guided_equals_the_reference(case: str, weight_k: float | None) -> None:
    layout, h, w = CASES[case]
    raw = _noisy_frame(layout, h, w, seed=3)
    ref = demosaic(raw, layout, method="bilinear").transpose(2, 3, 0, 1).copy()
    _reference_guided(ref, weight_k=weight_k)
    fast = demosaic(raw, layout, method="bilinear").transpose(2, 3, 0, 1).copy()
    guided_polarization(fast, weight_k=weight_k)
    assert np.abs(fast - ref).max() <= 1e-5 * np.abs(ref).max()
    if weight_k is not None:  # the default method's path in demosaic() too
        via_demosaic = demosaic(raw, layout, method="guided").transpose(2, 3, 0, 1)
        assert np.abs(via_demosaic - ref).max() <= 1e-5 * np.abs(ref).max()
        assert np.abs(fast - ref).max() > 0 or np.array_equal(fast, ref)  # compared on real data


@pytest.mark.parametrize("case", list(CASES))
def test_decode_frame_equals_the_reference(case: str) -> None:
    """decode_frame (default: guided) against the reference guided step and float64 Stokes/AoP/DoP."""
    layout, h, w = CASES[case]
    raw = _noisy_frame(layout, h, w, seed=7)
    saturated = raw >= 1.0
    options = DecodeOptions()
    assert options.demosaic == "guided"
    images = decode_frame(raw, layout, saturated=saturated, options=options)
    planes = demosaic(raw, layout, method="bilinear").transpose(2, 3, 0, 1).copy()
    _reference_guided(planes)
    invalid = saturation_footprint(saturated, layout, method="guided")
    ref = _reference_polarization_images(planes.transpose(2, 3, 0, 1), noise_floor=options.noise_floor,
                                         invalid=invalid)
    scale = np.abs(ref["i_int"]).max()
    channels = 3 if layout.is_colour else 1
    np.testing.assert_allclose(images.i_int[..., :channels], ref["i_int"], rtol=0, atol=1e-5 * scale)
    np.testing.assert_allclose(images.i_min[..., :channels], ref["i_min"], rtol=0, atol=1e-5 * scale)
    valid = ref["valid"]
    assert np.array_equal(images.valid, valid) and 0.3 < valid.mean() < 1.0
    np.testing.assert_allclose(images.dop[valid], ref["dop"][valid], rtol=0, atol=1e-5)
    d_aop = np.abs(images.aop - ref["aop"])[valid & (ref["dop"] > 0.02)]
    assert np.minimum(d_aop, np.pi - d_aop).max() < 1e-4  # radians; float32 atan2 of float32 s1, s2
    assert np.all((images.aop >= 0) & (images.aop < np.pi)) and np.all((images.dop >= 0) & (images.dop <= 1))


def test_polarization_images_of_strided_intensities_equal_the_planar_ones() -> None:
    """An (H, W, 4, C) C-ordered array (not demosaic's planar storage) gives the same result."""
    raw = _noisy_frame(IMX250MYR, 72, 96, seed=2)
    planar = demosaic(raw, IMX250MYR, method="guided")
    a = polarization_images(planar, noise_floor=0.01)
    b = polarization_images(np.ascontiguousarray(planar), noise_floor=0.01)
    for name in ("i_int", "i_min", "dop", "valid"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), rtol=0, atol=1e-6, err_msg=name)
    polarized = a.dop > 0.02  # elsewhere the AoP of a tiny (s1, s2) moves with its rounding
    assert polarized.mean() > 0.5
    np.testing.assert_allclose(a.aop[polarized], b.aop[polarized], rtol=0, atol=1e-4)


def test_dark_windows_do_not_break_the_box_sums_below_them() -> None:
    """A floor of 1e-20 would give dark windows weights of ~1e20, and the rounding of OpenCV's
    running box sums (double) would then leave errors ~1e4 in the weight sums of the columns below
    a dark area, ~100x a lit window's weight. The dark-threshold floor differs from it only there."""
    raw = _noisy_frame(IMX250MYR, 200, 264, seed=3)  # dark top-left corner: rows < 40, columns < 52
    tiny = demosaic(raw, IMX250MYR, method="bilinear").transpose(2, 3, 0, 1).copy()
    _reference_guided(tiny, tiny_floor=True)
    floored = demosaic(raw, IMX250MYR, method="guided").transpose(2, 3, 0, 1)
    scale = np.abs(floored).max()
    below = (slice(None), slice(None), slice(40 + 14, None), slice(0, 52 - 14))
    beside = (slice(None), slice(None), slice(None), slice(52 + 14, None))
    assert np.abs(tiny - floored)[below].max() > 1e-3 * scale
    assert np.abs(tiny - floored)[beside].max() <= 1e-5 * scale


@pytest.mark.parametrize("method", ["bilinear", "edge-aware", "guided", "eari", "eari-guided"])
def test_decode_frame_strips_equal_polarization_images_of_the_demosaic(method: str) -> None:
    """decode_frame's strip-by-strip Stokes (on_strip) gives exactly polarization_images of demosaic()."""
    raw = _noisy_frame(IMX250MYR, 104, 136, seed=11)
    mask = np.ones(raw.shape, dtype=bool)
    mask[:, :9] = False
    images = decode_frame(raw, IMX250MYR, saturated=raw >= 1.0, mask=mask,
                          options=DecodeOptions(demosaic=method))
    invalid = saturation_footprint(raw >= 1.0, IMX250MYR, method=method) | ~mask
    ref = polarization_images(demosaic(raw, IMX250MYR, method=method), noise_floor=0.01, invalid=invalid)
    for name in ("i_int", "i_min", "aop", "dop", "valid"):
        assert np.array_equal(getattr(images, name), getattr(ref, name)), name
    assert 0.2 < images.valid.mean() < 1.0
