"""Built-in shapes, normalization, procedural albedo, camera rings and lighting of synthetic captures."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest

from pmvir.io.ply import Mesh
from pmvir.sh import fibonacci_sphere, sh9_basis
from pmvir.synth.lighting import env_lights, environment_map, irradiance_shading, sh_lights
from pmvir.synth.relief import RELIEF_SHAPES
from pmvir.synth.rig import ring_cameras
from pmvir.synth.shapes import SHAPES, builtin_shape, geodesic_sphere, normalize_mesh
from pmvir.synth.texture import procedural_albedo


def _closed_and_oriented(faces: np.ndarray) -> bool:
    """Every directed edge appears once and its reverse once: closed, manifold, consistently oriented."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    directed = {tuple(x) for x in e.tolist()}
    return len(directed) == len(e) and all((b, a) in directed for a, b in directed)


@pytest.mark.parametrize("name", SHAPES)
def test_builtin_shapes_are_closed_normalized_and_detailed(name: str) -> None:
    m = builtin_shape(name)
    assert _closed_and_oriented(m.faces)
    tm = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(m.vertices), o3d.utility.Vector3iVector(m.faces)
    )
    assert tm.is_vertex_manifold()
    assert 20_000 <= len(m.faces) <= (200_000 if name in RELIEF_SHAPES else 60_000)
    lo, hi = m.vertices.min(0), m.vertices.max(0)
    assert np.linalg.norm(hi - lo) == pytest.approx(1.0, abs=1e-9)
    np.testing.assert_allclose((lo + hi) / 2, 0.0, atol=1e-9)
    v0, v1, v2 = (m.vertices[m.faces[:, k]] for k in range(3))
    assert np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() > 0  # outward: positive signed volume
    np.testing.assert_allclose(np.linalg.norm(m.normals, axis=1), 1.0, atol=1e-5)


def test_shapes_have_the_promised_relief() -> None:
    def radial_spread(name: str) -> float:
        v = builtin_shape(name).vertices
        r = np.linalg.norm(v, axis=1)
        return float(r.std() / r.mean())

    assert radial_spread("sphere") < 1e-6
    assert radial_spread("blob") > 0.03
    # Concavities: points of the dented shape far inside its convex hull.
    v = builtin_shape("dented").vertices
    hull = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(v)).compute_convex_hull()[0]
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(hull))
    depth = scene.compute_distance(o3d.core.Tensor(v.astype(np.float32))).numpy()
    assert depth.max() > 0.05  # dents deeper than 5 % of the bounding-box diagonal


def test_geodesic_sphere_counts() -> None:
    v, f = geodesic_sphere(3)
    assert len(f) == 20 * 9 and len(v) == 10 * 9 + 2
    np.testing.assert_allclose(np.linalg.norm(v, axis=1), 1.0)


def test_normalize_mesh_turns_up_axis_and_flips_inside_out_faces() -> None:
    v, f = geodesic_sphere(4)
    v = v * np.array([1.0, 3.0, 1.0])  # tall along y
    m = normalize_mesh(Mesh(v * 5 + 2, f[:, ::-1]), up="y")
    ext = m.vertices.max(0) - m.vertices.min(0)
    assert ext[2] == pytest.approx(3 * ext[0], rel=1e-6)  # y is now world z
    fn = np.cross(
        m.vertices[m.faces[:, 1]] - m.vertices[m.faces[:, 0]],
        m.vertices[m.faces[:, 2]] - m.vertices[m.faces[:, 0]],
    )
    centres = m.vertices[m.faces].mean(1)
    assert np.all(np.sum(fn * centres, axis=1) > 0)  # outward again


def test_albedo_is_seeded_in_range_with_broad_and_fine_variation() -> None:
    m = builtin_shape("blob")
    a = procedural_albedo(m.vertices, seed=4)
    assert a.dtype == np.float32 and a.shape == (len(m.vertices), 3)
    assert a.min() >= 0.03 and a.max() <= 0.92
    assert np.array_equal(a, procedural_albedo(m.vertices, seed=4))
    assert not np.array_equal(a, procedural_albedo(m.vertices, seed=5))
    lum = a.mean(1)
    # Fine detail: neighbouring vertices differ; broad patches: distinct mean colours far apart.
    e = m.faces[:, :2]
    assert np.median(np.abs(lum[e[:, 0]] - lum[e[:, 1]])) > 0.003
    assert np.mean(np.abs(lum[e[:, 0]] - lum[e[:, 1]]) > 0.1) > 0.003
    octants = [a[np.all((m.vertices > 0) == np.array(s), axis=1)].mean(0) for s in np.ndindex(2, 2, 2)]
    assert np.ptp(np.array(octants), axis=0).max() > 0.1


def test_rings_cover_below_level_and_above_and_frame_the_object() -> None:
    cams = ring_cameras(36, 612, 512, object_radius=0.35)
    centres = np.array([c.center for c in cams])
    elev = np.degrees(np.arcsin(centres[:, 2] / np.linalg.norm(centres, axis=1)))
    assert sorted(set(np.round(elev).astype(int))) == [-25, 10, 45]
    assert np.ptp(np.linalg.norm(centres, axis=1)) < 1e-9
    pts = fibonacci_sphere(2000) * 0.35  # the object's bounding sphere
    for cam in cams:
        uv, z = cam.project(pts)
        assert np.all(z > 0)
        assert uv[:, 0].min() > 0 and uv[:, 0].max() < 612 and uv[:, 1].min() > 0 and uv[:, 1].max() < 512
        # world up (+z) shows up in the image (image -y)
        assert (cam.R @ np.array([0, 0, 1.0]))[1] < 0


def test_sh_lighting_varies_per_view_and_stays_positive() -> None:
    lights = sh_lights(12, seed=0)
    dirs = fibonacci_sphere(5000)
    for lt in lights:
        s = sh9_basis(dirs) @ lt.sh
        assert s.min() > 0.05 * s.max() and 0.85 < s.max() < 1.15
    assert np.ptp(np.array([lt.sh for lt in lights]), axis=0).max() > 0.02
    # Specular radiance is the environment whose Lambertian shading is S (clamped at 0).
    lt = lights[0]
    assert np.all(lt.radiance(dirs) >= 0)


def test_envmap_shading_is_the_cosine_integral_and_its_sh_projection_is_close() -> None:
    lights = env_lights(3, seed=0)
    dirs = fibonacci_sphere(500)
    lt = lights[1]
    exact = lt.strength * irradiance_shading(environment_map(128, 256), _turn(dirs, -lt.rotation))
    np.testing.assert_allclose(lt.shading(dirs), exact, rtol=0, atol=0.005 * exact.max())
    # The ground truth SH9 projection explains most of the envmap shading (about 95 %).
    resid = lt.shading(dirs) - sh9_basis(dirs) @ lt.sh
    assert np.sqrt(np.mean(resid**2)) < 0.08 * np.sqrt(np.mean(exact**2))
    assert len({lt.rotation for lt in lights}) == 3


def _turn(d: np.ndarray, angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)


@pytest.mark.parametrize(("name", "genus"), [("knot", 1), ("gear", 1), ("spring", 0)])
def test_shape_genus(name: str, genus: int) -> None:
    """The knot and the gear are closed surfaces of genus 1, the spring of genus 0: V - E + F = 2 - 2g."""
    m = builtin_shape(name)
    e = np.unique(np.sort(np.concatenate([m.faces[:, [0, 1]], m.faces[:, [1, 2]], m.faces[:, [2, 0]]]), axis=1), axis=0)
    assert len(np.unique(m.faces)) - len(e) + len(m.faces) == 2 - 2 * genus


def test_mug_has_a_thin_handle_with_a_hole() -> None:
    """Two closed components (body and handle); a ray through the handle's loop passes free."""
    m = builtin_shape("mug")
    tm = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m.vertices), o3d.utility.Vector3iVector(m.faces))
    clusters, counts, _ = tm.cluster_connected_triangles()
    assert len(counts) == 2
    handle = np.unique(m.faces[np.asarray(clusters) == int(np.argmin(counts))])
    hv = m.vertices[handle]
    assert np.ptp(hv, axis=0)[1] < 0.1  # thin: the handle tube is under a tenth of the diagonal across
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(tm))
    body = m.vertices[np.unique(m.faces[np.asarray(clusters) != int(np.argmin(counts))])]
    inner = hv[:, 0].max() - np.ptp(hv[:, 1])  # the loop's inner edge: the outer edge less the tube's width
    x_hole = 0.5 * (body[:, 0].max() + inner)  # between the body's wall and the loop
    ray = o3d.core.Tensor([[x_hole, -2.0, 0.0, 0.0, 1.0, 0.0]], dtype=o3d.core.Dtype.Float32)
    assert not np.isfinite(scene.cast_rays(ray)["t_hit"].numpy()[0])


def test_spring_is_one_thin_coil_with_open_gaps() -> None:
    """One component (of genus 0: :func:`test_shape_genus`); rays across the coil's side hit a turn
    at its height and pass through the gap between two turns; the tube is thin."""
    m = builtin_shape("spring")
    tm = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(m.vertices), o3d.utility.Vector3iVector(m.faces))
    _, counts, _ = tm.cluster_connected_triangles()
    assert len(counts) == 1
    # In the unnormalized frame (helix radius 1, pitch 0.75, tube radius 0.22) the centre line
    # crosses the side x = 1, y = 0 at heights 0, 0.75, 1.5, 2.25.
    from pmvir.synth.shapes import _spring

    raw_v, raw_f = _spring()
    raw = o3d.geometry.TriangleMesh(o3d.utility.Vector3dVector(raw_v), o3d.utility.Vector3iVector(raw_f))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(raw))
    rays = [[1.0, -3.0, z, 0.0, 1.0, 0.0] for z in (0.75, 1.5, 0.75 + 0.375, 1.5 + 0.375)]
    hits = scene.cast_rays(o3d.core.Tensor(rays, dtype=o3d.core.Dtype.Float32))["t_hit"].numpy()
    assert np.all(np.isfinite(hits[:2])) and not np.any(np.isfinite(hits[2:]))
    scale = np.ptp(m.vertices[:, 0]) / np.ptp(raw_v[:, 0])
    assert 0.44 * scale < 0.105  # thin: the tube is a tenth of the diagonal across
