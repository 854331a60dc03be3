"""The built-in renderer: AoP against the normal azimuth on a sphere, exact Lambert, masks vs projection."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from pmvir.camera import Camera, look_at
from pmvir.io.ply import Mesh
from pmvir.synth.builtin_renderer import render_view
from pmvir.synth.generate import polarization_truth
from pmvir.synth.lighting import env_lights, sh_lights
from pmvir.synth.raycast import MeshScene, pixel_directions
from pmvir.synth.rig import ring_cameras
from pmvir.synth.sensor import noiseless_signal, stokes_to_intensities
from pmvir.synth.shapes import builtin_shape
from pmvir.synth.texture import procedural_albedo

W, H = 160, 128


def _scene(shape: str) -> tuple[MeshScene, list[Camera]]:
    m = builtin_shape(shape)
    albedo = procedural_albedo(m.vertices, seed=3)
    scene = MeshScene.from_mesh(Mesh(m.vertices, m.faces, albedo=albedo, normals=m.normals))
    radius = float(np.linalg.norm(m.vertices, axis=1).max())
    return scene, ring_cameras(6, W, H, object_radius=radius)


@pytest.fixture(scope="module")
def sphere() -> tuple[MeshScene, list[Camera]]:
    return _scene("sphere")


def _azimuth(cam: Camera, normal_cam: np.ndarray) -> np.ndarray:
    """Spec section 2: the perspective-exact azimuth of the normal seen along each pixel-centre ray,
    written out with the spec's reference axes (r0 = normalize(d x u), r1 = r0 x d, u = (0, -1, 0))."""
    u, v = np.meshgrid(np.arange(cam.width) + 0.5, np.arange(cam.height) + 0.5)
    _, d = pixel_directions(cam, u.reshape(-1), v.reshape(-1))
    d = d.reshape(normal_cam.shape).astype(np.float64)
    r0 = np.cross(d, [0.0, -1.0, 0.0])
    r0 /= np.linalg.norm(r0, axis=-1, keepdims=True)
    r1 = np.cross(r0, d)
    e = normal_cam - (normal_cam * d).sum(-1, keepdims=True) * d
    return np.arctan2((e * r1).sum(-1), (e * r0).sum(-1))


