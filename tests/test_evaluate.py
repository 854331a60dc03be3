"""Metrics of pmvir.evaluate against cases with a known answer (spec section 5)."""

from __future__ import annotations

import inspect
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial.transform import Rotation

from pmvir import cli
from pmvir.camera import look_at
from pmvir.errors import ConfigError, ManifestError, MeshError, PmvirError
from pmvir.evaluate import (
    N_GT_SAMPLES,
    EvaluationResult,
    albedo_scale_rmse,
    bbox_diagonal,
    evaluate,
    evaluate_paths,
    normal_angles,
    refine_alignment,
    sample_surface,
    shading_error,
)
from pmvir.geometry.sfm.align import CameraAlignment, Similarity
from pmvir.io.colmap_text import ColmapCamera, ColmapImage, qvec_from_rotmat, write_colmap_text_model
from pmvir.io.illumination import illumination_from_arrays, write_illumination
from pmvir.io.ply import Mesh, write_mesh_ply
from pmvir.sh import fibonacci_sphere, project_to_sh9, sh9_shading

SAMPLES = 100_000  # enough for these checks; the default (>= 1e6) is checked separately


def icosphere(radius: float, subdivisions: int) -> Mesh:
    """Icosahedron subdivided ``subdivisions`` times, every vertex pushed onto the sphere."""
    m = o3d.geometry.TriangleMesh.create_icosahedron(1.0).subdivide_midpoint(subdivisions)
    v = np.asarray(m.vertices)
    v = radius * v / np.linalg.norm(v, axis=1, keepdims=True)
    return Mesh(v, np.asarray(m.triangles))


def smooth_albedo(v: np.ndarray) -> np.ndarray:
    """A smooth, positive, per-channel different albedo field of position."""
    u = v / np.abs(v).max()
    return np.stack([0.5 + 0.3 * u[:, 0], 0.4 + 0.2 * u[:, 1] * u[:, 2], 0.6 - 0.25 * u[:, 2]], 1).astype(
        np.float32
    )


def with_albedo(mesh: Mesh, albedo: np.ndarray) -> Mesh:
    return Mesh(mesh.vertices, mesh.faces, albedo=albedo)


def triangle_circumradii(mesh: Mesh) -> np.ndarray:
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    la, lb, lc = np.linalg.norm(b - c, axis=1), np.linalg.norm(c - a, axis=1), np.linalg.norm(a - b, axis=1)
    area = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    return la * lb * lc / (4 * area)


