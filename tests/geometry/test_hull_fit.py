"""Holding a surface inside the masks' visual hull (pmvir.geometry.silhouette.hull_fit)."""

from __future__ import annotations

import cv2
import numpy as np
import open3d as o3d
import pytest

from pmvir.errors import ConfigError
from pmvir.geometry.silhouette.hull_fit import RimFit, fit_inside_hull, fit_to_rims, hull_depth, mask_distance
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


def test_the_kth_least_distance_is_the_kth_of_the_views_sorted(sphere_views: tuple) -> None:
    cameras, masks = sphere_views
    v, _ = _sphere(2)
    x = 1.04 * v
    dists = [mask_distance(m) for m in masks]
    every = np.sort([hull_depth(x, [c], [d])[0] for c, d in zip(cameras, dists, strict=True)], axis=0)
    for rank in (1, 2, 3):
        least, gsd = hull_depth(x, cameras, dists, rank=rank)
        assert np.array_equal(least, every[rank - 1]) and np.all(gsd > 0)
    with pytest.raises(ConfigError, match="rank"):
        hull_depth(x, cameras, dists, rank=0)


def test_one_mask_cutting_into_the_object_moves_nothing_when_two_views_must_agree(sphere_views: tuple) -> None:
    """View 0's mask loses a 6 px strip of the sphere (a segmentation's cut): with one view the true
    sphere's vertices there move inward, with two none does; a bulge past every silhouette moves in
    either way."""
    cameras, masks = sphere_views
    v, f = _sphere()
    cut = [m.copy() for m in masks]
    cols = np.flatnonzero(cut[0].any(axis=0))
    cut[0][:, cols.min():cols.min() + 6] = False
    one = fit_inside_hull(v, f, cameras, cut, tolerance_px=0.5)
    two = fit_inside_hull(v, f, cameras, cut, tolerance_px=0.5, views=2)
    assert one.moved > 20, one
    assert two.moved == 0 and np.array_equal(two.vertices, v), two
    cap = v[:, 2] > 0.3
    bulged = v * np.where(cap, 1.05, 1.0)[:, None]
    fit = fit_inside_hull(bulged, f, cameras, cut, tolerance_px=0.5, views=2)
    r0, r1 = np.linalg.norm(bulged, axis=1), np.linalg.norm(fit.vertices, axis=1)
    assert np.abs(r1[cap] - 1.0).mean() < 0.5 * np.abs(r0[cap] - 1.0).mean(), np.abs(r1[cap] - 1.0).mean()
    assert np.all(r1 <= r0 + 1e-12)