def _diff_mod_pi(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """|a - b| modulo pi, in [0, pi/2], radians."""
    return np.abs(np.angle(np.exp(2j * (a - b)))) / 2


def _pol(stokes: np.ndarray) -> np.ndarray:
    """Magnitude of the colour-mean linear polarization sqrt(s1^2 + s2^2), (H, W)."""
    m = stokes.mean(axis=2)
    return np.hypot(m[..., 1], m[..., 2])


@pytest.mark.parametrize("lighting", ["sh", "envmap"])
def test_plastic_sphere_aop_follows_the_dominant_component(sphere, lighting: str) -> None:
    """Diffuse-dominant pixels: phi = alpha (mod pi); specular-dominant: phi = alpha + pi/2."""
    scene, cams = sphere
    lights = sh_lights(6, seed=0) if lighting == "sh" else env_lights(6, seed=0)
    n_diffuse = n_specular = 0
    for k in (0, 2, 4):  # below, level, above
        full = render_view(scene, cams[k], lights[k], material="plastic", supersample=1)
        diffuse = render_view(scene, cams[k], lights[k], material="plastic", specular=0.0, supersample=1)
        pol_d = _pol(diffuse.stokes)
        pol_s = _pol(full.stokes - diffuse.stokes)  # Stokes vectors add: the specular part alone
        truth = polarization_truth(full.stokes, 1.0)
        mask = full.geometry.mask
        alpha = _azimuth(cams[k], full.geometry.normal_cam.astype(np.float64))
        d_dom = mask & (pol_d > 3 * pol_s) & (truth["dop"] > 0.002)
        s_dom = mask & (pol_s > 3 * pol_d) & (truth["dop"] > 0.002)
        n_diffuse += d_dom.sum()
        n_specular += s_dom.sum()
        assert np.degrees(_diff_mod_pi(truth["aop"][d_dom], alpha[d_dom])).max() < 1.0
        assert np.degrees(_diff_mod_pi(truth["aop"][s_dom], alpha[s_dom] + np.pi / 2)).max() < 1.0
    assert n_diffuse > 300 and n_specular > 300  # both regimes are present and were tested


def test_conductor_sphere_is_polarized_perpendicular_to_the_azimuth(sphere) -> None:
    scene, cams = sphere
    light = sh_lights(6, seed=1)[3]
    view = render_view(scene, cams[3], light, material="conductor", supersample=1)
    truth = polarization_truth(view.stokes, 1.0)
    sel = view.geometry.mask & (truth["dop"] > 0.01)
    assert sel.sum() > 0.5 * view.geometry.mask.sum()
    alpha = _azimuth(cams[3], view.geometry.normal_cam.astype(np.float64))
    assert np.degrees(_diff_mod_pi(truth["aop"][sel], alpha[sel] + np.pi / 2)).max() < 1.0
    # Strong specular polarization: DoP reaches well above a dielectric diffuse DoP.
    assert np.percentile(truth["dop"][view.geometry.mask], 95) > 0.5


def test_lambert_dop_is_exactly_zero_before_noise(sphere) -> None:
    scene, cams = sphere
    view = render_view(scene, cams[1], env_lights(6, seed=0)[1], material="lambert")
    assert np.all(view.stokes[..., 1:] == 0.0)
    assert np.all(polarization_truth(view.stokes, 1.0)["dop"] == 0.0)
    intensities = stokes_to_intensities(view.stokes)
    for a in range(1, 4):  # all four polarizer angles see the same intensity, bit for bit
        assert np.array_equal(intensities[:, :, a], intensities[:, :, 0])
    assert noiseless_signal(view.stokes, 0.7).max() > 0


def test_lambert_pixels_are_albedo_times_sh_shading(sphere) -> None:
    """Spec section 3: a Lambert pixel is K * S(N) * colour with S the view's pmvir-sh9 shading."""
    from pmvir.sh import sh9_shading
    from pmvir.synth.raycast import pixel_directions, trace

    scene, cams = sphere
    cam, light = cams[2], sh_lights(6, seed=2)[2]
    view = render_view(scene, cam, light, material="lambert", supersample=1)
    u, v = np.meshgrid(np.arange(W) + 0.5, np.arange(H) + 0.5)
    d_world, _ = pixel_directions(cam, u.reshape(-1), v.reshape(-1))
    hits = trace(scene, cam.center, d_world)
    n_world = view.geometry.normal_cam.reshape(-1, 3)[hits.hit] @ cam.R  # camera -> world
    expect = hits.albedo * sh9_shading(n_world.astype(np.float64), light.sh)[:, None] * light.colour
    got = view.stokes[..., 0].reshape(-1, 3)[hits.hit]
    np.testing.assert_allclose(got, expect, rtol=1e-4, atol=1e-6)


def test_orthographic_normal_frame_is_off_the_exact_rule_away_from_the_axis(sphere) -> None:
    """The default (aop_frame="ray") is the spec's perspective-exact rule; the orthographic
    switch agrees with it at the image centre only and is measurably off toward the edges."""
    scene, cams = sphere
    light = sh_lights(6, seed=0)[0]
    k, c0 = cams[0].K, cams[0]
    R, t = look_at(c0.center, 0.25 * c0.R[0] - 0.2 * c0.R[1])  # the sphere off the optical axis, wider lens
    cam = Camera.from_intrinsics(0.6 * k[0, 0], 0.6 * k[1, 1], k[0, 2], k[1, 2], W, H, R, t)
    view = render_view(scene, cam, light, material="conductor", supersample=1)
    ortho = render_view(scene, cam, light, material="conductor", aop_frame="normal", supersample=1)
    exact = polarization_truth(view.stokes, 1.0)
    sel = view.geometry.mask & (exact["dop"] > 0.01)
    alpha = _azimuth(cam, view.geometry.normal_cam.astype(np.float64))
    assert np.degrees(_diff_mod_pi(exact["aop"][sel], alpha[sel] + np.pi / 2)).max() < 0.05
    off = np.degrees(_diff_mod_pi(polarization_truth(ortho.stokes, 1.0)["aop"][sel], exact["aop"][sel]))
    assert np.median(off) > 3.0  # the sphere sits off the optical axis


def _rasterize_projection(mesh: Mesh, cam: Camera) -> np.ndarray:
    """Pixels whose centre (col + 0.5, row + 0.5) lies inside the projection of any triangle.

    The union of the projected triangles of a closed mesh is exactly its silhouette. Exact
    point-in-triangle tests (edge functions) on the pixel centres of each triangle's bounding box.
    """
    uv, depth = cam.project(mesh.vertices)
    assert np.all(depth > 0)
    tri = uv[mesh.faces]  # (F, 3, 2)
    lo = np.floor(tri.min(axis=1) - 0.5).astype(int)  # first pixel index whose centre may be inside
    span = int((np.ceil(tri.max(axis=1) - 0.5).astype(int) - lo).max()) + 1
    oy, ox = np.meshgrid(np.arange(span), np.arange(span), indexing="ij")
    cols = lo[:, None, 0] + ox.reshape(1, -1)
    rows = lo[:, None, 1] + oy.reshape(1, -1)
    px, py = cols + 0.5, rows + 0.5

    def edge(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return (b[:, None, 0] - a[:, None, 0]) * (py - a[:, None, 1]) - (b[:, None, 1] - a[:, None, 1]) * (
            px - a[:, None, 0]
        )

    e0, e1, e2 = edge(tri[:, 0], tri[:, 1]), edge(tri[:, 1], tri[:, 2]), edge(tri[:, 2], tri[:, 0])
    inside = ((e0 >= 0) & (e1 >= 0) & (e2 >= 0)) | ((e0 <= 0) & (e1 <= 0) & (e2 <= 0))
    inside &= (cols >= 0) & (cols < cam.width) & (rows >= 0) & (rows < cam.height)
    out = np.zeros((cam.height, cam.width), dtype=bool)
    out[rows[inside], cols[inside]] = True
    return out


@pytest.mark.parametrize("shape", ["dented", "knot"])
def test_masks_match_projected_ground_truth_from_below_level_and_above(shape: str) -> None:
    m = builtin_shape(shape)
    mesh = Mesh(m.vertices, m.faces, albedo=procedural_albedo(m.vertices, seed=0), normals=m.normals)
    scene = MeshScene.from_mesh(mesh)
    radius = float(np.linalg.norm(m.vertices, axis=1).max())
    cams = ring_cameras(6, W, H, object_radius=radius)
    light = sh_lights(1, seed=0)[0]
    elevations = []
    for k in (0, 2, 4):  # rings at -25, 10 and 45 degrees
        cam = cams[k]
        elevations.append(np.degrees(np.arcsin(cam.center[2] / np.linalg.norm(cam.center))))
        mask = render_view(scene, cam, light, material="lambert").geometry.mask
        proj = _rasterize_projection(mesh, cam)
        iou = (mask & proj).sum() / (mask | proj).sum()
        assert iou > 0.995, f"view {k}: IoU {iou:.4f}"  # issue: > 0.98; a half-pixel shift gives ~0.98
        # Every vertex that is not hidden projects inside the rendered mask (1-pixel tolerance).
        uv, _ = cam.project(mesh.vertices)
        ij = np.floor(uv).astype(int)
        dil = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
        inside = (ij[:, 0] >= 0) & (ij[:, 0] < W) & (ij[:, 1] >= 0) & (ij[:, 1] < H)
        assert inside.all() and dil[ij[:, 1], ij[:, 0]].all()
    assert elevations[0] < -10 and abs(elevations[1]) < 15 and elevations[2] > 30


def test_silhouette_pixels_are_antialiased(sphere) -> None:
    scene, cams = sphere
    light = sh_lights(1, seed=0)[0]
    sharp = render_view(scene, cams[1], light, material="lambert", supersample=1)
    smooth = render_view(scene, cams[1], light, material="lambert", supersample=4)
    mask = sharp.geometry.mask
    assert np.array_equal(mask, smooth.geometry.mask)
    s0_sharp, s0_smooth = sharp.stokes[..., 0].mean(-1), smooth.stokes[..., 0].mean(-1)
    assert np.all(s0_sharp[~mask] == 0.0)
    partial = (~mask) & (s0_smooth > 0)  # background centres, object partly inside the pixel
    assert partial.sum() > 20
    ring = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)
    assert np.all(ring[partial])  # only next to the silhouette
    interior = cv2.erode(mask.astype(np.uint8), np.ones((15, 15), np.uint8)).astype(bool)
    assert np.array_equal(s0_sharp[interior], s0_smooth[interior])
