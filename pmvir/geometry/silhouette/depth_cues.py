"""What a view's own stereo depths show: the support past the object, the object itself, or something in front of the support.

Cues of step 5 of :mod:`pmvir.geometry.silhouette.isolate`. A depth counts only where another view
sees the same point in the same colour (:class:`SeenAlike`, :func:`seen_alike`): stereo on a
textureless wall matches the table behind it. :func:`sees_past` finds the pixels whose depths land
farther than the object's points (background), :func:`sees_object` those whose depths land on its
solid points (certain foreground), :func:`in_front_of_support` those whose depths stand in front of
the support plane (the object's shaded underside); :func:`seen_behind` and
:func:`depth_past_share` tell strays in the air from a dark foot.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING, NamedTuple

import cv2
import numpy as np
from scipy.spatial import cKDTree

from pmvir.camera import Camera
from pmvir.geometry.mvs.fusion import backproject, depth_at
from pmvir.geometry.projection import project_points

if TYPE_CHECKING:
    from pmvir.geometry.mvs.sweep import DepthMap

#: :func:`sees_object` erodes the depth grid's pixels that show the object by this many: stereo's windows
#: carry an object's depth past its outline, and those pixels, with the table's colours, as certain
#: foreground drew a built-in knot's loops into its masks.
_SHOWN_ERODE = 2
#: A view's depth farther than this many point spacings from the object's points and columns sees past it ...
FREE_REACH = 3.0
#: ... and a pixel sees past the object where at least this share of the known depths around it do
#: (a window of :data:`FREE_WINDOW` of the depth grid's diagonal, at least half of it known).
_FREE_SHARE = 0.75
FREE_WINDOW = 0.02
#: A depth past the object counts where another view's depth lands within this share of the point's
#: depth of it ...
_ALIKE_DEPTH = 0.01
#: ... and that view shows it within this many 8-bit levels, in every channel, of this view's colour.
_ALIKE_COLOUR = 24.0
#: A point the stray filter left out and the object's box took back counts as the object's in
#: :func:`sees_past` unless at least this share of the views' depths at its pixel lie beyond it, of
#: those that do not see a surface in front of it (:func:`depth_past_share`): on a path-traced knot
#: on a table (36 views of 612x512) 26 % of those within 1.5 spacings of the true surface reach 0.5
#: with a margin of 3 spacings, 98 % of those farther than 4 (a blob on a turntable, 12 views of
#: 320x256: 37 % and 88 %) ...
_PAST_SHARE = 0.5
#: ... and this share of all the views with a depth there: the foot of a rock on a table, hidden by
#: the rock from most views, has the few depths that reach it past it at its silhouette. Of the points
#: passing :data:`_PAST_SHARE` (36 views of 612x512), those within 0.5 % of the diagonal of the true
#: surface and those farther, without and with this share: rock on a table 1180 and 3474, 80 and
#: 3005; path-traced knot on a table 113 and 2589, 7 and 2190.
_PAST_SHARE_ALL = 0.25


class SeenAlike(NamedTuple):
    """What :func:`sees_past` checks a view's depths past the object against: per view its camera,
    stereo depth map (None where it has none) and (H, W, 3) uint8 preview (:mod:`.isolate`, step 5)."""

    cameras: Sequence[Camera | None]
    depth_maps: Sequence[DepthMap | None]
    previews: Sequence[np.ndarray]


def _colour_at(camera: Camera, image: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(N, 3) float32: the 3x3 mean of ``image`` (the camera's 8-bit preview) around the pixels ``points``
    project to (clipped to the image; the mean leaves pixel noise out of colour comparisons)."""
    uv, _ = project_points(camera, points)
    h, w = image.shape[:2]
    cols = np.floor(uv[:, 0] * w / camera.width).astype(np.int64)
    rows = np.floor(uv[:, 1] * h / camera.height).astype(np.int64)
    total = np.zeros((len(cols), image.shape[2]), np.float32)
    for dr in (-1, 0, 1):
        for dc in (-1, 0, 1):
            total += image[np.clip(rows + dr, 0, h - 1), np.clip(cols + dc, 0, w - 1)]
    return total / 9.0


