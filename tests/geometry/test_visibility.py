"""Per-vertex visibility: ray casting against a brute-force float64 Moller-Trumbore reference."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from pmvir.camera import Camera, look_at
from pmvir.errors import MeshError
from pmvir.geometry.projection import project_columns
from pmvir.geometry.visibility import face_visibility, vertex_visibility
from pmvir.io.ply import vertex_normals

MIN_COS = 0.05
REL_TOL = 1e-4


def _o3d_arrays(mesh: o3d.geometry.TriangleMesh) -> tuple[np.ndarray, np.ndarray]:
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.triangles, dtype=np.int64)


def _torus_and_sphere() -> tuple[np.ndarray, np.ndarray]:
    """A torus (self-occluding) with a sphere floating above its hole: two components."""
    tv, tf = _o3d_arrays(o3d.geometry.TriangleMesh.create_torus(1.0, 0.35, 48, 16))
    sv, sf = _o3d_arrays(o3d.geometry.TriangleMesh.create_sphere(0.45, 12))
    sv = sv + np.array([0.3, 0.0, 0.6])
    return np.concatenate([tv, sv]), np.concatenate([tf, sf + len(tv)])


def _ring_cameras() -> list[Camera]:
    centres = [
        (4.0, 0.0, 0.8), (0.0, -4.0, 2.0), (-3.0, 3.0, 0.3),
        (0.5, 0.5, 4.5), (2.0, 2.5, -2.0), (-4.0, -1.0, 1.2),
    ]
    cams = []
    for c in centres:
        R, t = look_at(np.array(c), np.zeros(3))
        cams.append(Camera.from_intrinsics(110.0, 110.0, 80.0, 60.0, 160, 120, R, t))
    return cams


def _reference_visibility(
    v: np.ndarray, f: np.ndarray, cams: list[Camera], masks: list, *, margin: float = 1e-5
) -> tuple[np.ndarray, np.ndarray]:
    """Brute-force visibility in float64, and where it is ambiguous (ray grazing an edge or near tfar).

    Returns:
        vis (N, V) bool, ambiguous (N, V) bool.
    """
    n = vertex_normals(v, f)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = b - a, c - a
    vis = np.zeros((len(v), len(cams)), dtype=bool)
    amb = np.zeros_like(vis)
    tfar = 1.0 - REL_TOL
    for j, cam in enumerate(cams):
        centre = -cam.R.T @ cam.t
        pc = (cam.R @ v.T).T + cam.t
        z = pc[:, 2]
        u = cam.K[0, 0] * pc[:, 0] / z + cam.K[0, 2]
        w = cam.K[1, 1] * pc[:, 1] / z + cam.K[1, 2]
        cand = (z > 0) & (u >= 0) & (u < cam.width) & (w >= 0) & (w < cam.height)
        if masks[j] is not None:
            for i in np.flatnonzero(cand):
                cand[i] = bool(masks[j][int(np.floor(w[i])), int(np.floor(u[i]))])
        to_cam = centre - v
        cand &= np.sum(n * to_cam, axis=1) / np.linalg.norm(to_cam, axis=1) > MIN_COS
        idx = np.flatnonzero(cand)
        for chunk in np.array_split(idx, max(1, len(idx) // 128)):
            d = v[chunk] - centre  # (R, 3), t in units of |p - c|
            pvec = np.cross(d[:, None, :], e2[None])  # (R, F, 3)
            det = np.einsum("fk,rfk->rf", e1, pvec)
            ok = np.abs(det) > 1e-14
            inv = np.where(ok, 1.0 / np.where(ok, det, 1.0), 0.0)
            s = centre - a  # (F, 3)
            bu = np.einsum("fk,rfk->rf", s, pvec) * inv
            q = np.cross(s, e1)  # (F, 3)
            bv = np.einsum("rk,fk->rf", d, q) * inv
            t = np.einsum("fk,fk->f", e2, q)[None] * inv
            inside = (bu > margin) & (bv > margin) & (bu + bv < 1 - margin)
            sure = ok & inside & (t > margin) & (t < tfar - margin)
            near = (bu > -margin) & (bv > -margin) & (bu + bv < 1 + margin)
            maybe = ok & near & (t > -margin) & (t < tfar + margin)
            hit = ok & (bu >= 0) & (bv >= 0) & (bu + bv <= 1) & (t > 0) & (t < tfar)
            vis[chunk, j] = ~hit.any(axis=1)
            amb[chunk, j] = sure.any(axis=1) != maybe.any(axis=1)
    return vis, amb


def test_matches_brute_force_with_self_occlusion_and_mask():
    v, f = _torus_and_sphere()
    cams = _ring_cameras()
    mask = np.zeros((120, 160), dtype=bool)
    mask[:, :90] = True
    masks = [None, mask, None, None, None, None]
    fast = vertex_visibility(v, f, cams, masks, min_cos=MIN_COS, rel_tol=REL_TOL)
    ref, amb = _reference_visibility(v, f, cams, masks)
    assert fast.shape == (len(v), len(cams)) and fast.dtype == bool
    # The scene must really occlude: many front-facing in-image vertices are hidden.
    no_occlusion = vertex_visibility(
        v, f[:0], cams, masks, min_cos=MIN_COS, rel_tol=REL_TOL, normals=vertex_normals(v, f)
    )
    assert (no_occlusion & ~ref).sum() > 0.1 * no_occlusion.sum()
    assert amb.mean() < 0.01
    assert (fast == ref).mean() >= 0.995
    assert not np.any((fast != ref) & ~amb), "disagreement away from grazing rays"
    assert not fast[:, 1][np.floor(cams[1].project(v)[0][:, 0]) >= 90].any()


def test_plane_back_facing_is_not_visible():
    xs, ys = np.meshgrid(np.linspace(-1, 1, 6), np.linspace(-1, 1, 6))
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(36)], axis=1)
    i = np.arange(36).reshape(6, 6)
    f = np.concatenate(  # normals +z
        [
            np.stack([i[:-1, :-1], i[:-1, 1:], i[1:, 1:]], -1).reshape(-1, 3),
            np.stack([i[:-1, :-1], i[1:, 1:], i[1:, :-1]], -1).reshape(-1, 3),
        ]
    )
    cams = []
    oblique = (0.0, 5.0 * np.sin(np.radians(60)), 5.0 * np.cos(np.radians(60)))
    for centre in [(0, 0, 5.0), (0, 0, -5.0), oblique]:
        R, t = look_at(np.array(centre), np.zeros(3), up=np.array([1.0, 0.0, 0.0]))
        cams.append(Camera.from_intrinsics(200.0, 200.0, 100.0, 100.0, 200, 200, R, t))
    vis = vertex_visibility(v, f, cams)
    assert vis[:, 0].all()  # seen from the front
    assert not vis[:, 1].any()  # from behind: no occluder, but back-facing
    # 60 degrees off the normal: cosine about 0.5 (0.4..0.6 over the plane from 5 units away)
    assert vertex_visibility(v, f, cams[2:], min_cos=0.3)[:, 0].all()
    assert not vertex_visibility(v, f, cams[2:], min_cos=0.7)[:, 0].any()


def test_mask_sampled_at_floor_of_pixel_coordinates():
    cam = Camera.from_intrinsics(100.0, 100.0, 0.0, 0.0, 8, 6, np.eye(3), np.zeros(3))
    # Vertices on the plane z = 2 facing the camera, at chosen pixel coordinates (u, v).
    uu, vv = np.meshgrid(np.arange(-0.75, 9.0, 0.5), np.arange(-0.75, 7.0, 0.5))
    uv = np.stack([uu.ravel(), vv.ravel()], axis=1)
    v = np.concatenate([uv * 2.0 / 100.0, np.full((len(uv), 1), 2.0)], axis=1)
    normals = np.tile([0.0, 0.0, -1.0], (len(v), 1))
    faces = np.zeros((0, 3), dtype=np.int64)
    rows, cols = np.mgrid[0:6, 0:8]
    mask = (rows + cols) % 2 == 0
    vis = vertex_visibility(v, faces, [cam], [mask], normals=normals)[:, 0]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 8) & (uv[:, 1] >= 0) & (uv[:, 1] < 6)
    expected = np.zeros(len(v), dtype=bool)
    col = np.floor(uv[inside, 0]).astype(int)
    row = np.floor(uv[inside, 1]).astype(int)
    expected[inside] = mask[row, col]
    assert inside.sum() > 100 and (~inside).sum() > 20
    np.testing.assert_array_equal(vis, expected)
    # Without a mask every in-image vertex is visible, none outside.
    np.testing.assert_array_equal(vertex_visibility(v, faces, [cam], [None], normals=normals)[:, 0], inside)


def test_far_from_origin_scene_is_handled():
    """float32 ray casting on a mesh 1e4 units from the origin (shifted internally)."""
    v, f = _torus_and_sphere()
    cams = _ring_cameras()
    offset = np.array([1e4, -2e4, 5e3])
    moved = []
    for cam in cams:
        moved.append(Camera(K=cam.K, R=cam.R, t=cam.t - cam.R @ offset, width=cam.width, height=cam.height))
    near = vertex_visibility(v, f, cams)
    far = vertex_visibility(v + offset, f, moved)
    assert (near == far).mean() > 0.999


def test_project_columns_matches_camera_project():
    rng = np.random.default_rng(1)
    pts = rng.normal(size=(500, 3))
    for cam in _ring_cameras():
        cam = Camera(K=cam.K + np.array([[0, 0.3, 0], [0, 0, 0], [0, 0, 0]]), R=cam.R, t=cam.t, width=160, height=120)
        uv, depth = cam.project(pts)
        u, w, z = project_columns(np.ascontiguousarray(pts.T), cam)
        np.testing.assert_allclose(np.stack([u, w], 1), uv, rtol=1e-12, atol=1e-9)
        np.testing.assert_allclose(z, depth, rtol=1e-12, atol=1e-12)


def test_face_visibility_rules():
    vis = np.array([[1, 1], [1, 0], [1, 0], [0, 0]], dtype=bool)
    faces = np.array([[0, 1, 2], [0, 1, 3], [1, 2, 3]])
    np.testing.assert_array_equal(face_visibility(faces, vis), [[1, 0], [0, 0], [0, 0]])
    majority = face_visibility(faces, vis, min_visible_corners=2)
    np.testing.assert_array_equal(majority, [[1, 0], [1, 0], [1, 0]])
    any_corner = face_visibility(faces, vis, min_visible_corners=1)
    np.testing.assert_array_equal(any_corner, [[1, 1], [1, 1], [1, 0]])


def _one_triangle():
    v = np.array([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0], [0.0, 0.1, 2.0]])
    cam = Camera.from_intrinsics(100.0, 100.0, 10.0, 10.0, 20, 20, np.eye(3), np.zeros(3))
    return v, np.array([[0, 2, 1]]), cam


def test_mask_of_wrong_shape_raises_value_error():
    v, f, cam = _one_triangle()
    with pytest.raises(ValueError, match="mask 0"):
        vertex_visibility(v, f, [cam], [np.ones((10, 20), dtype=bool)])


def test_mask_count_mismatch_raises_value_error():
    v, f, cam = _one_triangle()
    with pytest.raises(ValueError, match="one mask entry per camera"):
        vertex_visibility(v, f, [cam], [None, None])


def test_bad_vertices_raise_value_error():
    v, f, cam = _one_triangle()
    with pytest.raises(ValueError, match="vertices"):
        vertex_visibility(v[:, :2], f, [cam])
    with pytest.raises(ValueError, match="NaN"):
        vertex_visibility(np.where(v == 0.1, np.nan, v), f, [cam])


def test_face_index_out_of_range_raises_mesh_error():
    v, _, cam = _one_triangle()
    with pytest.raises(MeshError, match="face indices"):
        vertex_visibility(v, np.array([[0, 1, 3]]), [cam])


def test_degenerate_face_raises_mesh_error():
    v, _, cam = _one_triangle()
    with pytest.raises(MeshError, match="degenerate"):
        vertex_visibility(v, np.array([[0, 1, 1]]), [cam])


def test_bad_tolerance_raises_value_error():
    v, f, cam = _one_triangle()
    with pytest.raises(ValueError, match="rel_tol"):
        vertex_visibility(v, f, [cam], rel_tol=0.0)
    with pytest.raises(ValueError, match="min_cos"):
        vertex_visibility(v, f, [cam], min_cos=1.0)


def test_bad_corner_rule_raises_value_error():
    with pytest.raises(ValueError, match="min_visible_corners"):
        face_visibility(np.array([[0, 1, 2]]), np.ones((3, 1), dtype=bool), min_visible_corners=0)
