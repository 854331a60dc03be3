"""Holding a surface inside the masks' visual hull (pmvir.geometry.hull_fit)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from pmvir.errors import ConfigError
from pmvir.geometry.hull_fit import fit_inside_hull, hull_depth, mask_distance
from pmvir.synth.rig import ring_cameras

W, H = 160, 128


@pytest.fixture(scope="module")
def sphere_views() -> tuple[list, list[np.ndarray]]:
    """12 cameras around the unit sphere and its exact masks (a pixel is in when its centre ray meets it)."""
    cameras = ring_cameras(12, W, H, object_radius=1.0)
    masks = []
    for cam in cameras:
        origins, dirs = cam.pixel_rays()
        along = -(origins * dirs).sum(-1)  # the ray's closest approach to the centre
        closest = origins + along[..., None] * dirs
        masks.append(np.linalg.norm(closest, axis=-1) <= 1.0)
    return cameras, masks


def _sphere(subdivisions: int = 4) -> tuple[np.ndarray, np.ndarray]:
    m = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_midpoint(subdivisions)
    v = np.asarray(m.vertices)
    return v / np.linalg.norm(v, axis=1, keepdims=True), np.asarray(m.triangles)


def test_mask_distance_puts_the_boundary_between_pixels() -> None:
    mask = np.zeros((9, 9), bool)
    mask[2:7, 2:7] = True
    d = mask_distance(mask)
    assert d[4, 2] == pytest.approx(0.5) and d[4, 1] == pytest.approx(-0.5)
    assert d[4, 4] == pytest.approx(2.5) and d[4, 0] == pytest.approx(-1.5)
    assert np.all(mask_distance(np.ones((4, 4), bool)) == np.inf)
    assert np.all(mask_distance(np.zeros((4, 4), bool)) == -np.inf)


def test_a_bulge_past_the_silhouettes_is_pulled_in_and_the_rest_stays(sphere_views: tuple) -> None:
    """The unit sphere with its upper cap pushed out 5%: the cap moves back toward the truth, every
    vertex within 1% of it before stays there, and none moves outward."""
    cameras, masks = sphere_views
    v, f = _sphere()
    cap = v[:, 2] > 0.3
    bulged = v * np.where(cap, 1.05, 1.0)[:, None]
    fit = fit_inside_hull(bulged, f, cameras, masks, tolerance_px=0.5)
    r0, r1 = np.linalg.norm(bulged, axis=1), np.linalg.norm(fit.vertices, axis=1)
    assert fit.outside_before > 0.5 * cap.sum() and fit.outside_after < 0.1 * fit.outside_before, fit
    assert np.all(r1 <= r0 + 1e-12)  # never outward
    assert np.abs(r1[cap] - 1.0).mean() < 0.3 * np.abs(r0[cap] - 1.0).mean(), np.abs(r1[cap] - 1.0).mean()
    assert np.abs(r1[~cap] - 1.0).max() < 0.01
    least, gsd = hull_depth(fit.vertices, cameras, [mask_distance(m) for m in masks])
    assert least.min() > -1.0 and np.all(gsd > 0)


def test_a_surface_inside_the_hull_does_not_move(sphere_views: tuple) -> None:
    cameras, masks = sphere_views
    v, f = _sphere()
    for surface in (0.97 * v, v):  # inside; on the truth (mixed silhouette pixels: within the tolerance)
        fit = fit_inside_hull(surface, f, cameras, masks, tolerance_px=0.5)
        assert fit.outside_before == 0 and fit.moved == 0, fit
        assert np.array_equal(fit.vertices, surface)


def test_views_without_masks_do_not_count(sphere_views: tuple) -> None:
    cameras, masks = sphere_views
    v, f = _sphere(3)
    fit = fit_inside_hull(1.1 * v, f, cameras, [None] * len(cameras))
    assert fit.moved == 0 and np.array_equal(fit.vertices, 1.1 * v)
    one = fit_inside_hull(1.1 * v, f, cameras, [masks[0]] + [None] * (len(cameras) - 1))
    assert 0 < one.moved < len(v)  # only what view 0's silhouette rules out
    # an empty mask (a failed segmentation) or a full one draws no silhouette: it moves nothing
    blank = [np.zeros_like(masks[0]), np.ones_like(masks[1])] + list(masks[2:])
    on_truth = fit_inside_hull(v, f, cameras, blank)
    assert on_truth.moved == 0 and np.array_equal(on_truth.vertices, v)


def test_bad_arguments_are_config_errors(sphere_views: tuple) -> None:
    cameras, masks = sphere_views
    v, f = _sphere(2)
    with pytest.raises(ConfigError, match="must be >= 0"):
        fit_inside_hull(v, f, cameras, masks, tolerance_px=-1.0)
    with pytest.raises(ConfigError, match="masks"):
        fit_inside_hull(v, f, cameras, masks[:3])
