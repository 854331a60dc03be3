"""Cross-view consistency filtering and fusion of depth maps into an oriented point cloud.

A depth of reference view r at pixel x is *consistent* with view s when the
point it back-projects to, projected into s, lands where s has a depth whose
own back-projection projects back into r within ``max_reproj_px`` of x, and
the two depths of the point seen from s differ by at most ``max_rel_depth``
(relative). A depth is kept when at least ``min_consistent`` views agree
(COLMAP's geometric filter in spirit); the fused point is the mean of its own
back-projection and the consistent views' back-projections, which averages
the noise of independent depth maps.

Agreement alone lets through what several views match alike but is not the
surface: on a glossy object the reflection of the surroundings is a virtual
image behind the surface, consistent between nearby views, and fused it makes
clusters of points inside the object that the initial surface follows into a
dent. The *occlusion test* (Merrell et al. 2007's free-space reasoning in
spirit) counts, for each depth of a view, the views whose depths land on the
same pixel in front of it by more than the relative margin: they see a surface
where this view's depth says free space. A depth that at least as many views
see through as agree with it, and more than ``max_occluding``, is dropped. The
test also drops some depths of surfaces seen at grazing angles, where a depth
projected a pixel off lands in front; those are the least accurate ones.

Normals are estimated on the fused cloud (Open3D, local PCA over the nearest
neighbours) and turned towards the camera that produced each point.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pmvir.camera import Camera
from pmvir.geometry.mvs.sweep import DepthMap
from pmvir.geometry.projection import project_points

_EPS = 1e-12


@dataclass(frozen=True)
class DensePoints:
    """A fused, oriented point cloud.

    Attributes:
        points: (P, 3) float64 world positions.
        normals: (P, 3) float64 unit normals, facing the camera that saw the point.
        views: (P,) int64 index of the reference view each point came from.
        consistent: (P,) int64 number of other views that agreed with it.
    """

    points: np.ndarray
    normals: np.ndarray
    views: np.ndarray
    consistent: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def backproject(camera: Camera, depth: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """World points of pixels [rows, cols] at camera-frame depths ``depth`` (all (N,)); (N, 3) float64."""
    d = np.asarray(depth, np.float64)
    pix = np.stack(
        [(np.asarray(cols, np.float64) + 0.5) * d, (np.asarray(rows, np.float64) + 0.5) * d, d]
    )  # (3, N)
    cam_pts = np.linalg.inv(camera.K) @ pix - camera.t[:, None]  # contiguous (3, N): BLAS-friendly
    return np.ascontiguousarray((camera.R.T @ cam_pts).T)


def depth_at(dm: DepthMap, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``points`` projected into ``dm``: their depth in its camera, and the pixel they land on (rows, cols,
    clipped) with its depth (0 where none, or where a point falls outside the image or behind the camera)."""
    uv, z = project_points(dm.camera, points)
    h, w = dm.depth.shape
    cols = np.floor(uv[:, 0]).astype(np.int64)
    rows = np.floor(uv[:, 1]).astype(np.int64)
    inside = (z > 0) & (cols >= 0) & (cols < w) & (rows >= 0) & (rows < h)
    rows_c, cols_c = np.clip(rows, 0, h - 1), np.clip(cols, 0, w - 1)
    d = np.where(inside, dm.depth[rows_c, cols_c], 0.0)
    return z, rows_c, cols_c, d


def _depth_points(dm: DepthMap) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The pixels of ``dm`` with a depth, (N,) rows and cols, and their (N, 3) float64 world points."""
    rows, cols = np.nonzero(dm.valid)
    d = dm.depth[rows, cols].astype(np.float64)
    return rows, cols, backproject(dm.camera, d, rows.astype(np.float64), cols.astype(np.float64))


def filter_and_fuse(
    depth_maps: Sequence[DepthMap | None],
    neighbours: Sequence[Sequence[int]],
    *,
    max_reproj_px: float = 1.0,
    max_rel_depth: float = 0.01,
    min_consistent: int = 2,
    max_occluding: int | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Geometric consistency filter, occlusion test (module docstring) and point averaging.

    Args:
        depth_maps: per view a DepthMap or None (view not used).
        neighbours: per view the views to check it against.
        max_reproj_px: largest forward-backward reprojection error, pixels of the reference grid.
        max_rel_depth: largest relative depth difference seen from the other view; also the margin
            by which another view's depth must lie in front of a depth to occlude it.
        min_consistent: least number of agreeing views for a depth to be kept.
        max_occluding: when given, a depth is dropped where more than this many views that share a
            neighbour relation with its view (and at least as many as agree with it) see a surface
            in front of it along its ray; None: no occlusion test.

    Returns:
        points (P, 3) float64, source view (P,) int64 and number of agreeing views (P,) int64.
    """
    occluding = None if max_occluding is None else occluding_views(depth_maps, neighbours, max_rel_depth)
    all_pts, all_views, all_counts = [], [], []
    for r, dm in enumerate(depth_maps):
        if dm is None or not dm.valid.any():
            continue
        rows, cols, X = _depth_points(dm)
        acc = X.copy()
        count = np.zeros(len(X), np.int64)
        for s in neighbours[r]:
            ds = depth_maps[s]
            if ds is None:
                continue
            z, rs, cs, zs = depth_at(ds, X)
            has = zs > 0
            Xs = backproject(ds.camera, np.where(has, zs, 1.0), rs.astype(np.float64), cs.astype(np.float64))
            uv_back, _ = project_points(dm.camera, Xs)
            err = np.hypot(uv_back[:, 0] - (cols + 0.5), uv_back[:, 1] - (rows + 0.5))
            ok = has & (err <= max_reproj_px) & (np.abs(z - zs) <= max_rel_depth * np.maximum(zs, _EPS))
            acc[ok] += Xs[ok]
            count += ok
        keep = count >= min_consistent
        if occluding is not None and max_occluding is not None:
            occ = occluding[r][rows, cols]
            keep &= ~((occ > max_occluding) & (occ >= count))
        all_pts.append(acc[keep] / (1.0 + count[keep, None]))
        all_views.append(np.full(int(keep.sum()), r, np.int64))
        all_counts.append(count[keep])
    if not all_pts:
        return np.zeros((0, 3)), np.zeros(0, np.int64), np.zeros(0, np.int64)
    return np.concatenate(all_pts), np.concatenate(all_views), np.concatenate(all_counts)