def inradius_about_origin(mesh: Mesh) -> float:
    """Distance from the origin to a convex mesh containing it: the smallest face-plane distance."""
    a, b, c = (mesh.vertices[mesh.faces[:, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    return float(np.min(np.abs((n * a).sum(1)) / np.linalg.norm(n, axis=1)))


def max_edge_angle(mesh: Mesh) -> float:
    """Largest angle subtended at the origin by an edge."""
    v = mesh.vertices / np.linalg.norm(mesh.vertices, axis=1, keepdims=True)
    cosines = [(v[mesh.faces[:, i]] * v[mesh.faces[:, j]]).sum(1) for i, j in ((0, 1), (1, 2), (2, 0))]
    return float(np.arccos(np.clip(np.min(cosines), -1, 1)))


@pytest.fixture(scope="module")
def gt() -> Mesh:
    m = icosphere(1.0, 4)
    return with_albedo(m, smooth_albedo(m.vertices))


def lighting(files: list[str], seed: int):
    rng = np.random.default_rng(seed)
    sh = np.concatenate([np.full((len(files), 1), 1.0), 0.3 * rng.standard_normal((len(files), 8))], axis=1)
    return illumination_from_arrays(files, sh, rng.uniform(0.5, 1.5, (len(files), 3)))


# --- defaults ------------------------------------------------------------------------------------


def test_default_gt_sample_count_is_at_least_one_million():
    assert N_GT_SAMPLES >= 1_000_000
    assert inspect.signature(evaluate).parameters["n_samples"].default >= 1_000_000
    assert inspect.signature(evaluate_paths).parameters["n_samples"].default >= 1_000_000
    args = cli.build_parser().parse_args(["evaluate", "x", "--gt", "y"])
    assert args.samples >= 1_000_000 and not args.align


# --- sampling ------------------------------------------------------------------------------------


def test_sample_surface_is_uniform_by_area():
    # Two triangles, areas 1/2 and 2 (ratio 1:4), far apart.
    v = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [10, 0, 0], [12, 0, 0], [10, 2, 0]], float)
    f = np.array([[0, 1, 2], [3, 4, 5]])
    pts, fid, bary = sample_surface(v, f, 200_000, seed=3)
    assert abs(np.mean(fid == 1) - 0.8) < 0.005
    np.testing.assert_allclose(bary.sum(1), 1.0, atol=1e-12)
    assert (bary >= 0).all()
    np.testing.assert_allclose(pts, np.einsum("nk,nkc->nc", bary, v[f[fid]]), atol=1e-12)
    # Uniform inside a triangle: the mean is the centroid, and 1/4 of points fall in the corner
    # sub-triangle (vertices, edge midpoints) at vertex 0.
    first = pts[fid == 0]
    np.testing.assert_allclose(first.mean(0), [1 / 3, 1 / 3, 0], atol=0.005)
    assert abs(np.mean(first[:, 0] + first[:, 1] < 0.5) - 0.25) < 0.01
    same, _, _ = sample_surface(v, f, 1000, seed=3)
    np.testing.assert_array_equal(same, sample_surface(v, f, 1000, seed=3)[0])


# --- mesh against itself -------------------------------------------------------------------------


def test_mesh_against_itself_is_zero(gt):
    illum = lighting(["frames/000.png", "frames/001.png"], seed=1)
    r = evaluate(gt, gt, est_illum=illum, gt_illum=illum, n_samples=SAMPLES)
    assert isinstance(r, EvaluationResult)
    assert r.accuracy < 1e-6 and r.accuracy_p90 < 1e-6
    assert r.albedo_rmse < 1e-5
    np.testing.assert_allclose(r.albedo_scale, 1.0, atol=1e-4)
    assert r.illumination_error < 1e-4
    assert set(r.illumination_per_frame) == {"frames/000.png", "frames/001.png"}
    assert r.n_vertices == len(gt.vertices) and r.n_gt_samples == SAMPLES and not r.aligned


def test_completeness_of_a_mesh_against_itself_is_bounded_by_its_triangles(gt):
    """Completeness measures distance to the nearest estimated VERTEX, not surface, so a mesh
    against itself scores > 0; every point of a triangle lies within the triangle's circumradius
    of one of its vertices, so the bound is max circumradius / diagonal, which tends to 0 as the
    mesh gets denser."""
    diag = bbox_diagonal(gt.vertices)
    coarse = icosphere(1.0, 2)
    r_fine = evaluate(gt, gt, n_samples=SAMPLES)
    r_coarse = evaluate(coarse, coarse, n_samples=SAMPLES)
    for mesh, r in ((gt, r_fine), (coarse, r_coarse)):
        bound = triangle_circumradii(mesh).max() / diag
        assert 0 < r.completeness < bound
        assert r.completeness_p90 <= bound and r.completeness_median <= r.completeness_p90
    # Four times the triangles (twice per subdivision), a quarter of the edge length.
    assert r_fine.completeness < 0.3 * r_coarse.completeness


# --- concentric spheres --------------------------------------------------------------------------


def test_sphere_offset_same_tessellation_gives_exact_accuracy():
    """Vertices of the r + d sphere lie radially above those of the r sphere; the closest point of
    an inscribed convex polyhedron to such a point is that vertex, at distance d exactly."""
    r, d = 1.0, 0.07
    gt_mesh, est = icosphere(r, 3), icosphere(r + d, 3)
    res = evaluate(est, gt_mesh, n_samples=SAMPLES)
    diag = bbox_diagonal(gt_mesh.vertices)
    np.testing.assert_allclose([res.accuracy, res.accuracy_median, res.accuracy_p90], d / diag, rtol=1e-5)
    assert res.albedo_rmse is None and res.illumination_error is None
    np.testing.assert_allclose([res.signed_offset, res.signed_offset_median], d / diag, rtol=1e-5)


def test_signed_offset_tells_a_shrunk_surface_from_a_swollen_one():
    """A sphere inside the true one has a negative signed offset, one outside a positive one, equal
    in size to the accuracy (every vertex on one side); turning the true faces' winding over turns
    the sign (it follows the winding). A surface that is noisy about the truth has |signed| far
    below its accuracy."""
    gt_mesh = icosphere(1.0, 3)
    diag = bbox_diagonal(gt_mesh.vertices)
    inner = evaluate(icosphere(0.95, 3), gt_mesh, n_samples=SAMPLES)
    outer = evaluate(icosphere(1.05, 3), gt_mesh, n_samples=SAMPLES)
    # inner vertices are nearest to a face (inside the inradius), outer ones to a vertex: 1 %
    np.testing.assert_allclose(inner.signed_offset, -0.05 / diag, rtol=1e-2)
    np.testing.assert_allclose(outer.signed_offset, 0.05 / diag, rtol=1e-4)
    np.testing.assert_allclose(
        [-inner.signed_offset, outer.signed_offset], [inner.accuracy, outer.accuracy], rtol=1e-6
    )
    flipped = Mesh(gt_mesh.vertices, gt_mesh.faces[:, ::-1].copy())
    flipped_inner = evaluate(icosphere(0.95, 3), flipped, n_samples=SAMPLES)
    np.testing.assert_allclose(flipped_inner.signed_offset, -inner.signed_offset, rtol=1e-6)
    v = icosphere(1.0, 3).vertices
    radial = 1.0 + 0.05 * np.where(np.arange(len(v)) % 2 == 0, 1.0, -1.0)
    noisy = evaluate(Mesh(v * radial[:, None], icosphere(1.0, 3).faces), gt_mesh, n_samples=SAMPLES)
    assert noisy.accuracy > 0.04 / diag and abs(noisy.signed_offset) < 0.2 * noisy.accuracy


# --- normal error --------------------------------------------------------------------------------


def grid(n: int, height) -> Mesh:
    """An n x n vertex grid over [-1, 1]^2 at z = height(x, y), faces counter-clockwise seen from +z."""
    x, y = np.meshgrid(np.linspace(-1, 1, n), np.linspace(-1, 1, n))
    v = np.stack([x.ravel(), y.ravel(), height(x, y).ravel()], axis=1)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[:-1, 1:].ravel(), i[1:, 1:].ravel(), i[1:, :-1].ravel()
    return Mesh(v, np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]))


