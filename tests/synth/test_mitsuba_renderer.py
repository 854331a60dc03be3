"""Mitsuba 3 polarized renderer: camera, environment, shading and Stokes frame against ground truth.

Rendering tests skip when the optional ``mitsuba`` extra (or its LLVM backend) is missing; the
input checks run without it.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage

from pmvir.camera import Camera, look_at
from pmvir.errors import ConfigError
from pmvir.sh import radiance_from_shading, sh9_basis, sh9_shading
from pmvir.synth.mitsuba_renderer import envmap_directions, envmap_from_sh, render_view_stokes


@pytest.fixture(scope="module")
def mitsuba():
    """Mitsuba and Dr.Jit with the renderer's variant selected (skips when unavailable)."""
    pytest.importorskip("mitsuba")
    from pmvir.errors import PmvirError
    from pmvir.synth import mitsuba_renderer

    try:
        return mitsuba_renderer._mitsuba()
    except PmvirError as exc:  # LLVM backend missing
        pytest.skip(str(exc))


def uv_sphere(center=(0.0, 0.0, 0.0), radius=1.0, n_lat=48, n_lon=96):
    """A closed UV sphere, faces counter-clockwise from outside; returns vertices, faces, unit normals."""
    theta = np.linspace(0.0, np.pi, n_lat + 1)[1:-1]
    phi = np.linspace(0.0, 2.0 * np.pi, n_lon, endpoint=False)
    t, p = np.meshgrid(theta, phi, indexing="ij")
    ring = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1).reshape(-1, 3)
    normals = np.concatenate([[[0.0, 0.0, 1.0]], ring, [[0.0, 0.0, -1.0]]])
    faces = []
    ring_index = lambda i, j: 1 + i * n_lon + (j % n_lon)  # noqa: E731
    south = len(normals) - 1
    for j in range(n_lon):
        faces.append([0, ring_index(0, j), ring_index(0, j + 1)])
        faces.append([south, ring_index(n_lat - 2, j + 1), ring_index(n_lat - 2, j)])
        for i in range(n_lat - 2):
            a, b = ring_index(i, j), ring_index(i, j + 1)
            c, d = ring_index(i + 1, j), ring_index(i + 1, j + 1)
            faces += [[a, c, d], [a, d, b]]
    vertices = np.asarray(center) + radius * normals
    return vertices, np.asarray(faces, dtype=np.int64), normals


def unit_sphere_truth(camera: Camera):
    """Per pixel centre: hit mask, unit-sphere point (= normal), ray direction (world)."""
    origins, dirs = camera.pixel_rays()
    b = np.einsum("hwk,hwk->hw", origins, dirs)
    disc = b * b - (np.einsum("hwk,hwk->hw", origins, origins) - 1.0)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    return disc > 0.0, origins + t[..., None] * dirs, dirs


def angle_error(a, b):
    """|a - b| modulo pi, in [0, pi/2]."""
    return np.abs(np.mod(a - b + np.pi / 2, np.pi) - np.pi / 2)


