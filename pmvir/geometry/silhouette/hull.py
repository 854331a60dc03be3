"""The volume the object can occupy, from known cameras alone: the masks' visual hull, or the common frustum.

With every pose and intrinsics known, dense stereo needs no sparse points to
bound its depth search: the object lies inside every view's mask (the visual
hull, Laurentini 1994), or, without masks, inside the cameras' common field of
view. :func:`carve_hull` samples that volume on a voxel grid:

1. **Seed box**: the point nearest (least squares) to every optical axis, and
   a half-size that covers, at that point's depth in each view, the mask's
   extent in pixels (without a mask: the image's) times 1.5.
2. **Carving**: a grid point is kept when it lies in front of every camera,
   projects inside the images of at least half of the views (the rig frames
   the object), and in each view where it projects inside the image it lands
   inside that view's mask (dilated by ``_MASK_TOLERANCE_PX``). Without masks
   a point must project inside every image (the common frustum).
3. **Tightening**: the grid is laid again over the bounding box of what was
   kept (plus two cells), and carved again, at the same resolution.

:class:`Hull` gives each view's depth range (:meth:`Hull.depth_range`) and
the hull's surface cells (cells with an empty face neighbour), which stand in
for sparse points in the choice of stereo neighbours.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from pmvir.camera import Camera
from pmvir.errors import ReconstructionError
from pmvir.geometry.projection import project_points

#: Masks are grown by this many pixels before carving (masks of mixed silhouette pixels, pose noise).
_MASK_TOLERANCE_PX = 2

#: The seed box covers the masks' extent times this.
_SEED_MARGIN = 1.5


@dataclass(frozen=True)
class Hull:
    """Grid points inside the visual hull (or the common frustum).

    Attributes:
        points: (P, 3) float64 centres of the kept cells, world units.
        surface: (S, 3) float64 centres of the kept cells with an empty face neighbour.
        cell: the cell side, world units.
        from_masks: True when masks carved it (a visual hull), False for the common frustum.
    """

    points: np.ndarray
    surface: np.ndarray
    cell: float
    from_masks: bool

    @property
    def diagonal(self) -> float:
        """Bounding-box diagonal of the kept cells, world units."""
        return float(np.linalg.norm(self.points.max(0) - self.points.min(0))) + self.cell

    def depth_range(self, camera: Camera) -> tuple[float, float] | None:
        """(near, far) camera depths of the kept cells in front of ``camera``, widened by a cell
        diagonal; None when no cell projects into its image."""
        uv, z = project_points(camera, self.points)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0)
        inside &= uv[:, 1] < camera.height
        if not inside.any():
            return None
        pad = float(np.sqrt(3.0)) * self.cell
        near = max(float(z[inside].min()) - pad, 1e-3 * float(z[inside].max()))
        return near, float(z[inside].max()) + pad


def _axes_point(cameras: Sequence[Camera]) -> np.ndarray:
    """Least-squares point nearest to every optical axis, (3,)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = cam.R[2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    return np.linalg.lstsq(A + 1e-9 * np.eye(3), b, rcond=None)[0]


def _seed_half_size(
    centre: np.ndarray, cameras: Sequence[Camera], masks: Sequence[np.ndarray | None]
) -> float:
    """Half-size of a cube around ``centre`` that holds, in every view, the mask's (or image's) extent."""
    half = 0.0
    for cam, mask in zip(cameras, masks, strict=True):
        uv, z = project_points(cam, centre[None])
        if z[0] <= 0:
            continue
        if mask is not None and mask.any():
            rows, cols = np.nonzero(mask)
            px = np.hypot(cols + 0.5 - uv[0, 0], rows + 0.5 - uv[0, 1]).max()
        else:
            px = np.hypot(cam.width, cam.height) / 2.0
        half = max(half, float(px) * float(z[0]) / float(min(cam.K[0, 0], cam.K[1, 1])))
    return _SEED_MARGIN * half


def _carve(
    lo: np.ndarray,
    hi: np.ndarray,
    resolution: int,
    cameras: Sequence[Camera],
    grown: Sequence[np.ndarray | None],
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray]:
    """Carve a grid over [lo, hi]; returns kept mask (n, n, n), grid axes (3, n), cell, removed-per-view."""
    cell = float((hi - lo).max()) / resolution
    axes = [lo[k] + cell * (np.arange(resolution) + 0.5) for k in range(3)]
    X, Y, Z = np.meshgrid(*axes, indexing="ij")
    pts = np.stack([X.ravel(), Y.ravel(), Z.ravel()], 1)
    keep = np.ones(len(pts), bool)
    inside_all = np.ones(len(pts), bool)
    seen = np.zeros(len(pts), np.int64)
    removed = np.zeros(len(cameras), np.int64)
    with_masks = any(m is not None for m in grown)
    for k, (cam, mask) in enumerate(zip(cameras, grown, strict=True)):
        uv, z = project_points(cam, pts)
        col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (z > 0) & (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        keep &= z > 0
        inside_all &= inside
        seen += inside
        if mask is not None:
            ok = np.ones(len(pts), bool)
            ok[inside] = mask[row[inside], col[inside]]
            removed[k] = int((keep & ~ok).sum())
            keep &= ok
    if with_masks:
        keep &= 2 * seen >= len(cameras)  # the rig frames the object: most views see every part of it
    else:
        keep &= inside_all
    return keep.reshape(X.shape), np.stack(axes), cell, removed


def carve_hull(
    cameras: Sequence[Camera],
    masks: Sequence[np.ndarray | None] | None = None,
    *,
    names: Sequence[str] | None = None,
    resolution: int = 64,
) -> Hull:
    """The visual hull of the masks, or without masks the common frustum, on a voxel grid (module docstring).

    Args:
        cameras: the V posed cameras (at least 2).
        masks: per view None or an (H, W) bool object mask on the camera's grid.
        names: per view a name for messages (default: the indices).
        resolution: grid cells along the longest side of the box.

    Returns:
        The :class:`Hull`.

    Raises:
        ReconstructionError: nothing is left: the masks (or fields of view) do not share a volume;
            the message names the views whose masks removed most of it.
    """
    if len(cameras) < 2:
        raise ValueError(f"a hull needs at least 2 cameras, got {len(cameras)}")
    masks = list(masks) if masks is not None else [None] * len(cameras)
    if len(masks) != len(cameras):
        raise ValueError(f"{len(masks)} masks for {len(cameras)} cameras")
    names = list(names) if names is not None else [str(i) for i in range(len(cameras))]
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * _MASK_TOLERANCE_PX + 1,) * 2)
    grown = [None if m is None else cv2.dilate(np.asarray(m, np.uint8), kernel).astype(bool) for m in masks]
    centre = _axes_point(cameras)
    half = _seed_half_size(centre, cameras, masks)
    lo, hi = centre - half, centre + half
    for _ in range(2):
        kept, axes, cell, removed = _carve(lo, hi, resolution, cameras, grown)
        if not kept.any():
            worst = [names[k] for k in np.argsort(-removed)[:5] if removed[k] > 0]
            cause = (
                f"the views' masks share no volume (views whose masks removed most of it: {', '.join(worst)}); "
                "are the poses, intrinsics and masks of one capture?"
                if any(m is not None for m in masks)
                else "the views' fields of view share no volume; do the cameras look at one object?"
            )
            raise ReconstructionError(f"cannot bound the object from the known cameras: {cause}")
        idx = np.argwhere(kept)
        lo = np.array([axes[k][idx[:, k].min()] for k in range(3)]) - 2.5 * cell
        hi = np.array([axes[k][idx[:, k].max()] for k in range(3)]) + 2.5 * cell
    padded = np.pad(kept, 1)
    interior = kept.copy()
    for k in range(3):
        for s in (-1, 1):
            interior &= np.roll(padded, s, axis=k)[1:-1, 1:-1, 1:-1]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1)
    return Hull(
        points=grid[kept].astype(np.float64),
        surface=grid[kept & ~interior].astype(np.float64),
        cell=cell,
        from_masks=any(m is not None for m in masks),
    )
