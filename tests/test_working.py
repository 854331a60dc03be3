"""The working resolution: binning of decoded images, masks, noise and intrinsics, and a binned run."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from pmvir.capture import open_capture
from pmvir.config import PipelineConfig
from pmvir.errors import ConfigError
from pmvir.evaluate import evaluate_paths
from pmvir.io.colmap_text import read_colmap_text_model
from pmvir.pipeline import run
from pmvir.polarization.stokes import PolarizationImages
from pmvir.synth import synthesize
from pmvir.working import (
    BinnedCapture,
    bin_images,
    bin_mask,
    bin_noise,
    binning_factor,
    frame_extent,
    unbin_mask,
)


@pytest.mark.parametrize(
    ("size", "limit", "factor"),
    [((2448, 2048), 1024, 3), ((2448, 2048), 1280, 2), ((612, 512), 1024, 1), ((1224, 1024), 1024, 2),
     ((2448, 2048), 0, 1), ((2048, 2448), 1224, 2)],
)
def test_binning_factor_is_the_smallest_that_fits(size: tuple[int, int], limit: int, factor: int) -> None:
    assert binning_factor(*size, limit) == factor


def test_binning_factor_rejects_nonsense() -> None:
    with pytest.raises(ConfigError):
        binning_factor(0, 10, 100)
    with pytest.raises(ConfigError):
        binning_factor(10, 10, -1)


def _images(aop: np.ndarray, dop: np.ndarray, i_int: np.ndarray) -> PolarizationImages:
    h, w = aop.shape
    rgb = np.repeat(i_int[..., None], 3, axis=2).astype(np.float32)
    return PolarizationImages(
        i_int=rgb, i_min=(rgb * (1 - dop[..., None])).astype(np.float32), aop=aop.astype(np.float32),
        dop=dop.astype(np.float32), valid=np.ones((h, w), bool),
    )


def test_a_uniform_field_keeps_its_polarization_and_intensity() -> None:
    aop = np.full((8, 10), 3.0, np.float32)  # near pi: the axial wrap must hold
    img = bin_images(_images(aop, np.full((8, 10), 0.4), np.full((8, 10), 0.3)), 2)
    assert img.aop.shape == (4, 5) and img.i_int.shape == (4, 5, 3)
    np.testing.assert_allclose(img.aop, 3.0, atol=1e-5)
    np.testing.assert_allclose(img.dop, 0.4, atol=1e-6)
    np.testing.assert_allclose(img.i_int, 0.3, atol=1e-6)
    assert img.valid.all()


def test_a_block_polarizes_as_its_summed_light() -> None:
    """Crossed AoPs of equal light cancel; the brighter pixel's AoP wins; raw angles near 0 and
    pi are one direction (averaging angles would give pi / 2)."""
    aop = np.array([[0.0, np.pi / 2], [0.05, np.pi - 0.05]], np.float32)
    dop = np.array([[0.5, 0.5], [0.5, 0.5]], np.float32)
    crossed = bin_images(_images(aop[:1].repeat(2, 0), dop, np.ones((2, 2))), 2)
    assert crossed.dop[0, 0] < 1e-6
    brighter = bin_images(_images(aop[:1].repeat(2, 0), dop, np.array([[3.0, 1.0], [3.0, 1.0]])), 2)
    assert abs(brighter.aop[0, 0]) < 1e-5 and brighter.dop[0, 0] == pytest.approx(0.25, abs=1e-6)
    wrap = bin_images(_images(aop[1:].repeat(2, 0), dop, np.ones((2, 2))), 2)
    assert min(wrap.aop[0, 0], np.pi - wrap.aop[0, 0]) < 1e-5
    assert wrap.dop[0, 0] == pytest.approx(0.5 * np.cos(0.1), abs=1e-5)


def test_an_invalid_pixel_invalidates_its_block_and_odd_edges_are_cropped() -> None:
    images = _images(np.zeros((5, 7)), np.zeros((5, 7)), np.ones((5, 7)))
    images.valid[0, 0] = False
    img = bin_images(images, 2)
    assert img.valid.shape == (2, 3)
    assert not img.valid[0, 0] and img.valid.sum() == 5
    assert bin_images(images, 1) is images


def test_masks_and_noise_bin_and_unbin() -> None:
    mask = np.zeros((4, 4), bool)
    mask[:2, :2] = True
    mask[2, 2] = True  # a quarter of its block: background
    mask[0:2, 2] = True  # half of its block: foreground
    np.testing.assert_array_equal(bin_mask(mask, 2), [[True, True], [False, False]])
    assert bin_mask(None, 2) is None
    noise = np.array([[1.0, 3.0], [np.nan, np.nan]], np.float32)
    np.testing.assert_allclose(bin_noise(noise, 2), [[2.0]])
    assert np.isnan(bin_noise(np.full((2, 2), np.nan, np.float32), 2)).all()
    full = unbin_mask(np.array([[True, False]]), 2, (3, 5))
    np.testing.assert_array_equal(full, [[1, 1, 0, 0, 0], [1, 1, 0, 0, 0], [0, 0, 0, 0, 0]])


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("working")
    return synthesize(root / "cap", shape="blob", views=16, size=(384, 320), material="plastic", seed=4)


def test_a_binned_capture_projects_where_the_full_one_does(capture: Path) -> None:
    with open_capture(capture) as cap:
        binned = BinnedCapture(cap, 2)
        assert frame_extent(cap) == (384, 320) and binning_factor(*frame_extent(cap), 200) == 2
        point = np.array([0.01, -0.02, 0.03])
        for full_frame, frame in zip(cap.frames, binned.frames, strict=True):
            full, half = full_frame.camera, frame.camera
            assert full is not None and half is not None
            assert (half.width, half.height) == (192, 160)
            uv_full = full.K @ (full.R @ point + full.t)
            uv_half = half.K @ (half.R @ point + half.t)
            np.testing.assert_allclose(uv_half[:2] / uv_half[2], uv_full[:2] / uv_full[2] / 2, atol=1e-9)
        mask = binned.read_mask(0)
        full_mask = cap.read_mask(0)
        assert mask is not None and full_mask is not None and mask.shape == (160, 192)
        assert abs(mask.mean() - full_mask.mean()) < 0.01
        assert binned.read_raw(0).mosaic.shape == (320, 384)  # raw frames stay full size


def test_a_binned_run_reconstructs_at_the_working_size(capture: Path, tmp_path: Path) -> None:
    config = PipelineConfig.model_validate(
        {"decode": {"max_working_size_px": 200}, "geometry": {"subdivision": {"max_area_px": 8.0}},
         "refine": {"solver": {"max_iterations": 4}}}
    )
    run(config, capture, tmp_path / "out")
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert report["resolution"] == {
        "frames": "384x320", "binning": 2, "decode": "384x320", "geometry": "192x160", "refine": "192x160"
    }
    cameras, images = read_colmap_text_model(tmp_path / "out" / "poses")
    assert len(images) == 16 and {(c.width, c.height) for c in cameras.values()} == {(192, 160)}
    metrics = evaluate_paths(tmp_path / "out", capture / "gt", n_samples=20000)
    assert metrics.accuracy < 0.006 and metrics.completeness < 0.008  # fractions of the diagonal
