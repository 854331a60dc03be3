"""Mitsuba 3 renders of spheres off the optical axis: the AoP follows the perspective-exact azimuth.

The spec's rule (section 2) is checked against an independent physical renderer: where the
rendered DoP is measurable the AoP is within 1 degree of ``perspective_azimuth`` (diffuse:
phi = alpha; specular: phi = alpha + pi/2) and measurably off the orthographic rule. Skips
without the ``mitsuba`` extra or its LLVM backend.
"""

from __future__ import annotations

import numpy as np
import pytest
from test_mitsuba_renderer import angle_error, mitsuba, uv_sphere  # noqa: F401 (fixture)

from pmvir.camera import Camera, look_at
from pmvir.polarization.azimuth import orthographic_azimuth, perspective_azimuth
from pmvir.synth.mitsuba_renderer import render_view_stokes

CENTRE = np.array([0.0, 0.0, 0.0])


def off_axis_camera() -> Camera:
    """A wide lens whose optical axis passes well beside the unit sphere at the origin."""
    R, t = look_at(np.array([0.0, -4.0, 0.0]), np.array([1.3, 0.0, 1.0]), up=np.array([0.0, 0.0, 1.0]))
    return Camera.from_intrinsics(34.0, 34.0, 32.0, 24.0, 64, 48, R, t)


def sphere_truth(camera: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel centre: hit mask, camera-frame unit normal, camera-frame unit ray."""
    origins, dirs = camera.pixel_rays()
    oc = origins - CENTRE
    b = np.einsum("hwk,hwk->hw", oc, dirs)
    disc = b * b - (np.einsum("hwk,hwk->hw", oc, oc) - 1.0)
    t = -b - np.sqrt(np.maximum(disc, 0.0))
    normal = origins + t[..., None] * dirs - CENTRE
    return disc > 0.0, normal @ camera.R.T, dirs @ camera.R.T


@pytest.mark.parametrize(("material", "options", "offset"), [
    ("pplastic", {"specular": 0.0}, 0.0),  # diffuse polarization: phi = alpha
    ("conductor", {"ior": 0.47, "extinction": 2.4}, np.pi / 2),  # specular: phi = alpha + pi/2
])
def test_aop_of_an_off_axis_sphere_is_perspective_exact(mitsuba, material, options, offset):  # noqa: F811
    vertices, faces, normals = uv_sphere(CENTRE)
    camera = off_axis_camera()
    image = render_view_stokes(vertices, faces, np.full((len(vertices), 3), 0.8), camera,
                               material=material, envmap=np.ones((8, 16, 3), np.float32),
                               normals=normals, spp=32, **options)
    hit, n_cam, d_cam = sphere_truth(camera)
    s = image.stokes.mean(axis=2)
    aop = np.mod(0.5 * np.arctan2(s[..., 2], s[..., 1]), np.pi)
    dop = np.hypot(s[..., 1], s[..., 2]) / np.maximum(s[..., 0], 1e-9)
    mask = (image.alpha == 1.0) & hit & (dop > 0.02)
    assert mask.sum() > 150
    alpha, defined = perspective_azimuth(n_cam, d_cam)
    err = np.degrees(angle_error(aop, alpha + offset))[mask & defined]
    ortho = np.degrees(angle_error(aop, orthographic_azimuth(n_cam) + offset))[mask]
    assert np.median(err) < 1.0 and np.percentile(err, 90) < 2.0
    assert np.median(ortho) > 3.0  # the sphere is off the axis: the orthographic rule is measurably off
