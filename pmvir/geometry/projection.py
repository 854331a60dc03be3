"""Pinhole projection of world points into a :class:`~pmvir.camera.Camera` (COLMAP pixel convention).

Two forms of the same model as :meth:`pmvir.camera.Camera.project`:
:func:`project_points` (rows of points, one BLAS product: fastest for large N) and
:func:`project_columns` (points stored as contiguous coordinate rows, no BLAS
threads). They round differently in the last bits; each caller keeps the one it uses.
"""

from __future__ import annotations

import numpy as np

from pmvir.camera import Camera


def project_points(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``camera.project`` of (N, 3) world points as one (3, 3) x (3, N) BLAS product (faster for large N).

    Returns:
        uv (N, 2) float64 pixel coordinates (COLMAP convention) and depth (N,) float64.
    """
    p_t = np.ascontiguousarray(
        np.asarray(points, np.float64).reshape(-1, 3).T
    )  # BLAS is slow on the F-order view
    h = (camera.K @ camera.R) @ p_t + (camera.K @ camera.t)[:, None]
    z = h[2]
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    return np.stack([h[0] / zs, h[1] / zs], axis=1), z


def project_columns(v_t: np.ndarray, cam: Camera) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pinhole projection of points stored as contiguous columns (fast, no BLAS threads).

    Same model as :meth:`pmvir.camera.Camera.project` (COLMAP pixel convention).

    Args:
        v_t: (3, N) float64 world points, one coordinate per row.
        cam: the camera.

    Returns:
        u, v: (N,) float64 pixel coordinates; depth: (N,) camera-frame z.
    """
    R, t, K = cam.R, cam.t, cam.K
    x, y, z = (R[i, 0] * v_t[0] + R[i, 1] * v_t[1] + R[i, 2] * v_t[2] + t[i] for i in range(3))
    zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
    xn, yn = x / zs, y / zs
    return K[0, 0] * xn + K[0, 1] * yn + K[0, 2], K[1, 1] * yn + K[1, 2], z
