"""Dense stereo (pmvir.geometry.mvs: sweep, fusion, dense, colmap) against ground truth."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pycolmap
import pytest
from pydantic import ValidationError

from pmvir.camera import Camera, look_at
from pmvir.capture import open_capture
from pmvir.config import MvsOptions
from pmvir.errors import CanceledError, ReconstructionError
from pmvir.evaluate import SurfaceQuery, sample_surface
from pmvir.geometry.mvs.colmap import (
    colmap_fusion,
    read_colmap_array,
    write_colmap_array,
    write_depth_maps,
    write_workspace,
)
from pmvir.geometry.mvs.dense import dense_stereo
from pmvir.geometry.mvs.fusion import backproject, filter_and_fuse, occluding_views
from pmvir.geometry.mvs.sweep import (
    DepthMap,
    StereoView,
    prepare_view,
    project_points,
    scale_camera,
    select_neighbours,
    sweep_depth,
    view_depth_range,
)
from pmvir.io.ply import read_mesh
from pmvir.progress import Progress
from pmvir.synth.rig import ring_cameras


def _true_depth(path: Path, name: str, shape: tuple[int, int]) -> np.ndarray:
    """The true depth on a downscaled grid: mean of the full-resolution block, 0 unless all of it is object"""
    full = np.load(path / "gt" / "views" / f"{name}.npz")["depth"]
    h, w = shape
    fy, fx = full.shape[0] // h, full.shape[1] // w
    blocks = full[: h * fy, : w * fx].reshape(h, fy, w, fx)
    return np.where((blocks > 0).all(axis=(1, 3)), blocks.mean(axis=(1, 3)), 0.0)


# -- geometry conventions


def test_scale_camera_scales_pixel_coordinates_exactly():
    R, t = look_at(np.array([2.0, 1.0, 0.5]), np.zeros(3))
    cam = Camera.from_intrinsics(500.0, 510.0, 300.5, 240.25, 612, 512, R, t)
    half = scale_camera(cam, 306, 256)
    pts = np.random.default_rng(0).normal(scale=0.3, size=(50, 3))
    uv, z = cam.project(pts)
    uv2, z2 = half.project(pts)
    np.testing.assert_allclose(uv2, uv * 0.5, rtol=0, atol=1e-9)  # COLMAP convention: corners scale
    np.testing.assert_allclose(z2, z)
    uv3, z3 = project_points(cam, pts)
    np.testing.assert_allclose(uv3, uv, atol=1e-9)
    np.testing.assert_allclose(z3, z, atol=1e-12)


def test_sweep_recovers_a_textured_plane_to_a_tenth_of_a_percent():
    """Two views of a fronto-parallel textured plane at depth 2, the source made by its exact homography."""
    size, f, depth = 160, 200.0, 2.0
    ref_cam = Camera.from_intrinsics(f, f, size / 2, size / 2, size, size, np.eye(3), np.zeros(3))
    R_src, t_src = look_at(np.array([0.6, 0.1, 0.0]), np.array([0.0, 0.0, depth]), np.array([0.0, -1.0, 0.0]))
    src_cam = Camera.from_intrinsics(f, f, size / 2, size / 2, size, size, R_src, t_src)
    rng = np.random.default_rng(1)
    texture = cv2.GaussianBlur(rng.random((size, size, 3)).astype(np.float32), (0, 0), 1.2)
    # source pixel -> plane point -> reference pixel (both COLMAP convention, converted to OpenCV's)
    T = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
    H_ref_from_src = (
        ref_cam.K
        @ np.linalg.inv(src_cam.R + np.outer(src_cam.t, [0, 0, 1.0 / depth]))
        @ np.linalg.inv(src_cam.K)
    )
    H_cv = np.linalg.inv(T) @ H_ref_from_src @ T
    src_img = cv2.warpPerspective(texture, H_cv, (size, size), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    full = np.ones((size, size), bool)
    ref = StereoView(texture, full, ref_cam)
    src = StereoView(src_img, full, src_cam)
    dm = sweep_depth(ref, [src], 1.5, 3.0, planes=64, window=7, top_k=1, min_score=0.5)
    inner = np.zeros_like(full)
    inner[20:-20, 20:-20] = True  # away from the borders the warp leaves empty
    d = dm.depth[inner & dm.valid]
    assert (inner & dm.valid).sum() > 0.95 * inner.sum()
    # measured: median relative error 1e-4; plane spacing in inverse depth ~0.3 % of the depth
    assert np.median(np.abs(d / depth - 1.0)) < 1e-3
    assert np.percentile(np.abs(d / depth - 1.0), 95) < 3e-3


def test_neighbours_are_the_nearest_views_within_the_angle_range():
    cams = ring_cameras(24, 200, 160, object_radius=0.5)  # three rings of 8 views, 45 degrees apart
    pts = np.random.default_rng(0).normal(scale=0.1, size=(400, 3))
    nb = select_neighbours(cams, pts, count=4, min_angle_deg=5.0, max_angle_deg=60.0)
    dirs = np.stack([c.center for c in cams])
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    for r, picks in enumerate(nb):
        angle = np.degrees(np.arccos(np.clip(dirs @ dirs[r], -1.0, 1.0)))
        angle[r] = np.inf
        assert r not in picks and len(picks) == 4
        # the triangulation angle is measured at the points (spread 0.1 around the centre): a pair
        # counts with the points that see it between 5 and 60 degrees; wider pairs are never picked
        assert np.all(angle[picks] < 70.0)
        assert angle[picks[0]] <= np.sort(angle)[1] + 1e-9


def test_depth_range_brackets_the_true_depths(blob_capture: Path):
    with open_capture(blob_capture) as cap:
        cam = cap.frames[5].camera
        mask = cap.read_mask(5)
    gt = read_mesh(blob_capture / "gt" / "mesh.ply")
    pts, _, _ = sample_surface(gt.vertices, gt.faces, 3000, seed=1)
    near, far = view_depth_range(cam, pts, mask, margin=0.1)
    depth = np.load(blob_capture / "gt" / "views" / "005.npz")["depth"]
    assert near <= depth[depth > 0].min() and far >= depth[depth > 0].max()
    assert view_depth_range(cam, pts + np.array([0.0, 0.0, 100.0]), mask) is None  # nothing in view


# -- the synthetic blob (36 views, 432 x 360, known poses; depth maps on the 216 x 180 grid)


def test_depth_maps_against_rendered_true_depth(blob_geometry, blob_capture: Path):
    """Median error in pixels of disparity-equivalent: the estimated and the true point projected into the
    view's best neighbour (depth-map grid) differ by this many pixels."""
    dense = blob_geometry.dense
    errors, coverage = [], []
    for i, dm in enumerate(dense.depth_maps):
        assert dm is not None
        truth = _true_depth(blob_capture, blob_geometry.names[i], dm.depth.shape)
        obj = cv2.erode((truth > 0).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        ok = obj & dm.valid
        coverage.append(ok.sum() / obj.sum())
        rows, cols = np.nonzero(ok)
        est = backproject(dm.camera, dm.depth[ok], rows.astype(float), cols.astype(float))
        true = backproject(dm.camera, truth[ok], rows.astype(float), cols.astype(float))
        src = dense.depth_maps[dense.neighbours[i][0]].camera
        errors.append(np.linalg.norm(project_points(src, est)[0] - project_points(src, true)[0], axis=1))
    e = np.concatenate(errors)
    # measured (before the consistency filter): median 0.4 px, 63 % under 1 px; coverage 0.98
    assert np.median(e) < 0.8
    assert np.mean(e < 1.0) > 0.5
    assert np.mean(coverage) > 0.9


def test_fused_points_lie_on_the_true_surface(blob_geometry, blob_capture: Path):
    gt = read_mesh(blob_capture / "gt" / "mesh.ply")
    pts = blob_geometry.dense.points.points
    closest, _, _ = SurfaceQuery(gt.vertices, gt.faces).closest(pts)
    d = np.linalg.norm(pts - closest, axis=1)  # GT diagonal is 1
    # measured: mean 0.0024, median 0.0017, 95th percentile 0.0066
    assert len(pts) > 20_000
    assert d.mean() < 0.004 and np.median(d) < 0.003 and np.percentile(d, 95) < 0.012
    n = blob_geometry.dense.points.normals
    to_cam = np.stack([blob_geometry.cameras[v].center for v in blob_geometry.dense.points.views]) - pts
    assert np.all((n * to_cam).sum(1) > 0)  # normals face the camera that saw the point
    assert blob_geometry.dense.backend == "cpu"
    assert min(blob_geometry.dense.consistent_fraction) > 0.1


def _sphere_depth(camera: Camera, radius: float) -> np.ndarray:
    """(h, w) float32 camera-frame depth of a sphere of ``radius`` at the origin; 0 where missed."""
    h, w = camera.height, camera.width
    rows, cols = (a.ravel().astype(np.float64) for a in np.mgrid[0:h, 0:w])
    c = camera.center
    v = backproject(camera, np.ones(len(rows)), rows, cols) - c  # the ray's point at depth d is c + d v
    a, b, k = (v * v).sum(1), 2.0 * (v @ c), c @ c - radius**2
    disc = b * b - 4.0 * a * k
    d = np.where(disc > 0, (-b - np.sqrt(np.maximum(disc, 0.0))) / (2.0 * a), 0.0)
    return d.reshape(h, w).astype(np.float32)


def test_occlusion_test_drops_a_virtual_surface_that_other_views_see_through():
    """A glossy object's reflection, matched as a virtual image behind its surface, agrees between two
    nearby views and is fused without the occlusion test; the views around see the surface in front of
    it along those rays and the test drops it, keeping the true surface."""
    radius = 0.5
    cams = ring_cameras(24, 160, 128, object_radius=radius, elevations=(0.0,))
    maps = [DepthMap(cam, _sphere_depth(cam, radius), np.ones((cam.height, cam.width), np.float32)) for cam in cams]
    neighbours = [[(i + k) % 24 for k in (1, -1, 2, -2, 3, -3)] for i in range(24)]  # 15 degrees apart
    # a virtual patch 15 % behind the surface in view 0, matched alike in view 1
    rows, cols = np.nonzero(np.hypot(*np.mgrid[-64:64, -80:80]) < 6)
    depth0 = maps[0].depth.copy()
    depth0[rows, cols] *= 1.15
    virtual = backproject(cams[0], depth0[rows, cols], rows, cols)
    uv, z = project_points(cams[1], virtual)
    depth1 = maps[1].depth.copy()
    depth1[np.floor(uv[:, 1]).astype(int), np.floor(uv[:, 0]).astype(int)] = z
    maps[0] = DepthMap(cams[0], depth0, maps[0].score)
    maps[1] = DepthMap(cams[1], depth1, maps[1].score)

    votes = occluding_views(maps, neighbours, 0.01)
    # views 2, 10 and 11 see the sphere in front of the patch (less where their pixels, seen obliquely
    # from view 0, leave some of its pixels without a depth landing on them)
    assert np.median(votes[0][rows, cols]) >= 2 and np.median(votes[0][maps[0].valid]) == 0
    plain, _, _ = filter_and_fuse(maps, neighbours, min_consistent=1)
    tested, _, _ = filter_and_fuse(maps, neighbours, min_consistent=1, max_occluding=1)

    def inside(pts: np.ndarray) -> np.ndarray:
        return np.linalg.norm(pts, axis=1) < 0.97 * radius

    assert inside(plain).sum() > 50  # both views' patches are fused without the test
    # measured: 207 patch points without the test, 5 with it (pixels that no view's depth lands on)
    assert inside(tested).sum() < 0.1 * inside(plain).sum()
    # the true surface stays: what is dropped besides the patches is at grazing angles
    surface = ~inside(plain)
    assert len(tested) - inside(tested).sum() > 0.98 * surface.sum()
    assert np.abs(np.linalg.norm(plain[surface], axis=1) - radius).max() < 0.01 * radius


def test_depth_maps_are_the_same_on_one_thread_and_on_several(blob_set, monkeypatch):
    """The views' sweeps run on a thread per core (OMP_NUM_THREADS caps them): the depth maps and the
    fused points do not depend on how many."""
    s = blob_set
    first = slice(0, 8)
    results = []
    for threads in ("1", "3"):
        monkeypatch.setenv("OMP_NUM_THREADS", threads)
        results.append(
            dense_stereo(
                s.images[first], s.masks[first], s.cameras[first], s.points, names=s.names[first],
                options=TWO_CONFIRMING,
            )
        )
    one, several = results
    maps = [(a, b) for a, b in zip(one.depth_maps, several.depth_maps, strict=True) if a is not None]
    assert len(maps) == 8 and all(b is not None for _, b in maps)
    for a, b in maps:
        np.testing.assert_array_equal(a.depth, b.depth)
        np.testing.assert_array_equal(a.score, b.score)
    np.testing.assert_array_equal(one.points.points, several.points.points)


def test_views_without_masks_are_matched_on_the_full_grid_where_its_depths_agree(blob_set, blob_capture: Path):
    """Without masks, views up to mvs.unmasked_full_grid_px are matched at full resolution (window 5),
    kept when enough of its depths are consistent; with masks, or below that share, on the half grid.
    Both grids' points lie on the true surface."""
    s, views = blob_set, slice(0, 8)
    gt = read_mesh(blob_capture / "gt" / "mesh.ply")
    query = SurfaceQuery(gt.vertices, gt.faces)
    # min_consistent_fraction 0: without masks the black background's depths count, and few agree;
    # voxel 0: every fused depth counts
    common = {"sparse_rig_views": 0, "unmasked_full_grid_px": 432, "planes": 48, "min_consistent_fraction": 0.0,
              "voxel": 0.0}
    runs = {
        "masked": (s.masks[views], MvsOptions(**common)),
        "unmasked": ([None] * 8, MvsOptions(**common, unmasked_full_min_consistent=0.0)),
        "unmasked, too few consistent": ([None] * 8, MvsOptions(**common)),
    }
    reported: list[tuple[float, str]] = []
    results = {
        name: dense_stereo(
            s.images[views], masks, s.cameras[views], s.points, names=s.names[views], options=options,
            progress=Progress(lambda stage, f, m: reported.append((f, m))) if "too few" in name else None,
        )
        for name, (masks, options) in runs.items()
    }
    h, w = s.images[0].shape[:2]
    half, full = (h // 2, w // 2), (h, w)
    for name, grid, window in (("masked", half, 3), ("unmasked", full, 5), ("unmasked, too few consistent", half, 3)):
        r = results[name]
        maps = [m for m in r.depth_maps if m is not None]
        assert len(maps) == 8 and all(m.depth.shape == grid for m in maps), name
        assert (r.grid, r.window) == (f"{grid[1]}x{grid[0]}", window), name
    assert results["masked"].full_grid_consistent is None and results["unmasked"].full_grid_consistent is None
    # the black background's noise: few of the full grid's depths agree (measured 0.05), so it is not kept
    tried = results["unmasked, too few consistent"].full_grid_consistent
    assert tried is not None and 0.0 < tried < 0.15
    assert "full_grid_not_kept" in results["unmasked, too few consistent"].timings
    # the full grid's try takes the first 80 % of the progress bar, the half grid's depth maps the rest
    full_try = [f for f, m in reported if "full-resolution grid" in m]
    half = [f for f, m in reported if m.startswith("depth map") and "full-resolution" not in m]
    assert len(full_try) == 8 and len(half) == 8 and max(full_try) < 0.8 <= min(half) < max(half) < 1.0
    assert reported[-1] == (1.0, "fusing depth maps")
    # on the object the full grid fuses more points (measured: 50,776 against 38,696 within 1 % of the
    # diagonal)
    near = {}
    for name in ("masked", "unmasked"):
        pts = results[name].points.points
        d = np.linalg.norm(pts - query.closest(pts)[0], axis=1)  # GT diagonal is 1
        near[name] = int((d < 0.01).sum())
        assert np.median(d[d < 0.05]) < 0.003, name
    assert near["unmasked"] > 1.15 * near["masked"], near


def test_colmap_workspace_and_fusion_of_our_depth_maps(
    blob_geometry, blob_capture: Path, blob_views, tmp_path: Path
):
    """The COLMAP backend's workspace and COLMAP's stereo fusion (CPU), fed with the CPU depth maps."""
    g = blob_geometry
    with open_capture(blob_capture) as cap:
        masks = [cap.read_mask(i) for i in range(len(cap))]
    root = write_workspace(
        tmp_path / "ws",
        [v.i_int for v in blob_views],
        masks,
        g.cameras,
        g.names,
        g.dense.neighbours,
        g.sparse.points,
    )
    write_depth_maps(root, g.names, g.dense.depth_maps)
    back = read_colmap_array(root / "stereo" / "depth_maps" / f"{g.names[0]}.png.geometric.bin")
    assert back.shape == g.dense.depth_maps[0].depth.shape
    points, normals = colmap_fusion(root, max_reproj_error=2.0, max_depth_error=0.01)
    gt = read_mesh(blob_capture / "gt" / "mesh.ply")
    closest, _, _ = SurfaceQuery(gt.vertices, gt.faces).closest(points)
    d = np.linalg.norm(points - closest, axis=1)
    assert len(points) > 5000
    assert np.median(d) < 0.003  # measured 0.0015
    assert np.allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-5)


def test_colmap_array_round_trip(tmp_path: Path):
    a = np.random.default_rng(0).random((7, 5, 3)).astype(np.float32)
    write_colmap_array(tmp_path / "a.bin", a)
    assert (tmp_path / "a.bin").read_bytes().startswith(b"5&7&3&")
    np.testing.assert_array_equal(read_colmap_array(tmp_path / "a.bin"), a)
    write_colmap_array(tmp_path / "b.bin", a[..., 0])
    np.testing.assert_array_equal(read_colmap_array(tmp_path / "b.bin"), a[..., 0])


# -- bad inputs


#: Two confirming views, as on captures of more than ``sparse_rig_views`` views: with one (12 views or
#: fewer) the silhouettes alone make depths inside a convex visual hull agree (measured: 10-16 % of the
#: object pixels of a textureless sphere and of unrelated textures, as many as on a textured blob).
TWO_CONFIRMING = MvsOptions(sparse_rig_views=0)


def test_textureless_views_raise_reconstruction_error(textureless_set):
    s = textureless_set
    with pytest.raises(ReconstructionError, match="textureless"):
        dense_stereo(s.images, s.masks, s.cameras, s.points, names=s.names, options=TWO_CONFIRMING)


def test_views_that_do_not_overlap_raise_reconstruction_error(unrelated_set):
    s = unrelated_set
    with pytest.raises(ReconstructionError, match="not overlap") as info:
        dense_stereo(
            s.images, s.masks, s.cameras, s.points, names=s.names,
            options=TWO_CONFIRMING.model_copy(update={"scale": 1.0}),
        )
    assert "000" in str(info.value)  # names views without consistent depth


def test_fewer_than_two_registered_views_raise(unrelated_set):
    s = unrelated_set
    cams = [s.cameras[0]] + [None] * (len(s.cameras) - 1)
    with pytest.raises(ReconstructionError, match="at least 2 registered views"):
        dense_stereo(s.images, s.masks, cams, s.points, names=s.names, options=MvsOptions())


def test_colmap_backend_without_cuda_raises(unrelated_set):
    if pycolmap.has_cuda:
        pytest.skip("pycolmap has CUDA here")
    s = unrelated_set
    with pytest.raises(ReconstructionError, match="CUDA"):
        dense_stereo(
            s.images,
            s.masks,
            s.cameras,
            s.points,
            names=s.names,
            options=MvsOptions(backend="colmap-cuda"),
        )


def test_dense_stereo_stops_when_canceled(unrelated_set):
    s = unrelated_set
    polls = []

    def cancel() -> bool:
        polls.append(1)
        return len(polls) > 2

    with pytest.raises(CanceledError):
        dense_stereo(
            s.images,
            s.masks,
            s.cameras,
            s.points,
            names=s.names,
            options=MvsOptions(),
            progress=Progress(should_cancel=cancel),
        )
    assert len(polls) == 3


def test_stereo_options_are_checked():
    with pytest.raises(ValidationError, match="odd"):
        MvsOptions(window=8)
    with pytest.raises(ValidationError, match="min_angle_deg"):
        MvsOptions(min_angle_deg=40.0, max_angle_deg=30.0)
    with pytest.raises(ValidationError):
        MvsOptions(scale=0.0)


def test_prepare_view_checks_shapes():
    cam = Camera.from_intrinsics(100.0, 100.0, 32.0, 24.0, 64, 48, np.eye(3), np.zeros(3))
    img = np.ones((48, 64, 3), np.float32)
    v = prepare_view(img, None, cam, scale=0.5)
    assert v.image.shape == (24, 32, 3) and v.mask.all() and v.camera.width == 32
    with pytest.raises(ValueError, match="camera"):
        prepare_view(np.ones((40, 64, 3), np.float32), None, cam, scale=0.5)
    with pytest.raises(ValueError, match="mask"):
        prepare_view(img, np.ones((10, 10), bool), cam, scale=0.5)


def test_depth_map_valid_is_positive_depth():
    cam = Camera.from_intrinsics(10.0, 10.0, 2.0, 2.0, 4, 4, np.eye(3), np.zeros(3))
    d = np.zeros((4, 4), np.float32)
    d[1, 2] = 3.0
    assert DepthMap(cam, d, d).valid.sum() == 1
