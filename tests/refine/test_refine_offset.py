"""The photo-consistent offset scan (pmvir.refine.offset): it finds a shrunk or swollen surface's offset."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from refine_scene import RGB_SCALE, SH, ring_cameras

from pmvir.errors import ConfigError
from pmvir.refine import observation_from_decoded
from pmvir.refine.forward import render_decoded
from pmvir.refine.offset import neighbour_views, photo_consistent_offset
from pmvir.refine.sampling import Observation
from pmvir.synth.shapes import geodesic_sphere


def _textured(vertices: np.ndarray) -> np.ndarray:
    """A 3D checker-like albedo (features of about 10 pixels at the test's image size)."""
    x, y, z = vertices.T
    t = np.sin(13 * x) * np.sin(13 * y + 1.0) * np.sin(13 * z + 2.0)
    a = 0.45 + 0.3 * np.tanh(4 * t)
    return np.stack([a, 0.8 * a + 0.1, 0.6 * a + 0.15], axis=1)


@pytest.fixture(scope="module")
def sphere_views():
    tv, tf = geodesic_sphere(48)
    cams = ring_cameras(12, 128)
    frames = render_decoded(
        tv, tf, _textured(tv), cams, np.tile(SH, (12, 1)), RGB_SCALE, dop_scale=0.0, intensity_noise=0.002
    )
    return tv, tf, cams, [observation_from_decoded(f) for f in frames]


def _gsd(cams, vertices) -> float:
    return float(np.mean([np.median(c.world_to_cam(vertices)[:, 2]) / c.K[0, 0] for c in cams]))


@pytest.mark.parametrize("shift_px", [-0.6, 0.6])
def test_the_scan_finds_a_shrunk_or_swollen_spheres_offset(sphere_views, shift_px):
    tv, tf, cams, obs = sphere_views
    gsd = _gsd(cams, tv)
    start = tv * (1.0 + shift_px * gsd)  # the unit sphere moved shift_px pixels along its normals
    scan = photo_consistent_offset(start, tf, cams, obs, min_cos=0.7)
    assert scan.applied, scan.reason
    # the offset brings the surface back within a quarter of the shift
    assert abs(scan.offset + shift_px * gsd) < 0.25 * abs(shift_px) * gsd, scan.to_dict()
    assert scan.pixels > 2000


def test_the_true_surface_stays_where_it_is(sphere_views):
    tv, tf, cams, obs = sphere_views
    scan = photo_consistent_offset(tv, tf, cams, obs, min_cos=0.7)
    assert scan.applied
    assert abs(scan.offset) < 0.15 * _gsd(cams, tv), scan.to_dict()
    assert np.argmin(scan.costs) == len(scan.costs) // 2  # the scan's minimum is at zero offset


def test_no_texture_no_offset(sphere_views):
    tv, tf, cams, _ = sphere_views
    flat = [
        observation_from_decoded(f)
        for f in render_decoded(
            tv, tf, np.full((len(tv), 3), 0.5), cams, np.tile([1.0] + [0.0] * 8, (12, 1)), 1.0
        )
    ]
    scan = photo_consistent_offset(tv * 0.99, tf, cams, flat)
    assert not scan.applied and scan.offset == 0.0
    assert "usable windows" in scan.reason


def test_a_barely_textured_surface_gets_no_offset(sphere_views):
    """Texture 100x fainter than the noise: the cost is nearly flat and its minimum is chance.

    Without the curvature rule the scan would move the TRUE sphere by about a pixel; with it, nothing.
    """
    tv, tf, cams, _ = sphere_views
    faint = 0.5 + 0.005 * (_textured(tv) - 0.5)
    noisy = [
        observation_from_decoded(f)
        for f in render_decoded(
            tv, tf, faint, cams, np.tile([1.0] + [0.0] * 8, (12, 1)), 1.0, dop_scale=0.0, intensity_noise=0.01
        )
    ]
    unguarded = photo_consistent_offset(tv, tf, cams, noisy, min_cos=0.7, min_curvature=0.0)
    assert unguarded.applied and abs(unguarded.offset) > 0.5 * _gsd(cams, tv), unguarded.to_dict()
    scan = photo_consistent_offset(tv, tf, cams, noisy, min_cos=0.7)
    assert scan.pixels >= 500 and 0 < np.argmin(scan.costs) < len(scan.costs) - 1  # the contrast refuses it
    assert not scan.applied and scan.offset == 0.0 and "too little texture" in scan.reason, scan.to_dict()
    # the textured sphere's cost curves far more than the 1% per px^2 asked for; asked for more, it is
    # refused; and the curvature does not depend on the scan's range (the refinement's later scans are
    # narrower: a rise to the ends refused them wrongly, README)
    tv, tf, cams, obs = sphere_views
    curvatures = {}
    for max_px in (1.5, 0.75):
        scan = photo_consistent_offset(tv * 0.99, tf, cams, obs, min_cos=0.7, max_px=max_px)
        assert scan.applied, scan.to_dict()
        x, c = scan.offsets_px, scan.costs
        curvatures[max_px] = np.polyfit(x, c, 2)[0] / c.min()
    assert curvatures[1.5] > 0.02, curvatures
    assert curvatures[0.75] == pytest.approx(curvatures[1.5], rel=0.3), curvatures
    scan = photo_consistent_offset(tv * 0.99, tf, cams, obs, min_cos=0.7, min_curvature=10.0)
    assert not scan.applied and "too little texture" in scan.reason


def test_neighbours_are_the_nearest_views_apart_from_the_view_itself():
    cams = ring_cameras(12, 64)
    nb = neighbour_views(cams, 2)
    assert all(i not in n and len(n) == 2 for i, n in enumerate(nb))
    # on a ring alternately above and below the equator, view i's nearest are i - 1 and i + 1
    assert sorted(nb[5]) == [4, 6]


def test_bad_options_are_refused(sphere_views):
    tv, tf, cams, obs = sphere_views
    with pytest.raises(ConfigError, match="min_curvature"):
        photo_consistent_offset(tv, tf, cams, obs, min_curvature=-0.1)
    with pytest.raises(ConfigError, match="odd"):
        photo_consistent_offset(tv, tf, cams, obs, window=4)
    with pytest.raises(ConfigError, match="observations"):
        photo_consistent_offset(tv, tf, cams, obs[:-1])
    with pytest.raises(ConfigError, match="step_px"):
        photo_consistent_offset(tv, tf, cams, obs, step_px=2.0, max_px=1.0)


@pytest.mark.parametrize("mode", ["off", "start", "stages"])
def test_the_refinement_scans_where_it_is_told_and_keeps_the_scans(sphere_views, mode):
    from refine_scene import accuracy

    from pmvir.config import RefineOptions
    from pmvir.geometry.visibility import vertex_visibility
    from pmvir.refine import refine_surface

    tv, tf, cams, obs = sphere_views
    start = tv * (1.0 - 0.6 * _gsd(cams, tv))  # shrunk by 0.6 px
    opts = RefineOptions(
        device="cpu",
        solver={"max_iterations": 1},
        pol={"enabled": False},
        offset_scan={"mode": mode, "min_cos": 0.7},
    )
    res = refine_surface(start, tf, cams, obs, vertex_visibility(start, tf, cams), options=opts)
    assert len(res.offset_scans) == {"off": 0, "start": 1, "stages": 4}[mode]
    assert all(scan.applied for scan in res.offset_scans)
    assert "offset_scan" in res.timings
    if mode != "off":  # one refinement iteration per stage hardly moves it: the scan brings it back
        assert accuracy(res.vertices, tv, tf) < 0.3 * accuracy(start, tv, tf)
    if mode == "stages":  # the first scan found the shrink; after it, nothing is left to find
        assert abs(res.offset_scans[0].offset - 0.6 * _gsd(cams, tv)) < 0.1 * _gsd(cams, tv)
        assert all(abs(scan.offset) < 0.1 * _gsd(cams, tv) for scan in res.offset_scans[1:])


def test_deblurring_takes_the_blur_induced_inward_bias_out(sphere_views):
    """Image blur moves the scan's minimum inward (README: demosaicing's blur, about 1.6 px); scanning again
    on images blurred once more and extrapolating to no blur (deblur_px) removes most of it. Measured at the
    TRUE sphere with its images blurred by 1.5 px: -0.10 px plain, -0.04 px deblurred."""
    tv, tf, cams, obs = sphere_views
    gsd = _gsd(cams, tv)
    blurred = [
        Observation(intensity=cv2.GaussianBlur(o.intensity, (0, 0), 1.5), aop=o.aop, dop=o.dop, valid=o.valid)
        for o in obs
    ]
    plain = photo_consistent_offset(tv, tf, cams, blurred, min_cos=0.7)
    deblurred = photo_consistent_offset(tv, tf, cams, blurred, min_cos=0.7, deblur_px=1.5)
    assert plain.applied and plain.offset < -0.07 * gsd, plain.to_dict()
    assert deblurred.applied and abs(deblurred.offset) < 0.5 * abs(plain.offset), deblurred.to_dict()
    assert deblurred.blurred_offset_px is not None and deblurred.blurred_offset_px < plain.offset / gsd
    assert "blurred_scan_cost" in deblurred.to_dict() and "blurred_scan_cost" not in plain.to_dict()
    with pytest.raises(ConfigError, match="deblur_px"):
        photo_consistent_offset(tv, tf, cams, obs, deblur_px=-1.0)
