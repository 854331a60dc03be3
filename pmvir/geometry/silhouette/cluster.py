"""The object's dense points: strays left out, DBSCAN's clusters, the still backdrop, solid points and columns.

Steps 3 and 4 of :mod:`pmvir.geometry.silhouette.isolate`, and the points its masks are drawn from.
:func:`object_points` removes the support plane's points, the still backdrop of a turntable
(:func:`still_points`) and the strays, clusters the rest (Open3D's DBSCAN) and keeps the cluster
nearest to the look-at point with the clusters near it (or the points inside a given box).
:func:`solid_points` picks the points with dense neighbourhoods, and :func:`columns_below` adds
vertical columns under them down toward the plane: the underside the points miss.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import numpy as np
from scipy.spatial import cKDTree

from pmvir.camera import Camera
from pmvir.config.isolate import IsolateOptions
from pmvir.errors import ReconstructionError
from pmvir.geometry.projection import project_points
from pmvir.geometry.silhouette.hull import _axes_point
from pmvir.geometry.silhouette.support import far_support_plane, support_plane

if TYPE_CHECKING:
    pass

#: Clusters smaller than this share of the points left after the plane's removal are not candidates
#: for the object's first cluster (they may still join it, :func:`_merged`).
_MIN_CLUSTER_SHARE = 0.02
#: DBSCAN runs on at most this many points (a random subset); the rest take their nearest one's label.
_MAX_CLUSTER_POINTS = 60_000
#: A point with fewer neighbours than this share of the median count is not solid (:func:`solid_points`);
#: measured on a 12-view table scene: 9 (median) on points beside the object, 23 (5th percentile) on it.
_SOLID_SHARE = 0.4
#: A column below the object whose foot has the support's points within this many spacings of it ...
#: (stereo puts some of the support's depth beside an object's foot: with 4, a blob on a turntable,
#: 12 views of 320x256, lost its lower third, completeness 2.85e-2 against 1.42e-2 with 2)
_SEEN_FOOT = 2.0
#: ... reaches down this share of the object's height (or to the plane): on 36 views of 612x512 a
#: knot's initial surface had 5.2 % of its vertices farther than 2 % of the diagonal from it with
#: columns down to the plane, 0.15 % with 0.05 (0.25 % with 0.1); a mug's completeness, whose dark
#: foot stereo misses, 1.10e-2 with 0.05, 1.42e-2 without columns.
_COLUMN_SHARE = 0.05
#: The density filter before clustering (:func:`_dense_core`) repeats at most this many times ...
_CORE_ROUNDS = 4
#: ... keeping the points with at least this share of the upper quartile of neighbour counts ...
_CORE_SHARE = 0.3
#: ... while the median point spacing falls by more than this share per round.
_CORE_SETTLE = 0.1
#: A point is still backdrop when it lands on still pixels in at least this share of the views that see it.
_STILL_SHARE = 0.8
#: The still-backdrop test runs where still pixels cover at least this share of the images (a still camera).
_MIN_STILL_AREA = 0.1
#: Fewest views with images of one size for the still-backdrop test.
_MIN_STILL_VIEWS = 6
#: :func:`still_pixels` takes the median over the views this many image rows at a time.
_STILL_ROWS = 64
#: RANSAC's and the subsets' random seed (the same capture gives the same masks).
SEED = 0


def point_spacing(points: np.ndarray) -> float:
    """Median distance of a point to its 4th nearest neighbour (at most 20k points sampled)."""
    pts = np.asarray(points, np.float64)
    if len(pts) < 5:
        return 0.0
    sample = pts[np.random.default_rng(0).choice(len(pts), min(len(pts), 20_000), replace=False)]
    d, _ = cKDTree(pts).query(sample, k=5)
    return float(np.median(d[:, 4]))


def _clusters(points: np.ndarray, eps: float, seed: int) -> np.ndarray:
    """(P,) DBSCAN labels (-1: noise) of the points, on a subset of at most _MAX_CLUSTER_POINTS."""
    import open3d as o3d

    idx = np.arange(len(points))
    if len(points) > _MAX_CLUSTER_POINTS:
        idx = np.sort(np.random.default_rng(seed).choice(len(points), _MAX_CLUSTER_POINTS, replace=False))
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points[idx]))
    scale = np.sqrt(len(points) / len(idx))  # a thinner subset is farther apart
    sub = np.asarray(pcd.cluster_dbscan(eps=eps * scale, min_points=8), np.int64)
    if len(idx) == len(points):
        return sub
    _, nearest = cKDTree(points[idx]).query(points, k=1)
    return sub[nearest]


class ObjectPoints(NamedTuple):
    """What :func:`object_points` found.

    Attributes:
        keep: (P,) bool the object's points.
        plane: the support plane (unit normal up, offset) or None.
        look: (3,) the look-at point.
        counts: the points at each step.
        dense: (P,) bool those of ``keep`` that passed the stray filter (the others were taken back
            within the object's box); ``keep`` with a bounding box.
    """

    keep: np.ndarray
    plane: np.ndarray | None
    look: np.ndarray
    counts: dict[str, int]
    dense: np.ndarray


def object_points(
    points: np.ndarray,
    cameras: Sequence[Camera],
    *,
    settings: IsolateOptions,
    bbox: Sequence[float] | None = None,
    backdrop: np.ndarray | None = None,
) -> ObjectPoints:
    """The dense points of the object (:mod:`.isolate`, steps 1-4).

    ``backdrop`` (P,) bool marks still-backdrop points (:func:`still_points`); they are left out
    unless they hold most of the points off the plane.

    Returns:
        :class:`ObjectPoints`.

    Raises:
        ReconstructionError: no points are left after the plane's removal, or none in the box.
    """
    pts = np.asarray(points, np.float64)
    look = _axes_point(cameras)
    reach = float(np.median([np.linalg.norm(cam.center - look) for cam in cameras]))
    distance = settings.plane_distance * reach
    plane, inliers = support_plane(
        pts, cameras, distance=distance, min_fraction=settings.plane_min_fraction, look_at=look, seed=SEED
    )
    from_far = plane is None
    if from_far:
        plane, inliers = far_support_plane(pts, cameras, distance=distance, look_at=look, seed=SEED)
    off = np.ones(len(pts), bool) if plane is None else pts @ plane[:3] + plane[3] > settings.plane_clearance * distance
    counts = {"points": len(pts), "plane_inliers": inliers, "removed_with_plane": int((~off).sum()),
              "plane_from_far_points": int(from_far and plane is not None)}
    if backdrop is not None and (off & backdrop).sum() < 0.5 * off.sum():
        counts["still_backdrop"] = int((off & backdrop).sum())
        off &= ~backdrop
    if not off.any():
        raise ReconstructionError("isolating the object: no dense point lies above the support plane")
    if bbox is not None:
        lo, hi = np.asarray(bbox[:3], np.float64), np.asarray(bbox[3:], np.float64)
        keep = off & np.all((pts >= lo) & (pts <= hi), axis=1)
        if not keep.any():
            raise ReconstructionError(f"isolating the object: no dense point off the support lies in the box {list(bbox)}")
        return ObjectPoints(keep, plane, look, counts | {"clusters": 0, "object_points": int(keep.sum())}, keep)
    rest = np.flatnonzero(off)
    rest, spacing = _dense_core(pts, rest)
    labels = _clusters(pts[rest], settings.cluster_eps * spacing, SEED)
    names, sizes = np.unique(labels[labels >= 0], return_counts=True)
    candidates = names[sizes >= _MIN_CLUSTER_SHARE * len(rest)]
    if not len(candidates):
        candidates = names[sizes == sizes.max()] if len(names) else np.array([-1])
    gaps = [float(np.linalg.norm(np.median(pts[rest[labels == c]], axis=0) - look)) for c in candidates]
    chosen = candidates[int(np.argmin(gaps))]
    parts = _merged(pts[rest], labels, int(chosen), names if len(names) else candidates, settings.merge_gap,
                    min_size=int(np.ceil(_MIN_CLUSTER_SHARE * len(rest))))
    keep = np.zeros(len(pts), bool)
    keep[rest[np.isin(labels, parts)]] = True
    dense = keep.copy()
    others = np.flatnonzero(off & ~keep)  # the object's sparser points (a dark foot) within its dense ones' box
    keep[others[_within_box(pts[others], pts[keep], plane, settings.cluster_eps * spacing)]] = True
    counts["stray_points"] = int((off & ~keep).sum())
    return ObjectPoints(keep, plane, look, counts | {
        "clusters": len(names), "clusters_merged": len(parts), "object_points": int(keep.sum())
    }, dense)


def _within_box(points: np.ndarray, body: np.ndarray, plane: np.ndarray | None, margin: float) -> np.ndarray:
    """(P,) bool: ``points`` inside ``body``'s box grown by ``margin`` sideways (axes along the
    support plane, or the world's without one) and no higher than its highest point."""
    axes = np.eye(3)
    if plane is not None:
        side = np.linalg.svd(plane[None, :3])[2][1:]  # two unit axes along the plane
        axes = np.vstack([side, plane[:3]])
    p, b = points @ axes.T, body @ axes.T
    lo, hi = b.min(axis=0) - margin, b.max(axis=0) + margin
    if plane is not None:
        lo[2], hi[2] = -np.inf, b[:, 2].max()
    return np.asarray(np.all((p >= lo) & (p <= hi), axis=1))


def _dense_core(points: np.ndarray, index: np.ndarray) -> tuple[np.ndarray, float]:
    """The surfaces among ``points[index]``: the points with at least :data:`_CORE_SHARE` of the upper
    quartile's neighbour count (:func:`solid_points`), again while the median spacing falls by more
    than :data:`_CORE_SETTLE` (at most :data:`_CORE_ROUNDS` times); the index left and its spacing.
    Stray depths (a low-contrast table's mismatches, scattered in the air over it) can be half of
    the points: the upper quartile is still the surfaces'. On a path-traced mug on a table (36
    views of 612x512) 17,231 of the 32,503 points above the plane go: all but 4 of the 3,576 in the
    air over the mug, and 5 % of those on the mug."""
    spacing = point_spacing(points[index])
    for _ in range(_CORE_ROUNDS):
        solid = solid_points(points[index], spacing, share=_CORE_SHARE, percentile=75.0)
        if solid.all() or solid.sum() < 10:
            break
        index = index[solid]
        settled = point_spacing(points[index])
        done = settled > (1.0 - _CORE_SETTLE) * spacing
        spacing = settled
        if done:
            break
    return index, spacing


def _merged(
    points: np.ndarray, labels: np.ndarray, chosen: int, candidates: np.ndarray, gap: float, min_size: int = 0
) -> list[int]:
    """The chosen cluster's label and those of the candidates that come within ``gap`` times the
    object's extent (the diagonal of its 1st-99th percentile box) of it, grown one cluster at a time,
    nearest first: the parts of one object that stereo leaves apart (a knot's tubes where they
    cross, a spring's coils) lay 3-10 % of the extent apart on 16-view scenes. A candidate smaller
    than ``min_size`` points stays only as a bridge, where a larger one joined through it: a
    path-traced knot on a table (16 views of 320x256) broke into three parts 11 % of its extent
    apart and a fourth of 62 points between two of them, while small clusters of stray depths
    beside a path-traced rock are not its own."""
    rest = np.sort(np.array([int(c) for c in candidates if c != chosen], np.int64))
    if not len(rest) or gap <= 0:
        return [chosen]
    inside = labels == chosen
    others = np.flatnonzero(np.isin(labels, rest))
    which = np.searchsorted(rest, labels[others])
    # each other point's distance to the body so far and the part it is nearest to; a part that
    # joins updates them from its own points only (no farther than the widest reach there can be)
    bound = gap * float(np.linalg.norm(np.ptp(points[inside | np.isin(labels, rest)], axis=0)))
    dist, owner = np.full(len(others), np.inf), np.full(len(others), chosen)
    parts, parent, new, open_ = [chosen], {chosen: chosen}, chosen, np.ones(len(rest), bool)
    while open_.any():
        d, _ = cKDTree(points[labels == new]).query(points[others], k=1, distance_upper_bound=bound)
        closer = d < dist
        dist[closer], owner[closer] = d[closer], new
        body = points[inside]
        reach = gap * float(np.linalg.norm(np.percentile(body, 99, 0) - np.percentile(body, 1, 0)))
        near = np.full(len(rest), np.inf)
        np.minimum.at(near, which, np.where(open_[which], dist, np.inf))
        k = int(np.argmin(near))
        if not near[k] <= reach:
            break
        mine = np.flatnonzero(which == k)
        new = int(rest[k])
        parent[new] = int(owner[mine[np.argmin(dist[mine])]])
        parts.append(new)
        open_[k] = False
        inside |= labels == new
    counts = np.bincount(which, minlength=len(rest))
    big = {chosen} | {int(c) for c, n in zip(rest, counts, strict=True) if n >= min_size}
    needed = set()
    for p in parts:  # the large parts and the small ones on their way to the chosen one
        if p in big:
            while p not in needed:
                needed.add(p)
                p = parent[p]
    return [p for p in parts if p in needed]


def still_pixels(previews: Sequence[np.ndarray], *, tolerance: float) -> np.ndarray | None:
    """(H, W) bool: pixels whose colour stays within ``tolerance`` 8-bit levels of their median over the
    views (the median over views of the largest channel deviation), or None where the views are fewer
    than :data:`_MIN_STILL_VIEWS`, differ in size, or ``tolerance`` is 0."""
    if tolerance <= 0 or len(previews) < _MIN_STILL_VIEWS or len({p.shape for p in previews}) != 1:
        return None
    height = previews[0].shape[0]
    deviation = np.empty(previews[0].shape[:2])
    for r0 in range(0, height, _STILL_ROWS):  # a block of rows at a time, not a float64 copy of every view
        stack = np.stack([image[r0:r0 + _STILL_ROWS] for image in previews], axis=-1)  # (rows, W, 3, V)
        median = _median_last(stack)
        deviation[r0:r0 + _STILL_ROWS] = _median_last(np.abs(stack - median[..., None]).max(axis=2))
    return np.asarray(deviation <= tolerance)


def _median_last(values: np.ndarray) -> np.ndarray:
    """float64 median over the last axis of ``values``, as ``np.median`` gives it (the mean of the two
    middle values of an even count), by a partition of that axis (``np.median`` across the first axis
    of a stack of views is ten times slower)."""
    n = values.shape[-1]
    half = n // 2
    if n % 2:
        return np.partition(values, half, axis=-1)[..., half].astype(np.float64)
    parted = np.partition(values, [half - 1, half], axis=-1)
    return (parted[..., half - 1].astype(np.float64) + parted[..., half]) / 2.0


def still_points(
    points: np.ndarray, cameras: Sequence[Camera | None], previews: Sequence[np.ndarray], *, tolerance: float
) -> np.ndarray:
    """(P,) bool: points on a still camera's backdrop (:mod:`.isolate`, step 3); all False where the
    images show no still camera (still pixels under :data:`_MIN_STILL_AREA` of them)."""
    pts = np.asarray(points, np.float64)
    views = [(cam, image) for cam, image in zip(cameras, previews, strict=True) if cam is not None]
    still = still_pixels([image for _, image in views], tolerance=tolerance)
    if still is None or still.mean() < _MIN_STILL_AREA:
        return np.zeros(len(pts), bool)
    h, w = still.shape
    hits, seen = np.zeros(len(pts)), np.zeros(len(pts))
    for cam, _ in views:
        uv, z = project_points(cam, pts)
        col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        seen += inside
        hits[inside] += still[row[inside], col[inside]]
    return np.asarray(hits >= _STILL_SHARE * np.maximum(seen, 1)) & (seen > 0)


def solid_points(
    points: np.ndarray, spacing: float, *, share: float = _SOLID_SHARE, percentile: float = 50.0
) -> np.ndarray:
    """(P,) bool: points with at least ``share`` of the neighbour count's ``percentile`` (over the
    points) within 3 spacings: the object's surface, not the sparse points stereo puts beside its
    silhouettes."""
    if len(points) < 10 or spacing <= 0:
        return np.ones(len(points), bool)
    tree = cKDTree(points)
    counts = tree.query_ball_point(points, 3.0 * spacing, return_length=True)
    return np.asarray(counts >= share * np.percentile(counts, percentile))


def columns_below(
    points: np.ndarray,
    plane: np.ndarray,
    spacing: float,
    *,
    support: np.ndarray | None = None,
    share: float = _COLUMN_SHARE,
    all_short: bool = False,
    seed: int = 0,
) -> np.ndarray:
    """Points on vertical segments below the lower half of ``points``, toward the support plane.

    What the dense points miss of an object's lower part (an overhang's underside, a foot seen at a
    grazing angle or in shadow) lies between them and the plane it stands on, and a segment reaches
    down to the plane. Where ``support`` points (the plane's, as stereo saw them) lie within
    :data:`_SEEN_FOOT` spacings of a segment's foot, the views saw the table right under it (through
    a knot's loop, beside a mug's wall): that segment reaches down only ``share`` of the object's
    height (the 99th percentile of the points' heights above the plane), or to the plane where that
    is nearer. With ``all_short`` every segment does: a support found among the far points
    (:func:`far_support_plane`) holds too few points to show where the views saw it, and columns
    down to a path-traced table in a rock's shadow stood as a skirt around the rock (accuracy
    2.2x the true masks', 1.2 % of the vertices farther than 2 % of the diagonal, against 1.5x and
    none). At most 4000 points of the lower half are used, each segment sampled every
    ``spacing`` (at least 2 samples, at most 64); (M, 3) float64.
    """
    pts = np.asarray(points, np.float64)
    if plane is None or len(pts) == 0 or spacing <= 0:
        return np.zeros((0, 3))
    height = pts @ plane[:3] + plane[3]
    low = pts[height <= np.median(height)]
    if len(low) > 4000:
        low = low[np.random.default_rng(seed).choice(len(low), 4000, replace=False)]
    length = np.maximum(low @ plane[:3] + plane[3], 0.0)
    seen = np.full(len(low), all_short)
    if support is not None and len(support) and not all_short:
        foot = low - length[:, None] * plane[None, :3]
        gap, _ = cKDTree(support).query(foot, k=1, distance_upper_bound=_SEEN_FOOT * spacing)
        seen = np.isfinite(gap)
    length[seen] = np.minimum(length[seen], share * max(float(np.percentile(height, 99)), 0.0))
    steps = np.linspace(0.0, 1.0, int(np.clip(np.ceil(length.max(initial=0.0) / spacing), 2, 64)))
    return (low[:, None, :] - steps[None, :, None] * length[:, None, None] * plane[None, None, :3]).reshape(-1, 3)
