"""Joining SfM models (pmvir.geometry.sfm_join): the similarity between two models' frames from common views."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from pmvir.camera import Camera
from pmvir.geometry.sfm_join import similarity_from_shared, transform_camera

K = np.array([[500.0, 0.0, 160.0], [0.0, 500.0, 120.0], [0.0, 0.0, 1.0]])


def _ring(n: int = 6, radius: float = 3.0) -> dict[int, Camera]:
    """n cameras on a circle, looking at the origin."""
    cameras = {}
    for i in range(n):
        a = 2 * np.pi * i / n
        centre = radius * np.array([np.cos(a), 0.3, np.sin(a)])
        z = -centre / np.linalg.norm(centre)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        cameras[i] = Camera(K=K, R=R, t=-R @ centre, width=320, height=240)
    return cameras


def _moved(cameras: dict[int, Camera], s: float, R: np.ndarray, t: np.ndarray) -> dict[int, Camera]:
    return {i: transform_camera(c, s, R, t) for i, c in cameras.items()}


def test_transform_camera_moves_the_centre_and_keeps_projections() -> None:
    cam = _ring()[1]
    s, R, t = 2.5, Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), np.array([1.0, -2.0, 0.5])
    moved = transform_camera(cam, s, R, t)
    assert np.allclose(moved.center, s * R @ cam.center + t)
    X = np.array([[0.1, 0.2, -0.1], [0.0, -0.3, 0.2]])
    uv, _ = cam.project(X)
    uv_moved, _ = moved.project(s * X @ R.T + t)
    assert np.allclose(uv, uv_moved)


def test_similarity_from_two_or_more_common_views_is_recovered() -> None:
    base = _ring()
    s, R, t = 0.4, Rotation.from_rotvec([-0.7, 0.1, 1.2]).as_matrix(), np.array([0.3, 2.0, -1.0])
    # other's frame: x_other = (R^T (x_base - t)) / s, so x_base = s R x_other + t
    R_inv = R.T
    other = _moved({i: base[i] for i in (2, 3, 4, 5)}, 1.0 / s, R_inv, -R_inv @ t / s)
    found = similarity_from_shared({i: base[i] for i in (0, 1, 2, 3)}, {i: other[i] for i in (2, 3, 4, 5)})
    assert found is not None
    s_found, R_found, t_found = found
    assert np.isclose(s_found, s) and np.allclose(R_found, R, atol=1e-9) and np.allclose(t_found, t)
    assert np.allclose(transform_camera(other[5], *found).center, base[5].center)


def test_one_common_view_or_disagreeing_views_do_not_join() -> None:
    base = _ring()
    assert similarity_from_shared({0: base[0], 1: base[1]}, {1: base[1], 2: base[2]}) is None
    # the common views' rotations disagree by 10 degrees (one pose wrong): no similarity
    wrong = base[3]
    tilted = Rotation.from_rotvec([0.0, np.radians(10.0), 0.0]).as_matrix() @ wrong.R
    bad = Camera(K=K, R=tilted, t=-tilted @ wrong.center, width=320, height=240)
    assert similarity_from_shared(base, {2: base[2], 3: bad}) is None
    # rotations agree but one centre is off by a fifth of the spread
    off = transform_camera(base[3], 1.0, np.eye(3), np.array([0.0, 1.2, 0.0]))
    assert similarity_from_shared(base, {2: base[2], 3: base[3], 4: off}) is None
    assert similarity_from_shared(base, {2: base[2], 3: base[3], 4: base[4]}) is not None