def test_normal_error_of_a_sphere_against_itself_is_near_zero():
    """Each vertex's closest point is the vertex itself, on one of its own faces: the angle is at
    most the spread of the faces about the vertex normal, which shrinks with the tessellation."""
    coarse, fine = icosphere(1.0, 3), icosphere(1.0, 5)
    r_coarse = evaluate(coarse, coarse, n_samples=1000)
    r_fine = evaluate(fine, fine, n_samples=1000)
    assert r_fine.normal_error < np.degrees(max_edge_angle(fine)) < 2.5
    assert r_fine.normal_error_median <= r_fine.normal_error * 1.5
    assert r_fine.normal_error < 0.3 * r_coarse.normal_error
    assert "normal_error" not in " ".join(r_fine.notes)


def test_normal_error_of_tilted_patches_is_their_known_tilt():
    """Two flat patches above a flat truth, tilted by 10 and 30 degrees (equal vertex counts):
    every vertex normal is its patch's normal and every closest face's normal is +z."""
    truth = grid(5, lambda x, y: 0 * x)
    truth = Mesh(4 * truth.vertices, truth.faces)
    a = grid(9, lambda x, y: 0.5 + np.tan(np.radians(10)) * x)
    b = grid(9, lambda x, y: 1.0 + np.tan(np.radians(30)) * y)
    both = Mesh(np.concatenate([a.vertices, b.vertices]), np.concatenate([a.faces, b.faces + 81]))
    np.testing.assert_allclose(normal_angles(a.vertices, a.faces, truth.vertices, truth.faces[[0] * 81]), 10)
    r = evaluate(both, truth, n_samples=1000)
    np.testing.assert_allclose(r.normal_error, 20.0, atol=1e-4)
    assert 10 - 1e-4 <= r.normal_error_median <= 30 + 1e-4


def test_normal_error_of_a_flipped_result_is_near_180(gt):
    """Turning every normal over turns each angle a into 180 - a (the closest faces are the same)."""
    flipped = Mesh(gt.vertices, gt.faces[:, ::-1])
    r, r_self = evaluate(flipped, gt, n_samples=1000), evaluate(gt, gt, n_samples=1000)
    assert r.normal_error > 180 - np.degrees(max_edge_angle(gt))
    assert r.normal_error == pytest.approx(180 - r_self.normal_error, abs=1e-6)
    assert r.normal_error_median == pytest.approx(180 - r_self.normal_error_median, abs=1e-6)


def test_normal_error_leaves_out_vertices_without_a_face(gt):
    """A stray vertex has no normal: it counts for accuracy but not for the normal error."""
    stray = Mesh(np.concatenate([gt.vertices, [[0.0, 0.0, 1.5]]]), gt.faces)
    r, r_gt = evaluate(stray, gt, n_samples=1000), evaluate(gt, gt, n_samples=1000)
    assert r.normal_error == pytest.approx(r_gt.normal_error)
    assert any(n.startswith("normal_error: 1 ") for n in r.notes)
    assert r.accuracy > r_gt.accuracy


def test_sphere_offset_bounds_from_tessellation():
    """GT: icosphere of radius r. Estimate: a UV sphere (another tessellation) of radius R = r + d.
    The GT polyhedron lies between its inradius r_in and r, so every estimated vertex is between
    d and R - r_in from it (accuracy). A GT sample p (|p| in [r_in, r]) is within the angle
    theta_max (largest edge angle of the estimate) of an estimated vertex v (|v| = R), hence
    d <= |p - v| <= sqrt((R - r_in)^2 + 2 r R (1 - cos theta_max)) (completeness)."""
    r, d = 1.0, 0.2
    R = r + d
    gt_mesh = icosphere(r, 4)
    s = o3d.geometry.TriangleMesh.create_sphere(radius=R, resolution=60)
    est = Mesh(np.asarray(s.vertices), np.asarray(s.triangles))
    res = evaluate(est, gt_mesh, n_samples=SAMPLES)
    diag = bbox_diagonal(gt_mesh.vertices)
    r_in = inradius_about_origin(gt_mesh)
    assert 0 < r - r_in < 2e-3  # the tolerance comes from the tessellation and is small
    tol32 = 1e-6  # float32 inside Open3D
    assert d / diag - tol32 <= res.accuracy <= (R - r_in) / diag + tol32
    theta = max_edge_angle(est)
    upper = np.sqrt((R - r_in) ** 2 + 2 * r * R * (1 - np.cos(theta)))
    assert d / diag - tol32 <= res.completeness <= upper / diag + tol32
    assert res.completeness_p90 <= upper / diag + tol32
    # The bounds are tight: both within 10 % of d.
    assert upper / d < 1.1 and (R - r_in) / d < 1.01


# --- albedo --------------------------------------------------------------------------------------


def test_albedo_is_interpolated_barycentrically(gt):
    """Midpoint subdivision puts new vertices on GT edges; their true albedo is the mean of the
    edge's end albedos, which Open3D's subdivision gives them as colours."""
    m = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(gt.vertices), o3d.utility.Vector3iVector(gt.faces)
    )
    m.vertex_colors = o3d.utility.Vector3dVector(gt.albedo.astype(np.float64))
    fine = m.subdivide_midpoint(1)
    est = Mesh(np.asarray(fine.vertices), np.asarray(fine.triangles), albedo=np.asarray(fine.vertex_colors))
    assert len(est.vertices) > 3 * len(gt.vertices)
    r = evaluate(est, gt, n_samples=10_000)
    assert r.albedo_rmse < 1e-5
    # Nearest-vertex lookup instead of interpolation would be far off: the field varies by ~0.02
    # along an edge of this mesh.
    per_edge = np.abs(gt.albedo[gt.faces[:, 0]] - gt.albedo[gt.faces[:, 1]]).mean()
    assert per_edge > 100 * r.albedo_rmse


def test_albedo_rmse_invariant_to_a_per_channel_scale(gt):
    s = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=30)
    v = np.asarray(s.vertices)
    noisy = smooth_albedo(v) + np.random.default_rng(0).normal(0, 0.03, (len(v), 3)).astype(np.float32)
    base = evaluate(Mesh(v, np.asarray(s.triangles), albedo=noisy), gt, n_samples=10_000)
    k = np.array([2.0, 0.5, 3.0], np.float32)
    scaled = evaluate(Mesh(v, np.asarray(s.triangles), albedo=noisy * k), gt, n_samples=10_000)
    assert 0.02 < base.albedo_rmse < 0.04  # the noise level (plus tessellation)
    assert scaled.albedo_rmse == pytest.approx(base.albedo_rmse, rel=1e-5)
    np.testing.assert_allclose(np.array(scaled.albedo_scale) * k, base.albedo_scale, rtol=1e-5)


