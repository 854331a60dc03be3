"""The support plane under the object: RANSAC among the planes with every camera on one side of them.

Step 2 of :mod:`pmvir.geometry.silhouette.isolate`. :func:`support_plane` draws candidate planes
from three dense points at a time and scores them by their inliers, among the planes that have
every camera and the look-at point on one side (views from above the table: walls and the object's
own flat patches are no candidates); the best is refitted to the points near it while its inliers
grow. Where no plane holds enough of the points, :func:`far_support_plane` looks for one among the
points farthest from the look-at point, with the object above it and its points reaching out past
the object's.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from pmvir.camera import Camera

if TYPE_CHECKING:
    pass

#: RANSAC's candidate planes (3 points each): with 10 % of the points on the support, the chance of
#: never drawing three of them is (1 - 0.001)^4000, about 2 %.
_RANSAC_ITERATIONS = 4000
#: Candidate planes scored together (a (sample, batch) array of distances).
_RANSAC_BATCH = 200
#: RANSAC draws its planes from a random subset of at most this many points.
_MAX_RANSAC_POINTS = 20_000
#: A support found among the far points (:func:`far_support_plane`) has at most this share of the
#: points near the object below it (path-traced tables: 0.6 % under a blob, 2-2.5 % under a rock,
#: where stereo's mismatches on the table's low contrast lie below it; a face of a rock: 8 %).
_MAX_BELOW = 0.04
#: RANSAC's best plane is refitted to the points within this many inlier distances of it ...
_LOCAL_BAND = 2.0
#: ... at most this many times, while its inliers grow (on a path-traced table: 4.6 % of the points
#: to 6.4 %, its tilt 3.1 deg to 0.1 deg).
_LOCAL_ROUNDS = 5


def support_plane(
    points: np.ndarray,
    cameras: Sequence[Camera],
    *,
    distance: float,
    min_fraction: float,
    look_at: np.ndarray | None = None,
    seed: int = 0,
) -> tuple[np.ndarray | None, int]:
    """The largest plane of the points that is a support seen from above (:mod:`.isolate`, step 2).

    RANSAC scores only the candidate planes with every camera (and ``look_at``, the object) more
    than ``distance`` on one side: the object's own near-flat patches and a backdrop, with cameras
    on both sides, are never candidates, however many points they hold.

    Args:
        points: (P, 3) world points.
        cameras: the registered views.
        distance: RANSAC inlier distance, world units (> 0).
        min_fraction: least share of the points on the plane.
        look_at: (3,) a point of the object, on the cameras' side of a support (optional).
        seed: RANSAC's random seed.

    Returns:
        (a, b, c, d) with the unit normal toward the cameras (a x + b y + c z + d > 0 on their side),
        or None; and the number of inliers (0 without a support).
    """
    pts = np.asarray(points, np.float64)
    if len(pts) < 3 or distance <= 0 or not cameras:
        return None, 0
    rng = np.random.default_rng(seed)
    sample = pts[rng.choice(len(pts), min(len(pts), _MAX_RANSAC_POINTS), replace=False)]
    above = np.array([cam.center for cam in cameras] + ([] if look_at is None else [np.asarray(look_at)]))
    best, best_count = None, 0
    for _ in range(_RANSAC_ITERATIONS // _RANSAC_BATCH):
        normal, offset, spans = _random_planes(sample, rng)
        side = above @ normal.T + offset  # (C, B)
        sign = np.where(side[0] < 0, -1.0, 1.0)
        ok = spans & np.all(side * sign > distance, axis=0)
        if not ok.any():
            continue
        counts = (np.abs(sample @ normal[ok].T + offset[ok]) <= distance).sum(axis=0)
        k = int(np.argmax(counts))
        if counts[k] > best_count:
            best_count = int(counts[k])
            best = sign[ok][k] * np.append(normal[ok][k], offset[ok][k])
    plane = _settled(pts, best, distance, min_fraction)
    if plane is None:
        return None, 0
    side = above @ plane[:3] + plane[3]
    if not (np.all(side > 0) or np.all(side < 0)):
        return None, 0
    plane = plane if side[0] > 0 else -plane
    return plane, int((np.abs(pts @ plane[:3] + plane[3]) <= distance).sum())


def far_support_plane(
    points: np.ndarray,
    cameras: Sequence[Camera],
    *,
    distance: float,
    look_at: np.ndarray,
    min_fraction: float = 0.02,
    seed: int = 0,
) -> tuple[np.ndarray | None, int]:
    """A support that holds too few of the points for :func:`support_plane`, found among the points
    farthest from the object (:mod:`.isolate`, step 2).

    Where the views see the table at grazing angles (path-traced, 16 views of 320x256: 3 % of a rock's
    dense points) RANSAC seldom draws three of its points, and the object's own faces hold as many.
    Here RANSAC draws its planes from the tenth of the points farthest from ``look_at`` (a quarter of
    them on that table) and scores them on all. A plane counts with ``look_at`` and every camera more
    than ``distance`` above it, three quarters of the cameras higher than ``look_at``, at most
    :data:`_MAX_BELOW` of the points near the object (within twice the distance of the nearest
    fifth) more than ``distance`` below, at least ``min_fraction`` of the points on it, and its
    points reaching out past the object (their median distance from the foot of ``look_at`` on it
    beyond the near points' median distance from ``look_at``): a face of the object has the object
    on both sides, a wall behind the object has views on both sides of the object, and a plane
    through the rim of an object's cut-off underside holds points within the object only.

    Returns:
        As :func:`support_plane`.
    """
    pts = np.asarray(points, np.float64)
    look = np.asarray(look_at, np.float64)
    if len(pts) < 10 or distance <= 0 or not cameras:
        return None, 0
    rng = np.random.default_rng(seed)
    sample = pts[rng.choice(len(pts), min(len(pts), _MAX_RANSAC_POINTS), replace=False)]
    r = np.linalg.norm(sample - look, axis=1)
    far = sample[r >= np.percentile(r, 90)]
    near = sample[r <= 2.0 * np.percentile(r, 20)]
    centres = np.array([cam.center for cam in cameras])
    near_reach = float(np.median(np.linalg.norm(near - look, axis=1)))

    def holds(normal: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """(B,) bool: planes (unit normals toward ``look``) that can be the support."""
        cams = centres @ normal.T + offset
        obj = look @ normal.T + offset
        below = (near @ normal.T + offset < -distance).mean(axis=0)
        higher = np.percentile(cams, 25, axis=0) > obj  # three quarters of the views look down on the object
        return np.asarray((obj > distance) & (cams.min(axis=0) > distance) & higher & (below <= _MAX_BELOW))

    best, best_count = None, 0
    for _ in range(_RANSAC_ITERATIONS // _RANSAC_BATCH):
        normal, offset, spans = _random_planes(far, rng)
        sign = np.where(normal @ look + offset < 0, -1.0, 1.0)
        normal, offset = normal * sign[:, None], offset * sign
        ok = spans & holds(normal, offset)
        if not ok.any():
            continue
        counts = (np.abs(sample @ normal[ok].T + offset[ok]) <= distance).sum(axis=0)
        for k in np.argsort(-counts):
            if counts[k] <= best_count:
                break
            candidate = np.append(normal[ok][k], offset[ok][k])
            if _reaches_out(sample, candidate, distance, look, near_reach):
                best_count, best = int(counts[k]), candidate
                break
    plane = _settled(pts, best, distance, min_fraction)
    if plane is None:
        return None, 0
    plane = plane if look @ plane[:3] + plane[3] > 0 else -plane
    if not (holds(plane[None, :3], plane[3:])[0] and _reaches_out(pts, plane, distance, look, near_reach)):
        return None, 0
    return plane, int((np.abs(pts @ plane[:3] + plane[3]) <= distance).sum())


def _reaches_out(points: np.ndarray, plane: np.ndarray, distance: float, look: np.ndarray, reach: float) -> bool:
    """Whether the median distance of the plane's points (within ``distance`` of it) from the foot of
    ``look`` on it exceeds ``reach``: a support stretches out past the object (:func:`far_support_plane`)."""
    on = points[np.abs(points @ plane[:3] + plane[3]) <= distance]
    foot = look - (look @ plane[:3] + plane[3]) * plane[:3]
    return bool(len(on) and np.median(np.linalg.norm(on - foot, axis=1)) > reach)


def _random_planes(points: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:data:`_RANSAC_BATCH` planes, each through three random ``points``: (B, 3) unit normals, (B,)
    offsets, and (B,) whether the three points span a plane."""
    tri = points[rng.integers(0, len(points), (_RANSAC_BATCH, 3))]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    normal = normal / np.maximum(length, 1e-12)[:, None]
    return normal, -np.einsum("ij,ij->i", normal, tri[:, 0]), length > 1e-12


def _settled(points: np.ndarray, best: np.ndarray | None, distance: float, min_fraction: float) -> np.ndarray | None:
    """RANSAC's best plane refitted (:func:`_local_refit`, then least squares to its inliers), or None
    where there is none or it holds fewer than ``min_fraction`` of the points (its orientation is
    the caller's to set)."""
    if best is None:
        return None
    best = _local_refit(points, best, distance)
    inliers = np.abs(points @ best[:3] + best[3]) <= distance
    if inliers.sum() < max(3, min_fraction * len(points)):
        return None
    return _refit(points[inliers])


def _local_refit(points: np.ndarray, plane: np.ndarray, distance: float) -> np.ndarray:
    """RANSAC's best plane refitted to the points within :data:`_LOCAL_BAND` inlier distances of it,
    while its inliers grow (at most :data:`_LOCAL_ROUNDS` times): three noisy points tilt a sample
    plane, and a tilted plane holds too few of a noisy table's points to count as the support."""
    count = int((np.abs(points @ plane[:3] + plane[3]) <= distance).sum())
    for _ in range(_LOCAL_ROUNDS):
        near = np.abs(points @ plane[:3] + plane[3]) <= _LOCAL_BAND * distance
        if near.sum() < 3:
            break
        refit = _refit(points[near])
        refit = refit if refit[:3] @ plane[:3] > 0 else -refit
        grown = int((np.abs(points @ refit[:3] + refit[3]) <= distance).sum())
        if grown <= count:
            break
        plane, count = refit, grown
    return plane


def _refit(points: np.ndarray) -> np.ndarray:
    """Least-squares plane (a, b, c, d), unit normal, of RANSAC's inliers (the sample plane tilts with noise)."""
    centre = points.mean(axis=0)
    normal = np.linalg.svd(points - centre, full_matrices=False)[2][2]
    return np.append(normal, -normal @ centre)