def _flap(v: np.ndarray, f: np.ndarray, x: float, size: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The mesh (``v``, ``f``) with a square flap of 5 x 5 vertices added in the x-z plane, centred at
    (``x``, 0, 0) and ``size`` wide (its normal along y), and the (V,) bool of the flap's vertices."""
    s, t = np.meshgrid(np.linspace(-0.5, 0.5, 5) * size, np.linspace(-0.5, 0.5, 5) * size)
    flap = np.stack([x + s.ravel(), np.zeros(25), t.ravel()], axis=1)
    grid = np.arange(25).reshape(5, 5)
    quads = np.stack([grid[:-1, :-1], grid[:-1, 1:], grid[1:, 1:], grid[1:, :-1]], -1).reshape(-1, 4)
    faces = np.concatenate([quads[:, [0, 1, 2]], quads[:, [0, 2, 3]]]) + len(v)
    on = np.r_[np.zeros(len(v), bool), np.ones(25, bool)]
    return np.vstack([v, flap]), np.vstack([f, faces]), on


def test_a_step_that_gains_nothing_in_the_image_is_taken_back(sphere_views: tuple) -> None:
    """A flap beside the sphere whose normal runs along the rays of the views that rule it out (those
    looking along y): a step along the normal brings it no closer to their masks. With every step
    kept it is carried 3 px away along y; with ``min_gain`` it stays where it is and counts as
    stopped, while the bulged cap still moves in as far as without."""
    cameras, masks = sphere_views
    v, f = _sphere()
    cap = v[:, 2] > 0.3
    bulged, faces, on = _flap(v * np.where(cap, 1.05, 1.0)[:, None], f, 1.12, 0.08)
    least, _ = hull_depth(bulged[on], cameras, [mask_distance(m) for m in masks], rank=2)
    assert np.all(least < -2.0), least  # the flap lies outside two views' masks by pixels
    kept = fit_inside_hull(bulged, faces, cameras, masks, tolerance_px=0.5, views=2)
    gated = fit_inside_hull(bulged, faces, cameras, masks, tolerance_px=0.5, views=2, min_gain=0.2)
    carried = np.abs(kept.vertices[on, 1] - bulged[on, 1])
    assert carried.min() > 2.0 * _gsd(cameras), carried  # along y, not toward the sphere
    assert np.abs(gated.vertices[on] - bulged[on]).max() < 1e-12
    assert gated.stopped >= on.sum() and kept.stopped == 0, (gated, kept)
    r_kept, r_gated = (np.linalg.norm(fit.vertices[~on], axis=1) for fit in (kept, gated))
    assert np.abs(r_gated[cap] - 1.0).mean() < 1.1 * np.abs(r_kept[cap] - 1.0).mean() + 1e-4
    assert np.abs(r_gated[cap] - 1.0).mean() < 0.5 * 0.05


def test_bad_arguments_are_config_errors(sphere_views: tuple) -> None:
    cameras, masks = sphere_views
    v, f = _sphere(2)
    with pytest.raises(ConfigError, match="must be >= 0"):
        fit_inside_hull(v, f, cameras, masks, tolerance_px=-1.0)
    with pytest.raises(ConfigError, match="views must be >= 1"):
        fit_inside_hull(v, f, cameras, masks, views=0)
    with pytest.raises(ConfigError, match="min_gain"):
        fit_inside_hull(v, f, cameras, masks, min_gain=1.5)
    with pytest.raises(ConfigError, match="masks"):
        fit_inside_hull(v, f, cameras, masks[:3])


def _gsd(cameras: list) -> float:
    return float(np.linalg.norm(cameras[0].center) / cameras[0].K[0, 0])


def test_a_shrunk_surface_moves_out_to_masks_trusted_as_drawn(sphere_views: tuple) -> None:
    """The unit sphere shrunk by 1 and 2 px, the masks trusted as drawn (margin 0): gain 1 brings it back
    within 0.2 px, gain 0.5 halfway; every vertex moves outward; the true sphere moves under 0.1 px on
    average (the rims' own inset)."""
    cameras, masks = sphere_views
    v, f = _sphere()
    gsd = _gsd(cameras)
    for shrink_px in (1.0, 2.0):
        scale = 1.0 - shrink_px * gsd
        for gain, left in ((1.0, 0.2), (0.5, 0.6)):
            fit = fit_to_rims(scale * v, f, cameras, masks, gain=gain, mask_margin_px=0.0)
            r = np.linalg.norm(fit.vertices, axis=1)
            assert np.all(r >= scale - 1e-12)  # never inward
            error_px = np.abs(r - 1.0).mean() / gsd
            assert error_px < left * shrink_px, (shrink_px, gain, error_px, fit)
            assert fit.inside > 0.9 * fit.rim_vertices > 0
    on_truth = fit_to_rims(v, f, cameras, masks, gain=0.5)
    assert np.abs(np.linalg.norm(on_truth.vertices, axis=1) - 1.0).mean() / gsd < 0.1, on_truth
    assert on_truth.mean_move_px < 0.1


def _dented(v: np.ndarray, depth: float) -> np.ndarray:
    """The unit sphere with its upper cap (z > 0.4) sunk by ``depth``, blending in over 0.2 < z < 0.4."""
    return v * (1.0 - depth * np.clip((v[:, 2] - 0.2) / 0.2, 0.0, 1.0))[:, None]


def test_a_dented_surface_moves_out_to_its_rims(sphere_views: tuple) -> None:
    """The upper cap sunk 1 and 2 px, the masks' margin estimated: the rest of the rims lie on the outline,
    so the margin is 0; the cap comes back halfway at gain 0.5 and within 0.15x at gain 1, and the rest
    stays within 0.2 px on average (the spread carries the cap's moves a little way)."""
    cameras, masks = sphere_views
    v, f = _sphere()
    gsd = _gsd(cameras)
    cap, rest = v[:, 2] > 0.4, v[:, 2] < 0.2
    for depth_px in (1.0, 2.0):
        dented = _dented(v, depth_px * gsd)
        for gain, left in ((1.0, 0.15), (0.5, 0.6)):
            fit = fit_to_rims(dented, f, cameras, masks, gain=gain)
            assert fit.margin_estimated and fit.mask_margin_px == 0.0, fit
            error_px = np.abs(np.linalg.norm(fit.vertices, axis=1) - 1.0) / gsd
            assert error_px[cap].mean() < left * depth_px, (depth_px, gain, error_px[cap].mean())
            assert error_px[rest].mean() < 0.2, (depth_px, gain, error_px[rest].mean())
            assert np.all(np.linalg.norm(fit.vertices, axis=1) >= np.linalg.norm(dented, axis=1) - 1e-12)


def test_dilated_masks_are_discounted_not_followed(sphere_views: tuple) -> None:
    """The true sphere with masks dilated by one pixel (a generous segmentation): trusted as drawn they
    push it out more than half a pixel; the estimated margin (0.75-1.25 px) or the known one (1 px) keeps
    it within 0.2 px. A uniformly shrunk surface looks the same to the silhouettes: its estimated margin
    takes up most of the shrink (the offset scans, not this fit, are there for a uniform offset)."""
    cameras, masks = sphere_views
    v, f = _sphere()
    gsd = _gsd(cameras)
    dilated = [cv2.dilate(m.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool) for m in masks]

    def error_px(fit: RimFit) -> float:
        return float(np.abs(np.linalg.norm(fit.vertices, axis=1) - 1.0).mean() / gsd)

    trusted = fit_to_rims(v, f, cameras, dilated, mask_margin_px=0.0)
    assert error_px(trusted) > 0.5 and trusted.mask_margin_px == 0.0 and not trusted.margin_estimated
    estimated = fit_to_rims(v, f, cameras, dilated)
    assert 0.75 <= estimated.mask_margin_px <= 1.25 and estimated.margin_estimated, estimated
    assert error_px(estimated) < 0.2, estimated
    known = fit_to_rims(v, f, cameras, dilated, mask_margin_px=1.0)
    assert error_px(known) < 0.2 and known.to_dict()["mask_margin_px"] == 1.0, known
    uniform = fit_to_rims((1.0 - gsd) * v, f, cameras, masks)
    assert 0.5 <= uniform.mask_margin_px <= 1.0 and uniform.mean_move_px < 0.3, uniform


def test_a_rim_fit_needs_masks_and_a_gain(sphere_views: tuple) -> None:
    cameras, masks = sphere_views
    v, f = _sphere(3)
    for fit in (
        fit_to_rims(0.9 * v, f, cameras, [None] * len(cameras)),
        fit_to_rims(0.9 * v, f, cameras, masks, gain=0.0),
        fit_to_rims(0.9 * v, f, cameras, [np.zeros_like(m) for m in masks]),
    ):
        assert fit.rim_vertices == 0 and np.array_equal(fit.vertices, 0.9 * v)


def test_a_rim_beyond_reach_of_the_mask_boundary_counts_for_nothing(sphere_views: tuple) -> None:
    """Masks of the unit sphere, but the mesh is a sphere 10 px inside it: no rim meets the mask's boundary
    within ``reach_px`` (4 px), so nothing is measured and nothing moves (a silhouette that far off is
    not this surface's)."""
    cameras, masks = sphere_views
    v, f = _sphere(3)
    far = fit_to_rims(0.8 * v, f, cameras, masks)
    assert far.rim_vertices == 0 and np.array_equal(far.vertices, 0.8 * v)


def test_bad_rim_fit_arguments_are_config_errors(sphere_views: tuple) -> None:
    cameras, masks = sphere_views
    v, f = _sphere(2)
    for options in ({"gain": -0.1}, {"tolerance_px": -1.0}, {"rim_cos": 0.0}, {"rim_cos": 1.0}, {"reach_px": 0.0}):
        with pytest.raises(ConfigError, match="expected gain"):
            fit_to_rims(v, f, cameras, masks, **options)
    for margin in (-0.5, 4.0):
        with pytest.raises(ConfigError, match="mask_margin_px"):
            fit_to_rims(v, f, cameras, masks, mask_margin_px=margin)
    with pytest.raises(ConfigError, match="masks"):
        fit_to_rims(v, f, cameras, masks[:3])