def test_albedo_scale_rmse_hand_computed():
    est = np.array([[1.0, 1.0, 0.0], [2.0, 1.0, 0.0]])
    true = np.array([[1.0, 2.0, 0.3], [2.0, 4.0, 0.3]])
    scale, rmse = albedo_scale_rmse(est, true)
    # R: exact with scale 1. G: s = (2 + 4) / 2 = 3, residuals (1, -1). B: estimate all zero -> scale 0.
    np.testing.assert_allclose(scale, [1.0, 3.0, 0.0])
    assert rmse == pytest.approx(np.sqrt((0 + 0 + 1 + 1 + 0.09 + 0.09) / 6))


# --- illumination --------------------------------------------------------------------------------


def test_illumination_error_hand_computed_values():
    one = np.array([1.0, 0, 0, 0, 0, 0, 0, 0, 0])
    white = np.ones(3)
    # Constant shading 1 vs 1.2: error 0.2 everywhere, true RMS 1.
    assert shading_error(one * 1.2, white, one, white, np.ones(3)) == pytest.approx(0.2, rel=1e-12)
    # Adding a * Nx: RMS of Nx over the sphere is 1/sqrt(3) (Fibonacci directions: to ~1e-4).
    a = 0.4
    tilted = one.copy()
    tilted[3] = a
    assert shading_error(tilted, white, one, white, np.ones(3)) == pytest.approx(a / np.sqrt(3), rel=1e-3)
    # The estimated shading is divided by the albedo scale: albedo / 2 needs shading * 2.
    assert shading_error(one * 2.4, white, one, white, np.full(3, 2.0)) == pytest.approx(0.2, rel=1e-12)


def test_illumination_error_invariant_to_albedo_rgb_scale_ambiguity(gt):
    gt_illum = lighting(["frames/000.png", "frames/001.png"], seed=2)
    k = np.array([0.5, 2.0, 1.5])
    est = with_albedo(gt, gt.albedo / k.astype(np.float32))
    est_illum = illumination_from_arrays(
        ["frames/000.png", "frames/001.png"], gt_illum.sh_array(), gt_illum.scale_array() * k
    )
    r = evaluate(est, gt, est_illum=est_illum, gt_illum=gt_illum, n_samples=10_000)
    assert r.albedo_rmse < 1e-5
    assert r.illumination_error < 1e-5


def test_illumination_error_of_wrong_lighting_matches_hand_value(gt):
    """Truth: constant shading 1 (white); estimate: 1 + 0.3 Nx in frame 000 and 1.2 in frame 001,
    named by basename only and listed in the other order. Same albedo, so the scale is 1 and the
    errors are 0.3/sqrt(3) (the RMS of Nx on the sphere is 1/sqrt(3)) and 0.2."""
    gt_illum = illumination_from_arrays(
        ["frames/000.png", "frames/001.png"], np.eye(9)[[0, 0]], np.ones((2, 3))
    )
    est_sh = np.eye(9)[[0, 0]].copy()
    est_sh[0, 0] = 1.2  # frame 001
    est_sh[1, 3] = 0.3  # frame 000
    est_illum = illumination_from_arrays(["001.png", "000.png"], est_sh, np.ones((2, 3)))
    r = evaluate(gt, gt, est_illum=est_illum, gt_illum=gt_illum, n_samples=10_000)
    assert r.illumination_per_frame["frames/000.png"] == pytest.approx(0.3 / np.sqrt(3), rel=1e-3)
    assert r.illumination_per_frame["frames/001.png"] == pytest.approx(0.2, rel=1e-4)
    assert r.illumination_error == pytest.approx((0.3 / np.sqrt(3) + 0.2) / 2, rel=1e-3)


