"""Pinhole cameras with pmvir's (COLMAP's) conventions.

* ``cam_from_world``: ``x_cam = R @ x_world + t``, OpenCV axes (x right, y down,
  z forward).
* Pixel coordinates (u, v): the top-left corner of the top-left pixel is (0, 0),
  so the centre of the pixel at array index [row, col] is (col + 0.5, row + 0.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike


@dataclass(frozen=True)
class Camera:
    """One view's intrinsics and pose.

    Attributes:
        K: (3, 3) float64 intrinsic matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]].
        R: (3, 3) float64 rotation of cam_from_world.
        t: (3,) float64 translation of cam_from_world.
        width, height: image size in pixels.
    """

    K: np.ndarray
    R: np.ndarray
    t: np.ndarray
    width: int
    height: int

    def __post_init__(self) -> None:
        object.__setattr__(self, "K", np.asarray(self.K, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "R", np.asarray(self.R, dtype=np.float64).reshape(3, 3))
        object.__setattr__(self, "t", np.asarray(self.t, dtype=np.float64).reshape(3))

    @classmethod
    def from_intrinsics(
        cls, fx: float, fy: float, cx: float, cy: float, width: int, height: int, R: np.ndarray, t: np.ndarray
    ) -> Camera:
        K = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
        return cls(K=K, R=R, t=t, width=width, height=height)

    @property
    def center(self) -> np.ndarray:
        """Camera centre in world coordinates, (3,)."""
        return -self.R.T @ self.t

    def world_to_cam(self, points: np.ndarray) -> np.ndarray:
        """(N, 3) world points to (N, 3) camera-frame points."""
        return np.asarray(points, dtype=np.float64) @ self.R.T + self.t

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points.

        Returns:
            uv: (N, 2) pixel coordinates (COLMAP convention), float64.
            depth: (N,) camera-frame z; points with depth <= 0 are behind the camera.
        """
        pc = self.world_to_cam(points)
        z = pc[:, 2]
        zs = np.where(np.abs(z) < 1e-12, 1e-12, z)
        u = self.K[0, 0] * pc[:, 0] / zs + self.K[0, 1] * pc[:, 1] / zs + self.K[0, 2]
        v = self.K[1, 1] * pc[:, 1] / zs + self.K[1, 2]
        return np.stack([u, v], axis=1), z

    def pixel_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """World-space rays through every pixel centre.

        Returns:
            origins: (H, W, 3) all equal to the camera centre.
            directions: (H, W, 3) unit directions.
        """
        cols, rows = np.meshgrid(np.arange(self.width) + 0.5, np.arange(self.height) + 0.5)
        d_world = self.ray_directions(np.stack([cols, rows], axis=-1))
        origins = np.broadcast_to(self.center, d_world.shape).copy()
        return origins, d_world

    def ray_directions(self, uv: np.ndarray) -> np.ndarray:
        """(..., 3) unit world-space directions of the rays through pixel positions ``uv`` (..., 2)
        (COLMAP convention: (0.5, 0.5) is the first pixel's centre)."""
        uv = np.asarray(uv, dtype=np.float64)
        pix = np.concatenate([uv, np.ones_like(uv[..., :1])], axis=-1)
        d_world = pix @ np.linalg.inv(self.K).T @ self.R  # R.T @ (K^-1 p) for each row vector
        d_world /= np.linalg.norm(d_world, axis=-1, keepdims=True)
        return d_world


def look_at(
    center: np.ndarray, target: np.ndarray, up: ArrayLike = (0.0, 0.0, 1.0)
) -> tuple[np.ndarray, np.ndarray]:
    """cam_from_world (R, t) of a camera at ``center`` looking at ``target``, world ``up`` shown up.

    Returns:
        R: (3, 3), t: (3,).
    """
    center = np.asarray(center, dtype=np.float64)
    z = np.asarray(target, dtype=np.float64) - center
    z /= np.linalg.norm(z)
    x = np.cross(z, np.asarray(up, dtype=np.float64))  # image x right (forward x up), y down
    if np.linalg.norm(x) < 1e-9:  # looking along up: pick any perpendicular
        x = np.cross(z, np.array([1.0, 0.0, 0.0]))
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    R = np.stack([x, y, z], axis=0)
    return R, -R @ center


def sample_bilinear(image: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Bilinear samples of an (H, W) or (H, W, C) image at pixel coordinates (COLMAP convention: pixel
    [r, c] centred at (c + 0.5, r + 0.5)), clamped to the image (a point beyond the border reads the
    border): (N,) or (N, C), every channel from one gather of its four neighbours.

    >>> image = np.array([[0.0, 1.0], [2.0, 3.0]])
    >>> sample_bilinear(image, np.array([1.0, 0.0]), np.array([1.0, 5.0]))
    array([1.5, 2. ])
    >>> sample_bilinear(np.dstack([image, 10 * image]), np.array([1.0, 0.0]), np.array([1.0, 5.0]))
    array([[ 1.5, 15. ],
           [ 2. , 20. ]])
    """
    h, w = image.shape[:2]
    x = np.clip(u - 0.5, 0.0, w - 1.0)
    y = np.clip(v - 0.5, 0.0, h - 1.0)
    x0 = np.minimum(np.floor(x).astype(np.int64), max(w - 2, 0))
    y0 = np.minimum(np.floor(y).astype(np.int64), max(h - 2, 0))
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = x - x0, y - y0
    if image.ndim == 3:
        fx, fy = fx[:, None], fy[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy
