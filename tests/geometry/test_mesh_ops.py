"""The vectorised mesh helpers against their one-by-one definitions."""

from __future__ import annotations

import numpy as np

from pmvir.geometry.mesh_ops import face_normals, grouped_medians, vertex_normals


def test_grouped_medians_equal_numpy_median_per_run() -> None:
    rng = np.random.default_rng(1)
    groups = np.sort(rng.integers(0, 300, 4000))  # runs of odd and even length, some of one
    values = rng.normal(size=len(groups))
    starts = np.flatnonzero(np.r_[True, groups[1:] != groups[:-1]])
    expected = [np.median(run) for run in np.split(values, starts[1:])]
    assert np.array_equal(grouped_medians(values, starts), expected)


def test_vertex_normals_are_the_normalised_sum_of_adjacent_face_cross_products() -> None:
    rng = np.random.default_rng(2)
    v = rng.normal(size=(200, 3))
    f = rng.integers(0, 200, (500, 3))
    fn = face_normals(v, f, normalize=False)
    expected = np.zeros_like(v)
    for face, n in zip(f, fn, strict=True):
        for i in face:
            expected[i] += n
    used = np.linalg.norm(expected, axis=1) > 0
    expected[used] /= np.linalg.norm(expected[used], axis=1, keepdims=True)
    assert np.allclose(vertex_normals(v, f), expected, atol=1e-12)


def test_ray_directions_point_back_through_their_pixels() -> None:
    from pmvir.synth.rig import ring_cameras

    cam = ring_cameras(3, 64, 48, object_radius=1.0)[1]
    uv = np.random.default_rng(0).uniform([0.0, 0.0], [64.0, 48.0], size=(50, 2))
    d = cam.ray_directions(uv)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    back, z = cam.project(cam.center + 2.5 * d)
    assert np.all(z > 0)
    np.testing.assert_allclose(back, uv, atol=1e-9)
    _, grid = cam.pixel_rays()  # every pixel centre
    np.testing.assert_allclose(grid[7, 11], cam.ray_directions(np.array([11.5, 7.5])), atol=1e-15)