def test_illumination_needs_gt_sh_and_albedo(gt):
    illum = lighting(["frames/000.png"], seed=3)
    r = evaluate(gt, gt, est_illum=illum, gt_illum=None, n_samples=1000)
    assert r.illumination_error is None and any("ground-truth SH" in n for n in r.notes)
    bare = Mesh(gt.vertices, gt.faces)
    r = evaluate(bare, gt, est_illum=illum, gt_illum=illum, n_samples=1000)
    assert r.albedo_rmse is None and r.illumination_error is None
    unmatched = illumination_from_arrays(["frames/zzz.png"], illum.sh_array(), illum.scale_array())
    r = evaluate(gt, gt, est_illum=unmatched, gt_illum=illum, n_samples=1000)
    assert r.illumination_error is None and any("without an estimate" in n for n in r.notes)


# --- files, --align and the CLI ------------------------------------------------------------------


TRUE_FROM_EST = Similarity(
    2.5, Rotation.from_euler("xyz", [30, -50, 110], degrees=True).as_matrix(), np.array([0.3, -1.2, 4.0])
)


def make_capture_and_result(tmp: Path, gt_mesh: Mesh) -> tuple[Path, Path]:
    """A capture with gt/ and true poses, and a result expressed in a frame TRUE_FROM_EST^-1 of it."""
    capture, result = tmp / "capture", tmp / "result"
    (capture / "gt").mkdir(parents=True)
    (result / "poses").mkdir(parents=True)
    write_mesh_ply(capture / "gt" / "mesh.ply", gt_mesh)
    files = [f"frames/{i:03d}.png" for i in range(6)]
    gt_illum = lighting(files, seed=4)
    write_illumination(capture / "gt" / "illumination.json", gt_illum)
    frames, images = [], []
    est_from_true = TRUE_FROM_EST.inverse()
    Rs = TRUE_FROM_EST.R
    for i, f in enumerate(files):
        ang = 2 * np.pi * i / len(files)
        centre = np.array([4 * np.cos(ang), 4 * np.sin(ang), 1.5 * np.sin(2 * ang)])
        R, t = look_at(centre, np.zeros(3))
        frames.append({"file": f, "cam_from_world": {"R": R.tolist(), "t": t.tolist()}})
        R_est = R @ Rs
        c_est = est_from_true.apply(centre[None])[0]
        images.append(ColmapImage(i + 1, qvec_from_rotmat(R_est), -R_est @ c_est, 1, Path(f).name))
    (capture / "capture.json").write_text(json.dumps({"format": "pmvir-capture/1", "frames": frames}))
    write_colmap_text_model(result / "poses", [ColmapCamera(1, "PINHOLE", 64, 48, (50, 50, 32, 24))], images)
    est_mesh = Mesh(est_from_true.apply(gt_mesh.vertices), gt_mesh.faces, albedo=gt_mesh.albedo * 0.7)
    write_mesh_ply(result / "mesh.ply", est_mesh)
    # S_est(d) = S_true(R d): project that rotated degree-2 function back onto the basis (exact).
    dirs = fibonacci_sphere(500)
    est_sh = np.stack([project_to_sh9(dirs, sh9_shading(dirs @ Rs.T, sh)) for sh in gt_illum.sh_array()])
    write_illumination(
        result / "illumination.json", illumination_from_arrays(files, est_sh, gt_illum.scale_array() / 0.7)
    )
    return capture, result


@pytest.fixture(scope="module")
def capture_and_result(tmp_path_factory, gt):
    return make_capture_and_result(tmp_path_factory.mktemp("eval"), gt)


def test_align_recovers_metrics_of_a_transformed_result(capture_and_result):
    capture, result = capture_and_result
    r = evaluate_paths(result, capture / "gt", align=True, n_samples=SAMPLES)
    assert r.aligned and r.alignment_rmse < 1e-6
    assert r.alignment["scale"] == pytest.approx(TRUE_FROM_EST.scale, rel=1e-6)
    np.testing.assert_allclose(r.alignment["R"], TRUE_FROM_EST.R, atol=1e-6)
    assert r.accuracy < 1e-5  # float32 PLY coordinates
    assert r.albedo_rmse < 1e-5
    np.testing.assert_allclose(r.albedo_scale, 1 / 0.7, rtol=1e-4)
    assert r.illumination_error < 1e-5 and len(r.illumination_per_frame) == 6
    unaligned = evaluate_paths(result, capture / "gt", align=False, n_samples=10_000)
    assert not unaligned.aligned and unaligned.accuracy > 0.1 and unaligned.illumination_error > 0.05


