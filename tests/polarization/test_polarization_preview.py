"""Preview images: sRGB encoding, exposure, DoP grey, AoP colour wheel, PNG writing."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from pmvir.polarization.preview import (
    aop_preview,
    dop_preview,
    exposure_scale,
    intensity_preview,
    srgb_encode,
    write_png,
)


def test_srgb_encode_known_values() -> None:
    got = srgb_encode(np.array([-1.0, 0.0, 0.0031308, 0.5, 1.0, 3.0]))
    np.testing.assert_allclose(got, [0.0, 0.0, 0.04045, 0.735357, 1.0, 1.0], atol=1e-5)
    assert got.dtype == np.float32


def test_exposure_scale_maps_the_percentile_of_valid_pixels_to_one() -> None:
    img = np.zeros((10, 10, 3), np.float32)
    img[..., 1] = np.linspace(0.0, 0.5, 100).reshape(10, 10)
    assert exposure_scale(img, percentile=100.0) == pytest.approx(2.0)
    valid = np.zeros((10, 10), bool)
    valid[:5] = True  # values up to about 0.247
    assert exposure_scale(img, valid, percentile=100.0) == pytest.approx(1 / img[4, 9, 1])
    assert exposure_scale(np.zeros((4, 4, 3), np.float32)) == 1.0


def test_intensity_preview_is_srgb_rgb_uint8() -> None:
    img = np.zeros((2, 2, 3), np.float32)
    img[0, 0] = [1.0, 0.5, 0.0]
    img[1, 1] = [2.0, 2.0, 2.0]  # clipped
    out = intensity_preview(img, scale=1.0)
    assert out.dtype == np.uint8 and out.shape == (2, 2, 3)
    np.testing.assert_array_equal(out[0, 0], [255, 188, 0])
    np.testing.assert_array_equal(out[1, 1], [255, 255, 255])
    np.testing.assert_array_equal(intensity_preview(img * 0.5, scale=2.0), out)


def test_intensity_preview_of_wrong_shape_raises_value_error() -> None:
    with pytest.raises(ValueError, match=r"\(H, W, 3\)"):
        intensity_preview(np.zeros((2, 2), np.float32))


def test_dop_preview_is_linear_grey_and_black_where_invalid() -> None:
    dop = np.array([[0.0, 0.5, 1.0, 0.7]], np.float32)
    valid = np.array([[True, True, True, False]])
    np.testing.assert_array_equal(dop_preview(dop, valid), [[0, 128, 255, 0]])


def test_aop_preview_hue_follows_aop_and_saturation_follows_dop() -> None:
    aop = np.deg2rad(np.array([[0.0, 60.0, 120.0, 0.0, 90.0, 0.0]], np.float32))
    dop = np.array([[1.0, 0.5, 0.7, 0.0, 1.0, 0.25]], np.float32)
    valid = np.array([[True, True, True, True, False, True]])
    rgb = aop_preview(aop, dop, valid, dop_full_saturation=0.5)
    assert rgb.dtype == np.uint8 and rgb.shape == (1, 6, 3)
    np.testing.assert_array_equal(rgb[0, 0], [255, 0, 0])  # 0: red
    np.testing.assert_array_equal(rgb[0, 1], [0, 255, 0])  # 60 deg: green (DoP 0.5 = full)
    np.testing.assert_array_equal(rgb[0, 2], [0, 0, 255])  # 120 deg: blue
    np.testing.assert_array_equal(rgb[0, 3], [255, 255, 255])  # unpolarized: white
    np.testing.assert_array_equal(rgb[0, 4], [0, 0, 0])  # invalid: black
    np.testing.assert_array_equal(rgb[0, 5], [255, 128, 128])  # half saturation


def test_aop_preview_with_mismatched_shapes_raises_value_error() -> None:
    with pytest.raises(ValueError, match="matching"):
        aop_preview(np.zeros((2, 2), np.float32), np.zeros((2, 3), np.float32))


def test_aop_preview_with_bad_scale_raises_value_error() -> None:
    with pytest.raises(ValueError, match="dop_full_saturation"):
        aop_preview(np.zeros((2, 2), np.float32), np.zeros((2, 2), np.float32), dop_full_saturation=0.0)


def test_write_png_keeps_rgb_order(tmp_path: Path) -> None:
    img = np.zeros((4, 4, 3), np.uint8)
    img[..., 0] = 200  # red
    path = write_png(tmp_path / "red.png", img)
    back = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)  # OpenCV reads BGR
    np.testing.assert_array_equal(back[0, 0], [0, 0, 200])
    assert not list(tmp_path.glob(".*tmp"))


def test_write_png_rejects_float_images(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="uint8"):
        write_png(tmp_path / "x.png", np.zeros((4, 4), np.float32))