def small_camera(width=48, height=40, fx=44.0, fy=40.0, cx=22.5, cy=21.0):
    R, t = look_at(np.array([1.0, -3.5, 1.5]), np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
    return Camera.from_intrinsics(fx, fy, cx, cy, width, height, R, t)


SH = np.array([1.0, 0.3, 0.2, -0.25, 0.05, -0.05, 0.08, 0.04, -0.06])  # radiance > 0 everywhere


def test_envmap_directions_follow_mitsuba_envmap(mitsuba):
    """The documented lat-long convention is the one the installed Mitsuba envmap evaluates."""
    mi, dr = mitsuba
    dirs = envmap_directions(64, 128)
    f = lambda d: 1.0 + 0.5 * d[..., 0] - 0.3 * d[..., 1] + 0.2 * d[..., 2]  # noqa: E731
    bitmap = mi.Bitmap(np.repeat(f(dirs)[..., None], 3, axis=-1).astype(np.float32))
    emitter = mi.load_dict({"type": "envmap", "bitmap": bitmap})
    probe = np.random.default_rng(3).normal(size=(200, 3))
    probe /= np.linalg.norm(probe, axis=1, keepdims=True)
    si = dr.zeros(mi.SurfaceInteraction3f, len(probe))
    si.wi = mi.Vector3f((-probe.T).astype(np.float32))  # wi points away from the light
    value = np.asarray(emitter.eval(si)[0, 0]).ravel()
    np.testing.assert_allclose(value, f(probe), atol=2e-3)


def test_projection_matches_camera(mitsuba):
    """Tiny spheres land where Camera.project puts their centres (fx != fy, off-centre cx, cy)."""
    R, t = look_at(np.array([0.4, -4.0, 1.2]), np.array([0.1, 0.0, 0.05]), up=np.array([0.0, 0.0, 1.0]))
    camera = Camera.from_intrinsics(70.0, 58.0, 27.3, 25.8, 64, 48, R, t)
    centers = np.array([[0.0, 0.0, 0.0], [0.55, 0.3, 0.4], [-0.6, -0.2, -0.35], [0.5, 0.1, -0.4]])
    parts = [uv_sphere(c, 0.08, 8, 16) for c in centers]
    offsets = np.cumsum([0] + [len(p[0]) for p in parts[:-1]])
    vertices = np.concatenate([p[0] for p in parts])
    faces = np.concatenate([p[1] + o for p, o in zip(parts, offsets, strict=True)])
    image = render_view_stokes(vertices, faces, np.full((len(vertices), 3), 0.5), camera,
                               material="diffuse", envmap=np.ones((8, 16, 3), np.float32), spp=32)
    labels, count = ndimage.label(image.alpha > 0)
    assert count == len(centers)
    rows, cols = np.mgrid[0:camera.height, 0:camera.width]
    found = []
    for k in range(1, count + 1):
        w = np.where(labels == k, image.alpha, 0.0)
        found.append([(w * (cols + 0.5)).sum() / w.sum(), (w * (rows + 0.5)).sum() / w.sum()])
    uv, _ = camera.project(centers)
    for expected in uv:  # match each projected centre to the nearest blob centroid
        nearest = min(found, key=lambda f: np.hypot(*(np.asarray(f) - expected)))
        assert np.hypot(*(np.asarray(nearest) - expected)) < 0.3


def test_diffuse_sphere_under_sh_matches_pmvir_model(mitsuba):
    """Lambert pixels are albedo * S(N) * rgb_scale, background pixels the SH environment."""
    vertices, faces, normals = uv_sphere()
    camera = small_camera(40, 36, 38.0, 36.0, 19.5, 18.5)
    albedo = np.array([0.7, 0.5, 0.3])
    rgb_scale = np.array([0.9, 1.0, 1.2])
    image = render_view_stokes(vertices, faces, np.tile(albedo, (len(vertices), 1)), camera,
                               material="lambert", sh=SH, rgb_scale=rgb_scale, normals=normals, spp=256)
    hit, points, dirs = unit_sphere_truth(camera)
    inside = ndimage.binary_erosion((image.alpha == 1.0) & hit)
    expected = albedo * sh9_shading(points, SH)[..., None] * rgb_scale
    s0 = image.stokes[..., 0]
    rel = s0[inside] / expected[inside] - 1.0
    assert inside.sum() > 150
    assert np.all(np.abs(rel.mean(axis=0)) < 0.01)  # unbiased per channel
    assert np.sqrt(np.mean(rel**2)) < 0.05  # Monte Carlo noise at 256 spp (about 0.03)
    assert np.abs(image.stokes[..., 1:]).max() < 1e-6  # Lambert is unpolarized
    background = image.alpha == 0.0
    radiance = (sh9_basis(dirs) @ radiance_from_shading(SH))[..., None] * rgb_scale
    np.testing.assert_allclose(s0[background], radiance[background], rtol=5e-3)


def test_envmap_from_sh_is_clamped_radiance():
    coeffs = np.array([0.1, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    env = envmap_from_sh(coeffs, np.array([1.0, 2.0, 0.5]), height=16, width=32)
    dirs = envmap_directions(16, 32)
    expected = np.maximum(sh9_basis(dirs) @ radiance_from_shading(coeffs), 0.0)
    assert env.shape == (16, 32, 3) and env.dtype == np.float32
    np.testing.assert_allclose(env, expected[..., None] * np.array([1.0, 2.0, 0.5]), rtol=1e-5, atol=1e-6)
    assert env.min() == 0.0  # the negative lobe is clamped


@pytest.mark.parametrize(("material", "options", "offset"), [
    ("pplastic", {"specular": 0.0}, 0.0),  # diffuse polarization only: phi = alpha
    ("conductor", {"ior": 0.47, "extinction": 2.4}, np.pi / 2),  # specular: phi = alpha + pi/2
])
def test_aop_follows_spec_sense_on_sphere(mitsuba, material, options, offset):
    """AoP = 0.5 atan2(s2, s1) is the normal azimuth (ccw from image +x toward image up), + offset."""
    vertices, faces, normals = uv_sphere()
    camera = small_camera()
    image = render_view_stokes(vertices, faces, np.full((len(vertices), 3), 0.8), camera,
                               material=material, envmap=np.ones((8, 16, 3), np.float32),
                               normals=normals, spp=16, **options)
    hit, n, d = unit_sphere_truth(camera)
    s = image.stokes.mean(axis=2)
    aop = np.mod(0.5 * np.arctan2(s[..., 2], s[..., 1]), np.pi)
    dop = np.hypot(s[..., 1], s[..., 2]) / np.maximum(s[..., 0], 1e-9)
    mask = (image.alpha == 1.0) & hit & (dop > 0.01)
    assert mask.sum() > 250
    # Exact: the plane of emission/incidence projected on the module's per-ray basis.
    x_ref = np.cross(d, -camera.R[1])
    x_ref /= np.linalg.norm(x_ref, axis=-1, keepdims=True)
    y_ref = np.cross(-d, x_ref)
    e = n - np.einsum("hwk,hwk->hw", n, d)[..., None] * d
    exact = np.arctan2(np.einsum("hwk,hwk->hw", e, y_ref), np.einsum("hwk,hwk->hw", e, x_ref))
    err = angle_error(aop, exact + offset)[mask]
    assert np.median(err) < np.radians(1.5) and np.percentile(err, 95) < np.radians(4.0)
    # The spec's orthographic relation (section 2): alpha = atan2(-ny, nx) of the camera-frame normal.
    n_cam = n @ camera.R.T
    alpha = np.arctan2(-n_cam[..., 1], n_cam[..., 0])
    err_spec = angle_error(aop, alpha + offset)[mask]
    assert np.median(err_spec) < np.radians(2.0)
    # The opposite (clockwise) sense would be far off.
    assert np.median(angle_error(aop, -alpha + offset)[mask]) > np.radians(20.0)


def test_same_seed_same_image_and_seed_changes_noise(mitsuba):
    vertices, faces, _ = uv_sphere(n_lat=12, n_lon=24)
    camera = small_camera(16, 12, 15.0, 14.0, 8.0, 6.0)
    args = (vertices, faces, np.full((len(vertices), 3), 0.6), camera)
    kw = dict(material="pplastic", sh=SH, rgb_scale=np.ones(3), spp=4)
    a = render_view_stokes(*args, seed=1, **kw)
    b = render_view_stokes(*args, seed=1, **kw)
    c = render_view_stokes(*args, seed=2, **kw)
    assert a.stokes.shape == (12, 16, 3, 3) and a.stokes.dtype == np.float32
    assert a.alpha.shape == (12, 16) and a.alpha.dtype == np.float32
    # Same seed, same samples: equal up to the order of the LLVM backend's threaded float sums (under
    # load a few values can differ by 1 ulp); another seed differs by sampling noise.
    np.testing.assert_allclose(a.stokes, b.stokes, rtol=1e-5, atol=1e-6)
    assert np.abs(a.stokes - c.stokes).max() > 1e-3


# ---- bad inputs (no Mitsuba needed: checked before rendering) ----

def _args():
    vertices, faces, _ = uv_sphere(n_lat=4, n_lon=8)
    return vertices, faces, np.full((len(vertices), 3), 0.5), small_camera(8, 8, 8.0, 8.0, 4.0, 4.0)


def _env():
    return np.ones((4, 8, 3), np.float32)


def test_rejects_bad_vertices_shape():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="vertices"):
        render_view_stokes(v[:, :2], f, a, cam, envmap=_env())


def test_rejects_face_index_out_of_range():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="face indices"):
        render_view_stokes(v, f + len(v), a, cam, envmap=_env())


def test_rejects_albedo_of_wrong_length():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="albedo"):
        render_view_stokes(v, f, a[:-1], cam, envmap=_env())