def test_icp_removes_the_camera_fits_error_but_not_a_shape_error():
    """A camera fit off by 0.5 deg, 0.3 % in scale and 0.5 % of the diagonal in position: ICP on the
    true surface takes the estimate back; a bump in the estimate stays measured."""
    sphere = icosphere(1.0, 4)
    truth = Mesh(sphere.vertices * np.array([1.0, 0.7, 0.5]), sphere.faces)  # no rotational symmetry
    off = Similarity(1.003, Rotation.from_euler("xyz", [0.3, -0.2, 0.3], degrees=True).as_matrix(),
                     np.array([0.004, -0.002, 0.003]))
    camera_fit = CameraAlignment(off, rmse=0.0, pairs=[])
    before = evaluate(truth, truth, n_samples=SAMPLES, alignment=camera_fit)
    refined = refine_alignment(camera_fit, truth.vertices, truth)
    after = evaluate(truth, truth, n_samples=SAMPLES, alignment=refined)
    assert before.accuracy > 1e-3 and after.accuracy < 0.05 * before.accuracy
    moved = np.linalg.norm(off.apply(truth.vertices) - truth.vertices, axis=1).max()
    assert refined.surface_shift == pytest.approx(moved, rel=0.1)
    assert after.alignment_refine_shift == pytest.approx(moved / before.gt_diagonal, rel=0.1)

    bumped = truth.vertices.copy()
    cap = bumped[:, 0] > 0.8
    bumped[cap] *= 1.03  # 3 % outward over the cap
    exact = CameraAlignment(Similarity(1.0, np.eye(3), np.zeros(3)), rmse=0.0, pairs=[])
    shape_error = evaluate(Mesh(bumped, truth.faces), truth, n_samples=SAMPLES, alignment=exact).accuracy
    fitted = refine_alignment(exact, bumped, truth)
    assert evaluate(Mesh(bumped, truth.faces), truth, n_samples=SAMPLES, alignment=fitted).accuracy > 0.7 * shape_error


def test_icp_needs_the_camera_alignment(capture_and_result):
    capture, result = capture_and_result
    with pytest.raises(ConfigError, match="--align"):
        evaluate_paths(result, capture / "gt", icp=True, n_samples=10_000)
    r = evaluate_paths(result, capture / "gt", align=True, icp=True, n_samples=SAMPLES)
    # the camera fit was exact already: ICP on the sphere's surface samples keeps the accuracy (it may
    # turn the sphere a little about its centre, which costs nothing)
    assert r.accuracy < 1e-4 and r.alignment_refine_shift < 2e-3
    assert r.to_dict()["alignment_refine_shift"] == r.alignment_refine_shift


def test_cli_prints_json_on_stdout_and_table_on_stderr(capture_and_result, tmp_path, capsys):
    capture, result = capture_and_result
    out = tmp_path / "sub" / "metrics.json"
    rc = cli.main(
        [
            "evaluate",
            str(result),
            "--gt",
            str(capture / "gt"),
            "--align",
            "--samples",
            "20000",
            "--seed",
            "1",
            "--out",
            str(out),
        ]
    )
    captured = capsys.readouterr()
    assert rc == 0
    doc = json.loads(captured.out)
    for key in (
        "accuracy",
        "completeness",
        "albedo_rmse",
        "illumination_error",
        "accuracy_median",
        "accuracy_p90",
        "completeness_median",
        "completeness_p90",
        "signed_offset",
        "signed_offset_median",
        "normal_error",
        "normal_error_median",
        "n_vertices",
        "n_gt_samples",
        "aligned",
        "alignment_rmse",
    ):
        assert key in doc, key
    assert doc["aligned"] is True and doc["n_gt_samples"] == 20000 and doc["accuracy"] < 1e-5
    assert json.loads(out.read_text()) == doc
    assert "accuracy (mean / median / p90)" in captured.err and "{" not in captured.err
    assert "signed offset (mean / median; < 0: inside)" in captured.err
    assert "normal error, degrees (mean / median)" in captured.err and doc["normal_error"] < 5


