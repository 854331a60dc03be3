"""Hold a surface inside the masks' visual hull: vertices that project outside a mask move inward.

Every point of the object projects inside every view's mask (the visual hull,
Laurentini 1994). The initial surface and the refinement do not ensure it: the
Poisson surface rounds thin parts out past their silhouettes, and the
refinement's terms see normals, not position, while its offset scans move the
whole mesh outward where its bulk lies inside. On the Mitsuba dragon at
308x256, 12% of the initial surface's vertices project more than 0.5 px
outside some mask, and they lie a mean 1.6 px outside the true surface
(README, "Held inside the silhouettes").

:func:`fit_inside_hull` moves each such vertex inward along its normal, in
small steps, until it projects at most ``tolerance_px`` outside every mask or
has moved ``max_move_px`` (in pixels of the ground sampling distance at the
vertex). A vertex inside every mask does not move, so the fit never pushes a
surface outward. The masks' boundaries are taken halfway between the last
object pixel and the first background pixel (:func:`mask_distance`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from pmvir.camera import Camera, sample_bilinear
from pmvir.errors import ConfigError, ShapeError
from pmvir.io.ply import vertex_normals


@dataclass(frozen=True)
class HullFit:
    """What :func:`fit_inside_hull` did.

    Attributes:
        vertices: (N, 3) float64 the vertices, those outside the hull moved inward.
        outside_before: vertices more than the tolerance outside some mask, before.
        outside_after: the same, after (those that reached ``max_move_px`` first).
        moved: vertices that moved.
        mean_move_px: their mean move in pixels of the ground sampling distance (0 when none moved).
        tolerance_px: the tolerance used.
    """

    vertices: np.ndarray
    outside_before: int
    outside_after: int
    moved: int
    mean_move_px: float
    tolerance_px: float

    def to_dict(self) -> dict[str, float | int]:
        return {
            "outside_before": self.outside_before,
            "outside_after": self.outside_after,
            "moved": self.moved,
            "mean_move_px": round(self.mean_move_px, 4),
            "tolerance_px": self.tolerance_px,
        }


def mask_distance(mask: np.ndarray) -> np.ndarray:
    """(H, W) float64 signed distance to the mask's boundary in pixels: positive inside, negative outside.

    The boundary lies halfway between an object pixel's centre and its background neighbour's, so
    a pixel next to the boundary is +0.5 (inside) or -0.5 (outside). A mask without background is
    inside everywhere (+inf); one without object pixels, outside everywhere (-inf).
    """
    m = np.asarray(mask, dtype=bool)
    if m.ndim != 2:
        raise ShapeError(f"expected an (H, W) mask, got shape {m.shape}")
    if m.all():
        return np.full(m.shape, np.inf)
    if not m.any():
        return np.full(m.shape, -np.inf)
    m8 = m.astype(np.uint8)
    inside = cv2.distanceTransform(m8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    outside = cv2.distanceTransform(1 - m8, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    return np.where(m, inside - 0.5, 0.5 - outside).astype(np.float64)


def hull_depth(
    vertices: np.ndarray, cameras: Sequence[Camera], distances: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex the least mask distance over the views (pixels; negative: outside that mask) and
    the ground sampling distance (world units per pixel) in the view that gives it.

    Views the vertex lies behind do not count; a vertex behind every view gets +inf.
    """
    x = np.asarray(vertices, dtype=np.float64)
    least = np.full(len(x), np.inf)
    gsd = np.zeros(len(x))
    for cam, dist in zip(cameras, distances, strict=True):
        uv, z = cam.project(x)
        d = np.where(z > 0, sample_bilinear(dist, uv[:, 0], uv[:, 1]), np.inf)
        lower = d < least
        least = np.where(lower, d, least)
        gsd = np.where(lower, np.maximum(z, 0.0) / cam.K[0, 0], gsd)
    return least, gsd


def fit_inside_hull(
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    masks: Sequence[np.ndarray | None],
    *,
    tolerance_px: float = 0.5,
    max_move_px: float = 3.0,
    iterations: int = 20,
) -> HullFit:
    """Move the vertices that project more than ``tolerance_px`` outside some mask inward along their
    normals (module docstring).

    Args:
        vertices, faces: the mesh (faces counter-clockwise seen from outside).
        cameras, masks: the registered views and their object masks (None, or a mask without object
            or without background pixels: that view does not count).
        tolerance_px: how far outside a mask (pixels) a vertex may project; masks and poses are
            good to about half a pixel.
        max_move_px: the most a vertex moves, in pixels of its ground sampling distance.
        iterations: steps; each moves a vertex by half its remaining violation (at most 1 px), along
            the current normals.

    Returns:
        :class:`HullFit`.

    Raises:
        ConfigError: negative tolerance or move, or mismatched inputs.
    """
    if tolerance_px < 0.0 or max_move_px < 0.0:
        raise ConfigError(f"tolerance_px and max_move_px must be >= 0, got {tolerance_px} and {max_move_px}")
    if len(cameras) != len(masks):
        raise ConfigError(f"{len(cameras)} cameras but {len(masks)} masks")
    v0 = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    # a mask without object or without background pixels draws no silhouette (an empty one is a
    # failed segmentation, not a view that rules the whole surface out): it does not count
    pairs = [
        (c, mask_distance(m))
        for c, m in zip(cameras, masks, strict=True)
        if m is not None and np.any(m) and not np.all(m)
    ]
    if not pairs or len(v0) == 0:
        return HullFit(v0.copy(), 0, 0, 0, 0.0, tolerance_px)
    cams = [c for c, _ in pairs]
    dists = [d for _, d in pairs]
    least, _ = hull_depth(v0, cams, dists)
    # only these can move (a vertex's violation depends on its own position alone)
    idx = np.flatnonzero(least < -tolerance_px)
    x = v0.copy()
    moved_px = np.zeros(len(idx))
    for _ in range(iterations):
        least_i, gsd = hull_depth(x[idx], cams, dists)
        out = (least_i < -tolerance_px) & (moved_px < max_move_px) & (gsd > 0)
        if not out.any():
            break
        step_px = np.minimum(np.minimum(0.5 * (-least_i[out] - tolerance_px), 1.0), max_move_px - moved_px[out])
        step_px = np.maximum(step_px, 0.01)  # halving toward the tolerance converges slowly at the end
        normals = vertex_normals(x, f).astype(np.float64)[idx[out]]
        x[idx[out]] -= (step_px * gsd[out])[:, None] * normals
        moved_px[out] += step_px
    least_i, _ = hull_depth(x[idx], cams, dists)
    moved = moved_px > 0
    return HullFit(
        vertices=x,
        outside_before=len(idx),
        outside_after=int((least_i < -tolerance_px).sum()),
        moved=int(moved.sum()),
        mean_move_px=float(moved_px[moved].mean()) if moved.any() else 0.0,
        tolerance_px=tolerance_px,
    )
