"""Fine-relief built-in shapes: relief a few pixels across, rendered by both renderers.

Views are crops of the default rig's 612 x 512 cameras (same focal length and distance), so a
pixel covers as much surface as in a full-size capture. The Mitsuba tests skip without the
``mitsuba`` extra or its LLVM backend.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_mitsuba_renderer import angle_error, mitsuba  # noqa: F401 (fixture)

from pmvir.camera import Camera
from pmvir.io.ply import Mesh, vertex_normals
from pmvir.polarization.azimuth import perspective_azimuth
from pmvir.synth.builtin_renderer import render_view
from pmvir.synth.generate import polarization_truth
from pmvir.synth.lighting import sh_lights
from pmvir.synth.raycast import MeshScene
from pmvir.synth.relief import RELIEF_SHAPES
from pmvir.synth.rig import ring_cameras
from pmvir.synth.shapes import SHAPES, builtin_shape
from pmvir.synth.texture import procedural_albedo

CROP = (96, 80)  # width, height of the crop at the image centre


def crop_camera(shape: str, view: int) -> Camera:
    """View ``view`` of the default 36-view rig round ``shape``, cropped to CROP at the image centre."""
    m = builtin_shape(shape)
    cam = ring_cameras(36, 612, 512, object_radius=float(np.linalg.norm(m.vertices, axis=1).max()))[view]
    w, h = CROP
    k = cam.K
    return Camera.from_intrinsics(k[0, 0], k[1, 1], k[0, 2] - (612 - w) / 2, k[1, 2] - (512 - h) / 2, w, h, cam.R, cam.t)


def smoothed(vertices: np.ndarray, faces: np.ndarray, iterations: int) -> np.ndarray:
    """Uniform Laplacian smoothing (each vertex moved to its neighbours' mean), ``iterations`` times."""
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    count = np.bincount(e[:, 0], minlength=len(vertices)).astype(np.float64)[:, None]
    v = vertices.copy()
    for _ in range(iterations):
        total = np.zeros_like(v)
        np.add.at(total, e[:, 0], v[e[:, 1]])
        v = total / count
    return v


def test_relief_shapes_are_built_in() -> None:
    assert set(RELIEF_SHAPES) <= set(SHAPES)


@pytest.mark.parametrize("name", RELIEF_SHAPES)
def test_relief_is_steep_and_shallow(name: str) -> None:
    """Smoothing away the finest relief (20 Laplacian steps: a few edges, a few pixels) turns the
    normals by several degrees on average while moving the surface by under a pixel; the blob's
    bumps, broad by comparison, hardly turn under the same smoothing (5 steps of its edges, twice
    as long)."""

    def turn_and_shift(shape: str, iterations: int) -> tuple[float, float]:
        m = builtin_shape(shape)
        s = smoothed(m.vertices, m.faces, iterations)
        cos = np.einsum("ij,ij->i", vertex_normals(m.vertices, m.faces), vertex_normals(s, m.faces))
        return float(np.degrees(np.arccos(np.clip(cos, -1, 1))).mean()), float(
            np.median(np.linalg.norm(s - m.vertices, axis=1))
        )

    turn, shift = turn_and_shift(name, 20)
    blob_turn, _ = turn_and_shift("blob", 5)
    assert turn > 6.0 and turn > 3 * blob_turn
    assert shift < 0.003  # of the unit diagonal: under a pixel at 612 x 512


@pytest.mark.parametrize("name", RELIEF_SHAPES)
def test_builtin_plastic_render_shows_relief_a_few_pixels_across(name: str) -> None:
    """The noise-free AoP follows the normal's azimuth where diffuse polarization dominates, and
    normals three pixels apart differ by degrees (the blob's by 1.5 on average, the sphere's 0.6)."""
    m = builtin_shape(name)
    scene = MeshScene.from_mesh(Mesh(m.vertices, m.faces, albedo=procedural_albedo(m.vertices, seed=1), normals=m.normals))
    cam = crop_camera(name, 13)
    view = render_view(scene, cam, sh_lights(36, seed=0)[13], material="plastic", specular=0.0, supersample=1)
    mask = view.geometry.mask
    assert mask.mean() > 0.6
    n = view.geometry.normal_cam.astype(np.float64)
    both = mask[:, 3:] & mask[:, :-3]
    turn = np.degrees(np.arccos(np.clip((n[:, 3:] * n[:, :-3]).sum(-1), -1, 1)))[both]
    assert turn.mean() > 3.0
    _, d_world = cam.pixel_rays()
    alpha, defined = perspective_azimuth(n, d_world @ cam.R.T)
    truth = polarization_truth(view.stokes, 1.0)
    sel = mask & defined & (truth["dop"] > 0.002)
    assert sel.sum() > 0.5 * mask.sum()
    assert np.degrees(angle_error(truth["aop"], alpha))[sel].max() < 1.0


@pytest.mark.parametrize(("roughness", "median_deg"), [(0.05, 2.5), (0.3, 15.0)])  # plastic, rough plastic
@pytest.mark.parametrize("name", RELIEF_SHAPES)
def test_mitsuba_renders_relief_shapes(mitsuba, name: str, roughness: float, median_deg: float) -> None:  # noqa: F811
    """Mitsuba's silhouette matches the built-in renderer's, and where its polarization is
    measurable its AoP follows the true azimuth of the relief pixel by pixel: phi = alpha where
    diffuse reflection dominates, alpha + 90 degrees where specular reflection does (a median of
    22.5 degrees off both would be chance; a rough plastic's microfacets scatter it most)."""
    from pmvir.synth.mitsuba_renderer import render_view_stokes

    m = builtin_shape(name)
    cam = crop_camera(name, 13)
    light = sh_lights(36, seed=0)[13]
    albedo = procedural_albedo(m.vertices, seed=1)
    image = render_view_stokes(
        m.vertices, m.faces, albedo, cam, material="plastic", roughness=roughness,
        sh=light.sh, rgb_scale=light.colour, normals=m.normals, spp=16,
    )
    scene = MeshScene.from_mesh(Mesh(m.vertices, m.faces, albedo=albedo, normals=m.normals))
    geo = render_view(scene, cam, light, material="plastic", supersample=1).geometry
    assert np.mean((image.alpha > 0.5) == geo.mask) > 0.97
    s = image.stokes.mean(axis=2)
    assert np.isfinite(s).all() and (s[..., 0] >= 0).all()
    dop = np.hypot(s[..., 1], s[..., 2]) / np.maximum(s[..., 0], 1e-9)
    aop = np.mod(0.5 * np.arctan2(s[..., 2], s[..., 1]), np.pi)
    _, d_world = cam.pixel_rays()
    alpha, defined = perspective_azimuth(geo.normal_cam.astype(np.float64), d_world @ cam.R.T)
    sel = geo.mask & (image.alpha == 1.0) & defined & (dop > 0.02)
    assert sel.sum() > 0.1 * geo.mask.sum()
    err = np.degrees(angle_error(aop, alpha))[sel]
    either = np.minimum(err, 90.0 - err)  # off both alpha and alpha + 90 degrees
    assert np.median(either) < median_deg