def test_cli_bare_mesh_in_a_subprocess(capture_and_result):
    capture, _ = capture_and_result
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "pmvir.cli",
            "evaluate",
            str(capture / "gt" / "mesh.ply"),
            "--gt",
            str(capture / "gt"),
            "--samples",
            "5000",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert proc.returncode == 0, proc.stderr
    doc = json.loads(proc.stdout)
    assert doc["accuracy"] < 1e-6 and doc["aligned"] is False and "alignment_rmse" not in doc
    assert doc["illumination_error"] is None  # a bare mesh has no lighting
    assert "illumination_error: no estimated SH illumination" in proc.stderr


# --- bad inputs ----------------------------------------------------------------------------------


def test_missing_gt_mesh_raises_mesh_error(capture_and_result, tmp_path):
    _, result = capture_and_result
    (tmp_path / "gt").mkdir()
    with pytest.raises(MeshError, match="no ground-truth mesh"):
        evaluate_paths(result, tmp_path / "gt", n_samples=100)


def test_missing_gt_mesh_gives_exit_2_and_one_line(capture_and_result, tmp_path, capsys):
    _, result = capture_and_result
    (tmp_path / "gt").mkdir()
    assert cli.main(["evaluate", str(result), "--gt", str(tmp_path / "gt"), "--samples", "100"]) == 2
    captured = capsys.readouterr()
    assert captured.out == "" and "no ground-truth mesh" in captured.err and captured.err.count("\n") == 1


def test_missing_gt_folder_raises(capture_and_result, tmp_path):
    _, result = capture_and_result
    with pytest.raises(PmvirError, match="no such ground-truth folder"):
        evaluate_paths(result, tmp_path / "nowhere", n_samples=100)


def test_missing_estimate_raises(capture_and_result, tmp_path):
    capture, _ = capture_and_result
    with pytest.raises(PmvirError, match="no such result folder or mesh file"):
        evaluate_paths(tmp_path / "nothing", capture / "gt", n_samples=100)


def test_estimate_without_faces_raises_mesh_error(gt):
    with pytest.raises(MeshError, match="estimated mesh has no faces"):
        evaluate(Mesh(gt.vertices, np.zeros((0, 3), int)), gt, n_samples=100)


def test_estimate_file_without_faces_raises_mesh_error(capture_and_result, tmp_path):
    from plyfile import PlyData, PlyElement

    capture, _ = capture_and_result
    vert = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    face = np.zeros(0, dtype=[("vertex_indices", "O")])
    PlyData([PlyElement.describe(vert, "vertex"), PlyElement.describe(face, "face")]).write(
        str(tmp_path / "e.ply")
    )
    with pytest.raises(MeshError, match="no faces"):
        evaluate_paths(tmp_path / "e.ply", capture / "gt", n_samples=100)


def test_gt_without_faces_raises_mesh_error(gt):
    with pytest.raises(MeshError, match="ground-truth mesh has no faces"):
        evaluate(gt, Mesh(gt.vertices, np.zeros((0, 3), int)), n_samples=100)


def test_non_finite_estimate_raises_mesh_error(gt):
    v = gt.vertices.copy()
    v[5, 1] = np.nan
    with pytest.raises(MeshError, match="NaN"):
        evaluate(Mesh(v, gt.faces), gt, n_samples=100)


def test_zero_area_gt_raises_mesh_error(gt):
    flat = Mesh(np.array([[0, 0, 0], [1, 0, 0], [2, 0, 0]], float), np.array([[0, 1, 2]]))
    with pytest.raises(MeshError, match="zero surface area"):
        evaluate(gt, flat, n_samples=100)


def test_zero_samples_raise_config_error(gt):
    with pytest.raises(ConfigError, match="at least one surface sample"):
        evaluate(gt, gt, n_samples=0)


def test_align_with_a_bare_mesh_raises_config_error(capture_and_result):
    capture, _ = capture_and_result
    with pytest.raises(ConfigError, match="--align needs a result folder"):
        evaluate_paths(capture / "gt" / "mesh.ply", capture / "gt", align=True, n_samples=100)


def test_align_without_capture_json_raises_manifest_error(capture_and_result, tmp_path):
    capture, result = capture_and_result
    (tmp_path / "gt").mkdir()
    (tmp_path / "gt" / "mesh.ply").write_bytes((capture / "gt" / "mesh.ply").read_bytes())
    with pytest.raises(ManifestError, match=r"capture\.json"):
        evaluate_paths(result, tmp_path / "gt", align=True, n_samples=100)