def seen_alike(points: np.ndarray, colours: np.ndarray, index: int, views: SeenAlike) -> np.ndarray:
    """(N,) bool: the points that some view other than ``index`` sees (its stereo depth at their pixel
    within :data:`_ALIKE_DEPTH` of their depth) in ``colours`` (every channel within
    :data:`_ALIKE_COLOUR` 8-bit levels of its :func:`_colour_at` there)."""
    pts = np.asarray(points, np.float64)
    out = np.zeros(len(pts), bool)
    for j, (cam, dm, image) in enumerate(zip(views.cameras, views.depth_maps, views.previews, strict=True)):
        if j == index or cam is None or dm is None:
            continue
        todo = np.flatnonzero(~out)
        if not len(todo):
            break
        z, _, _, d = depth_at(dm, pts[todo])
        on = todo[(d > 0) & (np.abs(d - z) <= _ALIKE_DEPTH * z)]
        if len(on):
            diff = np.abs(_colour_at(cam, image, pts[on]) - colours[on]).max(axis=1)
            out[on[diff <= _ALIKE_COLOUR]] = True
    return out


def sees_past(
    depth: DepthMap,
    body: cKDTree,
    reach: float,
    shape: tuple[int, int],
    *,
    index: int | None = None,
    views: SeenAlike | None = None,
    where: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool: the pixels where the view's own stereo depth lies beyond ``reach`` of every point
    of the object (``body``: the KD-tree of its points and columns) in at least :data:`_FREE_SHARE`
    of the known depths of a window around them: the view sees the table or the room there, past the
    object (a knot's loop, the gap under an arch), whatever the splatted points and columns cover.
    With ``views`` (and ``index``, this view's position in them) a depth past the object counts
    only where another view sees the point it lands on in the same colour (:func:`seen_alike`);
    elsewhere it is unknown: stereo on a textureless wall matches the table behind it, whose colour
    is not the wall's. ``where`` ((H, W) bool, the preview's grid) limits that check to the pixels
    that matter (beyond them every depth is unknown).
    ``shape``: the preview's (H, W); the depth grid is resized to it."""
    rows, cols = np.nonzero(depth.valid)
    h, w = depth.depth.shape
    past = np.zeros((h, w), np.float32)
    known_px = depth.valid.astype(np.float32)
    if len(rows):
        world = backproject(depth.camera, depth.depth[rows, cols], rows, cols)
        gap, _ = body.query(world, k=1, distance_upper_bound=reach)
        beyond_px = ~np.isfinite(gap)
        if views is not None and index is not None and beyond_px.any():
            cam = views.cameras[index]
            if cam is not None:
                far = np.flatnonzero(beyond_px)
                if where is not None:
                    grid = cv2.resize(where.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
                    near = grid[rows[far], cols[far]]
                    beyond_px[far[~near]] = False
                    known_px[rows[far[~near]], cols[far[~near]]] = 0.0
                    far = far[near]
                alike = seen_alike(world[far], _colour_at(cam, views.previews[index], world[far]), index, views)
                known_px[rows[far[~alike]], cols[far[~alike]]] = 0.0  # past, but unconfirmed: unknown
                beyond_px[far[~alike]] = False
        past[rows, cols] = beyond_px
    k = max(1, round(FREE_WINDOW * float(np.hypot(h, w))))
    known = cv2.blur(known_px, (2 * k + 1, 2 * k + 1))
    beyond = cv2.blur(past, (2 * k + 1, 2 * k + 1))
    free = (known >= 0.5) & (beyond >= _FREE_SHARE * np.maximum(known, 1e-6))
    return np.asarray(cv2.resize(free.astype(np.uint8), (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST), bool)


def sees_object(
    depth: DepthMap, solid: cKDTree, reach: float, shape: tuple[int, int], *, plane: np.ndarray | None, lift: float,
    index: int | None = None, views: SeenAlike | None = None, where: np.ndarray | None = None,
) -> np.ndarray:
    """(H, W) bool: the pixels where the view's own stereo depth lands within ``reach`` of a solid point of
    the object (``solid``: their KD-tree) and more than ``lift`` above the support ``plane`` (any height
    without one): the view sees the object itself there. With ``views`` (``index``: this view's place
    in them) only where another view sees the depth's point alike (:func:`seen_alike`): stereo's windows
    carry an object's depth past its outline onto the table or through a loop, and the views that see
    that point show the object's colours, not the table's. ``where`` ((H, W) bool, the preview's grid)
    limits the pixels looked at. The depth grid's pixels are eroded by :data:`_SHOWN_ERODE` and resized to ``shape``
    (the preview's (H, W)); near the plane the table around a foot lies within reach of the foot's points."""
    rows, cols = np.nonzero(depth.valid)
    h, w = depth.depth.shape
    if where is not None and len(rows):
        grid = cv2.resize(where.astype(np.uint8), (w, h), interpolation=cv2.INTER_NEAREST) > 0
        inside = grid[rows, cols]
        rows, cols = rows[inside], cols[inside]
    out = np.zeros((h, w), np.uint8)
    if len(rows):
        world = backproject(depth.camera, depth.depth[rows, cols], rows, cols)
        gap, _ = solid.query(world, k=1, distance_upper_bound=reach)
        on = np.isfinite(gap)
        if plane is not None:
            on &= world @ plane[:3] + plane[3] > lift
        cam = None if views is None or index is None else views.cameras[index]
        if cam is not None and views is not None and index is not None and on.any():
            ask = np.flatnonzero(on)
            on[ask] = seen_alike(world[ask], _colour_at(cam, views.previews[index], world[ask]), index, views)
        out[rows[on], cols[on]] = 1
    inner = cv2.erode(out, np.ones((2 * _SHOWN_ERODE + 1,) * 2, np.uint8))
    return np.asarray(cv2.resize(inner, (shape[1], shape[0]), interpolation=cv2.INTER_NEAREST), bool)


def rays_to_plane(camera: Camera, uv: np.ndarray, plane: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The unit rays (N, 3) through the camera's pixels ``uv`` ((N, 2)), their length ``t`` (N,) to
    ``plane`` (a, b, c, d; negative: behind the camera) and the (N, 3) points where they meet it."""
    rays = camera.ray_directions(uv)
    normal, offset = np.asarray(plane[:3], np.float64), float(plane[3])
    along = rays @ normal
    t = -(normal @ camera.center + offset) / np.where(np.abs(along) < 1e-12, 1e-12, along)
    return rays, t, camera.center + t[:, None] * rays


def in_front_of_support(
    camera: Camera, depth_map: DepthMap, plane: np.ndarray, where: np.ndarray, margin: float,
    *, index: int | None = None, views: SeenAlike | None = None,
) -> np.ndarray:
    """(H, W) bool: the pixels ``where`` ((H, W) bool, the camera's image grid) whose own stereo depth
    lies more than ``margin`` in front of the support ``plane`` along their ray: they see something
    standing on it (the foot of an object, whose points the plane's band took), not the support.
    With ``views`` (``index``: this view's place in them) only where another view sees the depth's
    point alike (:func:`seen_alike`): a mismatch of stereo on a noisy table seen through a knot's
    loop lands in front of it as well, where no other view confirms it."""
    out = np.zeros(where.shape, bool)
    rows, cols = np.nonzero(where)
    if not len(rows):
        return out
    scale = np.array([camera.width / where.shape[1], camera.height / where.shape[0]])
    rays, t, on_plane = rays_to_plane(camera, (np.stack([cols, rows], 1) + 0.5) * scale, plane)
    z, _, _, d = depth_at(depth_map, on_plane)
    front = np.flatnonzero((t > 0) & (d > 0) & (d < z - margin))
    if views is not None and index is not None and len(front):
        ray = rays[front]
        world = camera.center + ray * (d[front] / (ray @ camera.R[2]))[:, None]
        image = views.previews[index]
        front = front[seen_alike(world, _colour_at(camera, image, world), index, views)]
    out[rows[front], cols[front]] = True
    return out


def depth_past_share(
    points: np.ndarray, depth_maps: Sequence[DepthMap | None], margin: float
) -> tuple[np.ndarray, np.ndarray]:
    """Two (P,) float: per point the share of the views whose stereo depth at its pixel lies more than
    ``margin`` beyond it, among those whose depth lies beyond it or within ``margin`` of it (the views
    that see a surface in front of it do not count), and among all views with a depth at its pixel."""
    beyond = np.zeros(len(points), np.int64)
    at = np.zeros(len(points), np.int64)
    known_all = np.zeros(len(points), np.int64)
    for dm in depth_maps:
        if dm is None:
            continue
        z, _, _, d = depth_at(dm, points)
        known = d > 0
        known_all += known
        beyond += known & (d > z + margin)
        at += known & (np.abs(d - z) <= margin)
    return beyond / np.maximum(beyond + at, 1), beyond / np.maximum(known_all, 1)


def seen_behind(points: np.ndarray, depth_maps: Sequence[DepthMap | None], margin: float) -> np.ndarray:
    """(P,) bool: the points the views' depths pass behind (:func:`depth_past_share`): at least
    :data:`_PAST_SHARE` of the views that do not see a surface in front of them, and at least
    :data:`_PAST_SHARE_ALL` of all views."""
    of_seeing, of_all = depth_past_share(points, depth_maps, margin)
    return np.asarray((of_seeing >= _PAST_SHARE) & (of_all >= _PAST_SHARE_ALL))