def occluding_views(
    depth_maps: Sequence[DepthMap | None], neighbours: Sequence[Sequence[int]], margin: float
) -> list[np.ndarray]:
    """Per view an (h, w) int16 count of the views whose depths lie in front of its own along its rays.

    Every depth of a view s is projected into each view r that is s's neighbour or has s as one;
    where the nearest of them landing on a pixel of r lies in front of r's depth there by more than
    ``margin`` (relative to r's depth), s sees a surface where r's depth says free space: one vote
    for that pixel. Views without a depth map get an empty (0, 0) array.
    """
    n = len(depth_maps)
    partners: list[set[int]] = [set() for _ in range(n)]
    for r in range(n):
        for s in neighbours[r]:
            partners[r].add(s)
            partners[s].add(r)
    votes = [np.zeros((0, 0) if dm is None else dm.depth.shape, np.int16) for dm in depth_maps]
    for s, ds in enumerate(depth_maps):
        if ds is None or not ds.valid.any():
            continue
        _, _, X = _depth_points(ds)
        for r in sorted(partners[s]):
            dr = depth_maps[r]
            if dr is None:
                continue
            z, rr, cr, zr = depth_at(dr, X)
            seen = zr > 0
            nearest = np.full(dr.depth.shape, np.inf)  # s's nearest depth per pixel of r
            np.minimum.at(nearest, (rr[seen], cr[seen]), z[seen])
            votes[r] += (dr.depth > 0) & (nearest < dr.depth * (1.0 - margin))
    return votes


def estimate_normals(
    points: np.ndarray, views: np.ndarray, cameras: Sequence[Camera | None], *, neighbours: int = 24
) -> np.ndarray:
    """Unit normals by local PCA (Open3D), each turned to face the camera of its view.

    Args:
        points: (P, 3) float64.
        views: (P,) int64 view index of each point.
        cameras: the cameras indexed by ``views``.
        neighbours: points in each PCA neighbourhood.

    Returns:
        (P, 3) float64 unit normals.
    """
    import open3d as o3d

    if len(points) == 0:
        return np.zeros((0, 3))
    centre = points.mean(0)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points - centre))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(knn=neighbours))
    n = np.asarray(pcd.normals).copy()
    centres = np.stack([np.zeros(3) if c is None else c.center for c in cameras])
    to_cam = centres[views] - points
    flip = (n * to_cam).sum(1) < 0
    n[flip] *= -1.0
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), _EPS)


def voxel_thin(points: np.ndarray, voxel: float) -> np.ndarray:
    """Indices (sorted) of the first point in each occupied cube of side ``voxel``."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    key = np.floor((points - points.min(0)) / voxel).astype(np.int64)
    _, first = np.unique(key, axis=0, return_index=True)
    return np.sort(first)


def fuse_depth_maps(
    depth_maps: Sequence[DepthMap | None],
    neighbours: Sequence[Sequence[int]],
    cameras: Sequence[Camera | None],
    *,
    max_reproj_px: float = 1.0,
    max_rel_depth: float = 0.01,
    min_consistent: int = 2,
    max_occluding: int | None = None,
    voxel: float | None = None,
) -> DensePoints:
    """Filter, fuse and orient: :func:`filter_and_fuse`, optional voxel thinning, :func:`estimate_normals`.

    Args:
        depth_maps, neighbours, max_reproj_px, max_rel_depth, min_consistent, max_occluding: see
            :func:`filter_and_fuse`.
        cameras: per view the camera (full resolution; only centres are used).
        voxel: when given, keep one point (the first) per cube of this side (world units).

    Returns:
        :class:`DensePoints`.
    """
    pts, views, counts = filter_and_fuse(
        depth_maps,
        neighbours,
        max_reproj_px=max_reproj_px,
        max_rel_depth=max_rel_depth,
        min_consistent=min_consistent,
        max_occluding=max_occluding,
    )
    if voxel is not None and len(pts):
        first = voxel_thin(pts, voxel)
        pts, views, counts = pts[first], views[first], counts[first]
    normals = estimate_normals(pts, views, cameras)
    return DensePoints(points=pts, normals=normals, views=views, consistent=counts)
