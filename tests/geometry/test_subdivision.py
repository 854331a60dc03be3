"""sqrt(3) subdivision without smoothing, and the projected-area stop rule."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
from pydantic import ValidationError

from pmvir.camera import Camera, look_at
from pmvir.config import GeometryOptions, PipelineConfig
from pmvir.errors import MeshError
from pmvir.geometry.mesh_ops import (
    ReferenceSurface,
    closest_points_on_triangles,
    edge_topology,
    euler_characteristic,
    face_areas,
    face_normals,
    is_closed_manifold,
)
from pmvir.geometry.subdivision import (
    densify_for_views,
    inherit_visibility,
    projected_face_areas,
    sqrt3_subdivide,
    subdivide_until,
)
from pmvir.geometry.visibility import face_visibility, vertex_visibility
from pmvir.sh import fibonacci_sphere


def _sphere(resolution: int = 6) -> tuple[np.ndarray, np.ndarray]:
    m = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution)
    return np.asarray(m.vertices, dtype=np.float64), np.asarray(m.triangles, dtype=np.int64)


def _grid(n: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """An open n x n-vertex grid in the plane z = 0, normals +z."""
    xs, ys = np.meshgrid(np.arange(n, dtype=np.float64), np.arange(n, dtype=np.float64))
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(n * n)], axis=1)
    i = np.arange(n * n).reshape(n, n)
    f = np.concatenate(
        [
            np.stack([i[:-1, :-1], i[:-1, 1:], i[1:, 1:]], -1).reshape(-1, 3),
            np.stack([i[:-1, :-1], i[1:, 1:], i[1:, :-1]], -1).reshape(-1, 3),
        ]
    )
    return v, f


def _cameras(n: int = 8, radius: float = 4.0) -> list[Camera]:
    cams = []
    for c in fibonacci_sphere(n) * radius:
        up = np.array([0.0, 0.0, 1.0]) if abs(c[2]) < 0.9 * radius else np.array([1.0, 0.0, 0.0])
        R, t = look_at(c, np.zeros(3), up=up)
        cams.append(Camera.from_intrinsics(60.0, 60.0, 40.0, 30.0, 80, 60, R, t))
    return cams


def _on_some_face(points: np.ndarray, v: np.ndarray, f: np.ndarray, tol: float = 1e-6) -> np.ndarray:
    """(P,) bool: the point lies within tol of the plane of some face, with barycentrics >= -1e-9."""
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    e1, e2 = b - a, c - a
    n = np.cross(e1, e2)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    d = points[:, None, :] - a[None]  # (P, F, 3)
    plane = np.abs(np.einsum("pfk,fk->pf", d, n))
    g11, g12, g22 = np.sum(e1 * e1, 1), np.sum(e1 * e2, 1), np.sum(e2 * e2, 1)
    r1, r2 = np.einsum("pfk,fk->pf", d, e1), np.einsum("pfk,fk->pf", d, e2)
    det = g11 * g22 - g12 * g12
    s = (g22 * r1 - g12 * r2) / det
    t = (g11 * r2 - g12 * r1) / det
    on = (plane <= tol) & (s >= -1e-9) & (t >= -1e-9) & (s + t <= 1 + 1e-9)
    return on.any(axis=1)


def test_closed_mesh_counts_topology_orientation_and_surface():
    v0, f0 = _sphere()
    chi = euler_characteristic(f0, len(v0))
    assert chi == 2 and euler_characteristic(f0, len(v0) + 5) == chi  # unused vertices do not count
    v, f = v0, f0
    for r in range(3):
        step = sqrt3_subdivide(v, f, split_boundary=r % 2 == 1)
        assert len(step.faces) == 3 * len(f)
        assert len(step.vertices) == len(v) + len(f)
        np.testing.assert_array_equal(step.vertices[: len(v)], v)  # old vertices are not relaxed
        v, f = step.vertices, step.faces
        assert is_closed_manifold(f, len(v))
        assert euler_characteristic(f, len(v)) == chi
        centroids = v[f].mean(axis=1)
        assert np.all(np.sum(face_normals(v, f) * centroids, axis=1) > 0)  # outward
        assert np.all(face_areas(v, f) > 0)
        if r == 0:  # one step: every centroid on an input face
            assert _on_some_face(v[len(v0):], v0, f0).all()


def test_subdivided_sphere_stays_on_input_surface():
    v0, f0 = _sphere(6)
    cams = _cameras(4)
    vis = np.ones((len(v0), 4), dtype=bool)
    kw = dict(max_area_px=1e-9, max_rounds=3, max_vertices=10**6)
    res = subdivide_until(v0, f0, vis, cams, **kw)
    assert res.rounds == 3
    np.testing.assert_array_equal(res.vertices[: len(v0)], v0)
    assert _on_some_face(res.vertices[len(v0):], v0, f0, tol=1e-6).all()
    assert is_closed_manifold(res.faces, len(res.vertices))
    assert euler_characteristic(res.faces, len(res.vertices)) == 2
    assert np.all(np.sum(face_normals(res.vertices, res.faces) * res.vertices[res.faces].mean(1), axis=1) > 0)
    # Without projection, centroids of triangles across flipped edges leave the surface.
    raw = subdivide_until(v0, f0, vis, cams, **kw, project=False)
    np.testing.assert_array_equal(raw.faces, res.faces)
    assert not _on_some_face(raw.vertices[len(v0):], v0, f0, tol=1e-6).all()


def test_closest_points_on_triangles_against_dense_sampling():
    rng = np.random.default_rng(3)
    a, b, c = rng.normal(size=(3, 300, 3))
    p = rng.normal(size=(300, 3)) * 2.0
    q = closest_points_on_triangles(p, a, b, c)
    s, t = np.meshgrid(np.linspace(0, 1, 101), np.linspace(0, 1, 101))
    keep = s + t <= 1 + 1e-12
    s, t = s[keep], t[keep]
    samples = a[:, None] + (b - a)[:, None] * s[None, :, None] + (c - a)[:, None] * t[None, :, None]
    sampled = np.linalg.norm(samples - p[:, None], axis=2).min(axis=1)
    got = np.linalg.norm(q - p, axis=1)
    assert np.all(got <= sampled + 1e-12)
    assert np.all(got >= sampled - 0.02 * np.linalg.norm(b - a, axis=1).clip(1))  # sampling resolution
    tri_v = np.concatenate([a[:50], b[:50], c[:50]])
    tri_f = np.stack([np.arange(50), np.arange(50) + 50, np.arange(50) + 100], 1)
    assert _on_some_face(q[:50], tri_v, tri_f, tol=1e-9).all()


def test_reference_surface_projection_lands_on_faces():
    v, f = _sphere(8)
    surface = ReferenceSurface(v, f)
    rng = np.random.default_rng(0)
    p = rng.normal(size=(200, 3))
    p /= np.linalg.norm(p, axis=1, keepdims=True)
    p *= rng.uniform(0.9, 1.1, size=(200, 1))
    q, _ = surface.project(p)
    assert _on_some_face(q, v, f, tol=1e-9).all()
    corners = (np.tile(v[f[:, k]], (len(p), 1)) for k in range(3))
    every = closest_points_on_triangles(np.repeat(p, len(f), 0), *corners).reshape(len(p), len(f), 3)
    brute = np.linalg.norm(p[:, None] - every, axis=2).min(axis=1)
    np.testing.assert_allclose(np.linalg.norm(q - p, axis=1), brute, atol=1e-5)


def test_projection_from_nearby_faces_matches_the_global_search():
    """``near``: points that moved a little off their faces, and points given a wrong face, land
    where the global search puts them."""
    v, f = _sphere(8)
    surface = ReferenceSurface(v, f)
    rng = np.random.default_rng(1)
    faces = rng.integers(0, len(f), size=300)
    w = rng.dirichlet(np.ones(3), size=300)
    on = np.einsum("nk,nkd->nd", w, v[f[faces]])
    h = np.linalg.norm(v[f[:, 0]] - v[f[:, 1]], axis=1).mean()
    moved = on + rng.normal(scale=0.02 * h, size=on.shape)
    near = faces.copy()
    centroids = v[f].mean(axis=1)
    near[:50] = [rng.choice(np.flatnonzero(centroids @ x < -0.5)) for x in on[:50]]  # wrong hints: across the sphere
    q_near, ids_near = surface.project(moved, near=near)
    q, _ = surface.project(moved)
    assert _on_some_face(q_near, v, f, tol=1e-9).all()
    np.testing.assert_allclose(q_near[:50], q[:50], atol=1e-12)  # searched as without hints
    # the nearby hints: the closest point, or one as near within a fraction of the distance (a point
    # moved inside, near an edge, may be nearer the other face's plane)
    dist_near, dist = np.linalg.norm(q_near - moved, axis=1), np.linalg.norm(q - moved, axis=1)
    assert np.all(dist_near >= dist - 1e-12)
    assert np.all(dist_near <= 1.5 * dist + 1e-12)
    assert np.mean(np.abs(q_near - q).max(axis=1) < 1e-9) > 0.95
    assert (ids_near[50:] == faces[50:]).mean() > 0.5  # most stay on their face, found without a search
    # a zero-area face (three points on a line) as the hint: the point is searched for
    flat_v = np.concatenate([v, [[0.0, 0.0, 3.0], [1.0, 0.0, 3.0], [2.0, 0.0, 3.0]]])
    flat_f = np.concatenate([f, [[len(v), len(v) + 1, len(v) + 2]]])
    point = np.array([[0.0, 0.0, 1.05]])
    q_flat, ids_flat = ReferenceSurface(flat_v, flat_f).project(point, near=np.array([len(f)]))
    np.testing.assert_allclose(q_flat, surface.project(point)[0], atol=1e-12)
    assert ids_flat[0] != len(f)


def test_new_edges_join_adjacent_centroids():
    v, f = _sphere(4)
    step = sqrt3_subdivide(v, f)
    topo = edge_topology(step.faces, len(step.vertices))
    n = len(v)
    new_new = topo.edges[(topo.edges[:, 0] >= n) & (topo.edges[:, 1] >= n)] - n  # face index pairs
    old = edge_topology(f, n)
    expected = np.sort(old.edge_faces, axis=1)
    got = np.sort(new_new, axis=1)
    assert len(got) == len(expected)  # one flipped edge per original edge
    assert set(map(tuple, got)) == set(map(tuple, expected))
    assert not np.any((topo.edges[:, 0] < n) & (topo.edges[:, 1] < n))  # every original edge flipped


def test_open_grid_boundary_two_step_rule():
    v0, f0 = _grid(4)
    boundary0 = edge_topology(f0, len(v0)).boundary.sum()
    v, f = v0, f0
    for r in range(4):
        step = sqrt3_subdivide(v, f, split_boundary=r % 2 == 1)
        v, f = step.vertices, step.faces
        topo = edge_topology(f, len(v))
        assert np.all(topo.interior | topo.boundary)  # manifold with boundary, consistently oriented
        assert np.all(face_normals(v, f)[:, 2] > 0.999999)  # orientation kept
        assert np.all(v[:, 2] == 0)
        assert euler_characteristic(f, len(v)) == 1
        np.testing.assert_allclose(face_areas(v, f).sum(), 9.0, rtol=1e-12)
        ends = v[topo.edges[topo.boundary]]
        lengths = np.linalg.norm(ends[:, 1] - ends[:, 0], axis=1)
        if r == 0:  # odd step: boundary kept
            assert topo.boundary.sum() == boundary0
            np.testing.assert_allclose(lengths, 1.0)
        if r == 1:  # even step: boundary edges cut in three
            assert topo.boundary.sum() == 3 * boundary0
            np.testing.assert_allclose(lengths, 1.0 / 3.0)
        if r == 3:
            assert topo.boundary.sum() == 9 * boundary0
            np.testing.assert_allclose(lengths, 1.0 / 9.0)


def test_non_manifold_edge_is_kept_and_mesh_stays_conforming():
    v = np.array([[0, 0, 0], [1, 0, 0], [0.5, 1, 0], [0.5, -1, 0], [0.5, 0, 1]], dtype=np.float64)
    f = np.array([[0, 1, 2], [1, 0, 3], [0, 1, 4]])  # edge 0-1 used three times
    step = sqrt3_subdivide(v, f)
    assert len(step.faces) == 9
    topo = edge_topology(step.faces, len(step.vertices))
    e01 = np.flatnonzero((topo.edges[:, 0] == 0) & (topo.edges[:, 1] == 1))
    assert len(e01) == 1 and topo.edge_face_count[e01[0]] == 3
    np.testing.assert_allclose(face_areas(step.vertices, step.faces).sum(), face_areas(v, f).sum())


def test_even_step_on_face_with_two_boundary_edges_raises_mesh_error():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float64)
    with pytest.raises(MeshError, match="at most one boundary edge"):
        sqrt3_subdivide(v, np.array([[0, 1, 2]]), split_boundary=True)


def test_degenerate_face_raises_mesh_error():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], dtype=np.float64)
    with pytest.raises(MeshError, match="degenerate"):
        sqrt3_subdivide(v, np.array([[0, 1, 1]]))


def test_inherit_visibility_rules():
    vis = np.array([[1, 1, 0], [1, 0, 0], [1, 1, 1]], dtype=bool)
    parents = np.array([[0, 1, 2], [0, 2, -1], [1, 2, -1]])
    np.testing.assert_array_equal(inherit_visibility(vis, parents), [[1, 0, 0], [1, 1, 0], [1, 0, 0]])
    np.testing.assert_array_equal(
        inherit_visibility(vis, parents, min_visible_corners=2), [[1, 1, 0], [1, 1, 0], [1, 0, 0]]
    )
    np.testing.assert_array_equal(
        inherit_visibility(vis, parents, min_visible_corners=1), [[1, 1, 1], [1, 1, 1], [1, 1, 1]]
    )


def test_projected_face_areas_known_triangle():
    v = np.array([[0.0, 0.0, 2.0], [0.1, 0.0, 2.0], [0.0, 0.1, 2.0]])
    f = np.array([[0, 2, 1]])
    near = Camera.from_intrinsics(100.0, 100.0, 10.0, 10.0, 20, 20, np.eye(3), np.zeros(3))
    far = Camera.from_intrinsics(100.0, 100.0, 10.0, 10.0, 20, 20, np.eye(3), np.array([0.0, 0.0, 2.0]))
    # legs 0.1 at depth 2 -> 5 px (area 12.5); at depth 4 -> 2.5 px (area 3.125)
    np.testing.assert_allclose(projected_face_areas(v, f, [near, far], np.array([[True, True]])), [12.5])
    np.testing.assert_allclose(projected_face_areas(v, f, [near, far], np.array([[False, True]])), [3.125])
    np.testing.assert_array_equal(projected_face_areas(v, f, [near, far], np.array([[False, False]])), [0.0])


def _visible_areas(v, f, vis, cams) -> float:
    return float(projected_face_areas(v, f, cams, face_visibility(f, vis)).max())


def test_subdivide_until_stop_rule_and_inherited_visibility():
    v, f = _sphere(5)
    cams = _cameras()
    vis = vertex_visibility(v, f, cams)
    a0 = _visible_areas(v, f, vis, cams)
    threshold = a0 / 20.0
    res = subdivide_until(v, f, vis, cams, max_area_px=threshold, max_rounds=10, max_vertices=10**6)
    assert res.converged and res.rounds >= 2
    assert res.max_area_px < threshold
    assert _visible_areas(res.vertices, res.faces, res.visibility, cams) < threshold
    assert len(res.faces) == len(f) * 3**res.rounds
    np.testing.assert_array_equal(res.visibility[: len(v)], vis)
    earlier = subdivide_until(
        v, f, vis, cams, max_area_px=threshold, max_rounds=res.rounds - 1, max_vertices=10**6
    )
    assert not earlier.converged and earlier.rounds == res.rounds - 1
    assert earlier.max_area_px >= threshold
    # inherited visibility agrees with ray casting the subdivided mesh
    recast = vertex_visibility(res.vertices, res.faces, cams)
    new = slice(len(v), None)
    inherited = res.visibility[new]
    assert inherited.sum() > 0
    assert (recast[new][inherited]).mean() > 0.98
    assert _on_some_face(res.vertices[len(v):], v, f).all()


def test_subdivide_until_already_fine_does_nothing():
    v, f = _sphere(5)
    cams = _cameras()
    vis = vertex_visibility(v, f, cams)
    res = subdivide_until(v, f, vis, cams, max_area_px=1e9, max_rounds=5, max_vertices=10**6)
    assert res.converged and res.rounds == 0 and len(res.faces) == len(f)


def test_subdivide_until_respects_max_vertices():
    v, f = _sphere(5)
    cams = _cameras()
    vis = vertex_visibility(v, f, cams)
    cap = len(v) + len(f) + 10  # room for one step, not two
    res = subdivide_until(v, f, vis, cams, max_area_px=1e-3, max_rounds=10, max_vertices=cap)
    assert res.rounds == 1 and not res.converged and len(res.vertices) <= cap


def test_subdivide_until_open_mesh_alternates_boundary_rule():
    v, f = _grid(4)
    R, t = look_at(np.array([1.5, 1.5, 6.0]), np.array([1.5, 1.5, 0.0]), up=np.array([0.0, 1.0, 0.0]))
    cams = [Camera.from_intrinsics(40.0, 40.0, 40.0, 40.0, 80, 80, R, t)]
    vis = vertex_visibility(v, f, cams)
    assert vis.all()
    res = subdivide_until(v, f, vis, cams, max_area_px=0.5, max_rounds=10, max_vertices=10**6)
    assert res.converged and res.rounds >= 3
    topo = edge_topology(res.faces, len(res.vertices))
    assert np.all(topo.interior | topo.boundary)
    np.testing.assert_allclose(face_areas(res.vertices, res.faces).sum(), 9.0, rtol=1e-12)


def test_subdivide_until_bad_threshold_raises_value_error():
    v, f = _sphere(4)
    cams = _cameras(2)
    vis = np.ones((len(v), 2), dtype=bool)
    with pytest.raises(ValueError, match="max_area_px"):
        subdivide_until(v, f, vis, cams, max_area_px=0.0, max_rounds=3, max_vertices=1000)


def test_subdivide_until_visibility_shape_mismatch_raises_value_error():
    v, f = _sphere(4)
    cams = _cameras(2)
    with pytest.raises(ValueError, match="visibility"):
        subdivide_until(
            v, f, np.ones((len(v), 3), dtype=bool), cams, max_area_px=1.0, max_rounds=3, max_vertices=1000
        )


def test_subdivide_until_negative_rounds_raises_value_error():
    v, f = _sphere(4)
    cams = _cameras(2)
    with pytest.raises(ValueError, match="max_rounds"):
        subdivide_until(
            v, f, np.ones((len(v), 2), dtype=bool), cams, max_area_px=1.0, max_rounds=-1, max_vertices=1000
        )


def test_densify_for_views_follows_geometry_options():
    v, f = _sphere(5)
    cams = _cameras()
    options = PipelineConfig.model_validate({"geometry": {"subdivision": {"max_area_px": 5.0}}}).geometry
    res = densify_for_views(v, f, cams, None, options)
    assert res.converged and res.max_area_px < 5.0 and res.rounds >= 2
    np.testing.assert_array_equal(res.visibility[: len(v)], vertex_visibility(v, f, cams))
    capped = densify_for_views(v, f, cams, None, options.model_copy(update={"subdivision": options.subdivision.model_copy(update={"max_rounds": 1})}))
    assert capped.rounds == 1 and not capped.converged


def test_geometry_options_reject_bad_values():
    with pytest.raises(ValidationError):
        GeometryOptions(subdivision={"max_area_px": 0.0})
    with pytest.raises(ValidationError):
        GeometryOptions(subdivision={"min_visible_corners": 4})
    with pytest.raises(ValidationError):
        GeometryOptions(visibility={"rel_tol": 0.0})
    with pytest.raises(ValidationError):
        GeometryOptions(unknown_field=1)


def test_edge_topology_of_tetrahedron_and_inconsistent_orientation():
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=np.float64)
    f = np.array([[0, 2, 1], [0, 1, 3], [1, 2, 3], [0, 3, 2]])  # outward
    assert np.linalg.det(v[f]).sum() > 0  # six times the signed volume: outward faces
    topo = edge_topology(f, 4)
    assert topo.n_edges == 6 and topo.interior.all() and not topo.boundary.any()
    assert np.all(topo.edges[:, 0] < topo.edges[:, 1])
    for e, (a, b) in enumerate(topo.edges):  # edge_faces[e, 0] holds a -> b
        row = f[topo.edge_faces[e, 0]]
        k = int(np.flatnonzero(row == a)[0])
        assert row[(k + 1) % 3] == b
    np.testing.assert_array_equal(np.sort(topo.face_edges.ravel()), np.repeat(np.arange(6), 2))
    assert euler_characteristic(f, 4) == 2
    flipped = f.copy()
    flipped[0] = flipped[0, ::-1]
    assert not edge_topology(flipped, 4).interior[edge_topology(flipped, 4).face_edges[0]].any()
    assert not is_closed_manifold(flipped, 4)
    open_tet = edge_topology(f[:3], 4)
    assert open_tet.boundary.sum() == 3 and open_tet.interior.sum() == 3