def test_rejects_normals_of_wrong_shape():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="normals"):
        render_view_stokes(v, f, a, cam, envmap=_env(), normals=v[:-1])


def test_rejects_unknown_material():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="unknown material"):
        render_view_stokes(v, f, a, cam, material="velvet", envmap=_env())


def test_rejects_both_sh_and_envmap():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="exactly one"):
        render_view_stokes(v, f, a, cam, sh=SH, rgb_scale=np.ones(3), envmap=_env())


def test_rejects_no_lighting():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="exactly one"):
        render_view_stokes(v, f, a, cam)


def test_rejects_sh_without_rgb_scale():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="rgb_scale"):
        render_view_stokes(v, f, a, cam, sh=SH)


def test_rejects_sh_of_wrong_length():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="SH coefficients"):
        render_view_stokes(v, f, a, cam, sh=SH[:4], rgb_scale=np.ones(3))


def test_rejects_envmap_without_three_channels():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="envmap"):
        render_view_stokes(v, f, a, cam, envmap=np.ones((4, 8), np.float32))


def test_rejects_negative_envmap():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match=">= 0"):
        render_view_stokes(v, f, a, cam, envmap=-_env())


def test_rejects_zero_spp():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="spp"):
        render_view_stokes(v, f, a, cam, envmap=_env(), spp=0)


def test_rejects_smooth_pplastic():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="roughness"):
        render_view_stokes(v, f, a, cam, material="pplastic", roughness=0.0, envmap=_env())


def test_rejects_index_of_one():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="ior"):
        render_view_stokes(v, f, a, cam, material="conductor", ior=1.0, envmap=_env())


def test_rejects_negative_specular():
    v, f, a, cam = _args()
    with pytest.raises(ConfigError, match="specular"):
        render_view_stokes(v, f, a, cam, material="pplastic", specular=-1.0, envmap=_env())


def test_envmap_directions_reject_tiny_maps():
    with pytest.raises(ConfigError, match="texels"):
        envmap_directions(2, 8)
