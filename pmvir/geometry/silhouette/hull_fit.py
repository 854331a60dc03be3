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
object pixel and the first background pixel (:func:`mask_distance`). Masks that
cut into the object here and there (drawn by a segmentation) ask ``views`` of
at least 2: a vertex then moves only as far as the second view ruling it out
says, so one mask's cut moves nothing.

Where a vertex's normal runs along the rays of the views that rule it out (a
web across a knot's loop, a flap by the table), a step along it gains little in
the image and would carry the vertex far from any surface: with ``min_gain``
such a step is taken back and the vertex stops (on the built-in knot on a table
without masks the farthest vertex is 3.2 % of the diagonal with it, 5.1 %
without).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d

from pmvir.camera import Camera, sample_bilinear
from pmvir.errors import ConfigError, ShapeError
from pmvir.geometry.mesh_ops import grouped_medians, raycasting_scene, vertex_normals


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
        views: how many views had to see a vertex outside their masks for it to move.
        stopped: vertices stopped where a step along the normal brought them less than ``min_gain`` of its
            length closer to the masks.
        seconds: wall time of the fit (set by the caller that times it; 0 otherwise).
    """

    vertices: np.ndarray
    outside_before: int
    outside_after: int
    moved: int
    mean_move_px: float
    tolerance_px: float
    views: int = 1
    stopped: int = 0
    seconds: float = 0.0

    def to_dict(self) -> dict[str, float | int]:
        return {
            "outside_before": self.outside_before,
            "outside_after": self.outside_after,
            "moved": self.moved,
            "mean_move_px": round(self.mean_move_px, 4),
            "tolerance_px": self.tolerance_px,
            "views": self.views,
            "stopped": self.stopped,
            "seconds": round(self.seconds, 3),
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
    vertices: np.ndarray, cameras: Sequence[Camera], distances: Sequence[np.ndarray], *, rank: int = 1
) -> tuple[np.ndarray, np.ndarray]:
    """Per vertex the least mask distance over the views (pixels; negative: outside that mask), or with
    ``rank`` k the k-th least, and the ground sampling distance (world units per pixel) in the view
    that gives it.

    Views the vertex lies behind do not count; a vertex in front of fewer than ``rank`` views gets
    +inf.

    Raises:
        ConfigError: ``rank`` below 1.
    """
    if rank < 1:
        raise ConfigError(f"rank must be >= 1, got {rank}")
    x = np.asarray(vertices, dtype=np.float64)
    least = np.full((rank, len(x)), np.inf)  # the ``rank`` least distances so far, ascending
    gsd = np.zeros((rank, len(x)))
    for cam, dist in zip(cameras, distances, strict=True):
        uv, z = cam.project(x)
        d = np.where(z > 0, sample_bilinear(dist, uv[:, 0], uv[:, 1]), np.inf)
        g = np.maximum(z, 0.0) / cam.K[0, 0]
        for k in range(rank):  # inserted in order: the larger of the two goes on down
            lower = d < least[k]
            least[k], d = np.where(lower, d, least[k]), np.where(lower, least[k], d)
            gsd[k], g = np.where(lower, g, gsd[k]), np.where(lower, gsd[k], g)
    return least[rank - 1], gsd[rank - 1]


def fit_inside_hull(
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    masks: Sequence[np.ndarray | None],
    *,
    tolerance_px: float = 0.5,
    max_move_px: float = 3.0,
    iterations: int = 20,
    views: int = 1,
    min_gain: float = 0.0,
) -> HullFit:
    """Move the vertices that project more than ``tolerance_px`` outside some mask (``views`` masks)
    inward along their normals (module docstring).

    Args:
        vertices, faces: the mesh (faces counter-clockwise seen from outside).
        cameras, masks: the registered views and their object masks (None, or a mask without object
            or without background pixels: that view does not count).
        tolerance_px: how far outside a mask (pixels) a vertex may project; masks and poses are
            good to about half a pixel.
        max_move_px: the most a vertex moves, in pixels of its ground sampling distance.
        iterations: steps; each moves a vertex by half its remaining violation (at most 1 px), along
            the current normals.
        views: how many views must see a vertex outside their masks for it to move: its violation is
            the ``views``-th largest, so above 1 a mask that cuts into the object moves nothing.
        min_gain: a step stays only where it brings the vertex at least this share of its length (px)
            closer to the masks; elsewhere it is taken back and the vertex stops (0: every step stays).

    Returns:
        :class:`HullFit`.

    Raises:
        ConfigError: negative tolerance or move, views below 1, min_gain outside [0, 1], or mismatched
            inputs.
    """
    if not 0.0 <= min_gain <= 1.0:
        raise ConfigError(f"min_gain must be within [0, 1], got {min_gain}")
    if tolerance_px < 0.0 or max_move_px < 0.0:
        raise ConfigError(f"tolerance_px and max_move_px must be >= 0, got {tolerance_px} and {max_move_px}")
    if views < 1:
        raise ConfigError(f"views must be >= 1, got {views}")
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
        return HullFit(v0.copy(), 0, 0, 0, 0.0, tolerance_px, views)
    cams = [c for c, _ in pairs]
    dists = [d for _, d in pairs]
    least, _ = hull_depth(v0, cams, dists, rank=views)
    # only these can move (a vertex's violation depends on its own position alone)
    idx = np.flatnonzero(least < -tolerance_px)
    # their normals need only the faces around them (the same sums, in the same order)
    movable = np.zeros(len(v0), dtype=bool)
    movable[idx] = True
    around = f[movable[f].any(axis=1)]
    x = v0.copy()
    moved_px = np.zeros(len(idx))
    stuck = np.zeros(len(idx), dtype=bool)  # a step along the normal that did not bring it closer
    least_i, gsd = hull_depth(x[idx], cams, dists, rank=views)
    for _ in range(iterations):
        out = (least_i < -tolerance_px) & (moved_px < max_move_px) & (gsd > 0) & ~stuck
        if not out.any():
            break
        step_px = np.minimum(
            np.minimum(0.5 * (-least_i[out] - tolerance_px), 1.0), max_move_px - moved_px[out]
        )
        step_px = np.maximum(step_px, 0.01)  # halving toward the tolerance converges slowly at the end
        normals = vertex_normals(x, around).astype(np.float64)[idx[out]]
        step = (step_px * gsd[out])[:, None] * normals
        x[idx[out]] -= step
        after, after_gsd = hull_depth(x[idx[out]], cams, dists, rank=views)
        # where the normal runs along the view rays (a web across a knot's loop, a flap by the table) a
        # step gains little in the image and would carry the vertex away: it is taken back, the vertex stops
        gained = (after - least_i[out] >= min_gain * step_px) if min_gain > 0.0 else np.ones(len(step), bool)
        back = idx[out][~gained]
        x[back] += step[~gained]
        sel = np.flatnonzero(out)
        stuck[sel[~gained]] = True
        moved_px[sel[gained]] += step_px[gained]
        least_i[sel[gained]], gsd[sel[gained]] = after[gained], after_gsd[gained]
    least_i, _ = hull_depth(x[idx], cams, dists, rank=views)
    moved = moved_px > 0
    return HullFit(
        vertices=x,
        outside_before=len(idx),
        outside_after=int((least_i < -tolerance_px).sum()),
        moved=int(moved.sum()),
        mean_move_px=float(moved_px[moved].mean()) if moved.any() else 0.0,
        tolerance_px=tolerance_px,
        views=views,
        stopped=int(stuck.sum()),
    )


MARGIN_QUANTILE = 0.1
"""The quantile of the rim vertices' distances inside the masks that :func:`fit_to_rims` takes as the
masks' margin. Measured (README, "Masks drawn generously"): exact masks give 0 on the truth and
on refined meshes (a third to a half of all rim samples lie on the outline), masks dilated by 1 and 2 px
give 1.0 and 2.25."""


@dataclass(frozen=True)
class RimFit:
    """What :func:`fit_to_rims` did.

    Attributes:
        vertices: (N, 3) float64 the vertices, moved outward where their rims lie inside the masks.
        rim_vertices: vertices near some view's rim whose distance to the mask's boundary was measured.
        inside: of those, the ones farther inside the masks than the tolerance (their median over views).
        mean_move_px: the mean outward move over all vertices, in pixels of the ground sampling distance.
        max_move_px: the largest move, same units.
        gain, tolerance_px: the options used.
        mask_margin_px: how far the masks reach past the rims everywhere, discounted from every distance
            (estimated, or as given).
        margin_estimated: whether ``mask_margin_px`` was estimated from the rims (``mask_margin_px=None``).
        margin_estimate_px: the estimate, also where a given margin was used instead (0 when no rim was
            measured).
    """

    vertices: np.ndarray
    rim_vertices: int
    inside: int
    mean_move_px: float
    max_move_px: float
    gain: float
    tolerance_px: float
    mask_margin_px: float = 0.0
    margin_estimated: bool = False
    margin_estimate_px: float = 0.0

    def to_dict(self) -> dict[str, float | int]:
        return {
            "rim_vertices": self.rim_vertices,
            "inside": self.inside,
            "mean_move_px": round(self.mean_move_px, 4),
            "max_move_px": round(self.max_move_px, 4),
            "gain": self.gain,
            "tolerance_px": self.tolerance_px,
            "mask_margin_px": round(self.mask_margin_px, 4),
            "margin_estimated": self.margin_estimated,
            "margin_estimate_px": round(self.margin_estimate_px, 4),
        }


def _rim_distances(
    vertices: np.ndarray,
    normals: np.ndarray,
    scene: o3d.t.geometry.RaycastingScene,
    origin: np.ndarray,
    cam: Camera,
    mask: np.ndarray,
    rim_cos: float,
    reach_px: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One view's near-rim vertices, how far (pixels) inside the mask each projects along its normal's image
    direction, and the ground sampling distance there; vertices whose march meets another part of the
    mesh or does not leave the mask within ``reach_px`` are left out. ``scene`` holds the mesh moved by
    ``-origin`` (float32 rays stay precise far from the world's origin)."""

    def cast(origins: np.ndarray, dirs: np.ndarray) -> np.ndarray:
        rays = np.concatenate([np.broadcast_to(origins - origin, dirs.shape), dirs], -1).astype(np.float32)
        return scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()

    # Rays are cast only where their answer can count. A march is read for "free" at mask pixels and
    # ends within reach_px at a pixel outside the mask, so only mask pixels within reach of the
    # boundary matter (a band; the rest of the mask stays "not free"), and only the vertices that pass
    # the other rim tests need their own ray. The result is the same as casting every ray.
    h, w = mask.shape
    r = int(np.ceil(reach_px)) + 1
    band = mask & ~cv2.erode(mask.astype(np.uint8), np.ones((2 * r + 1, 2 * r + 1), np.uint8),
                             borderType=cv2.BORDER_REPLICATE).astype(bool)
    rows, cols = np.nonzero(band)
    dirs = cam.ray_directions(np.stack([cols + 0.5, rows + 0.5], axis=-1))
    free = np.zeros_like(mask)
    free[rows, cols] = ~np.isfinite(cast(cam.center, dirs))  # band pixels the mesh leaves uncovered
    to_v = vertices - cam.center
    dist = np.linalg.norm(to_v, axis=1)
    to_v /= np.maximum(dist, 1e-300)[:, None]
    uv, z = cam.project(vertices)
    candidate = np.flatnonzero(
        (np.abs((normals * to_v).sum(1)) < rim_cos)
        & (z > 0)
        & (uv[:, 0] >= 0)
        & (uv[:, 0] < w)
        & (uv[:, 1] >= 0)
        & (uv[:, 1] < h)
    )
    hit = cast(cam.center, to_v[candidate])
    idx = candidate[np.abs(hit - dist[candidate]) < 3e-3 * dist[candidate]]
    step, _ = cam.project(vertices[idx] + 1e-4 * dist[idx, None] * normals[idx])
    direction = np.zeros_like(uv)
    direction[idx] = step - uv[idx]
    direction[idx] /= np.maximum(np.linalg.norm(direction[idx], axis=1), 1e-12)[:, None]
    inside = np.full(len(idx), np.nan)
    alive = np.ones(len(idx), dtype=bool)
    for s in np.arange(0.25, reach_px + 1e-9, 0.25):
        p = uv[idx] + s * direction[idx]
        col = np.floor(p[:, 0]).astype(np.int64)
        row = np.floor(p[:, 1]).astype(np.int64)
        off = (col < 0) | (col >= w) | (row < 0) | (row >= h)
        col, row = col.clip(0, w - 1), row.clip(0, h - 1)
        in_mask = mask[row, col]
        ended = alive & ~in_mask & ~off
        inside[ended] = s - 0.25
        # off the image (the boundary is not seen), or past the first pixel the mesh is in the way
        # (another part of the object draws this silhouette): no distance
        blocked = alive & (off | (in_mask & ~free[row, col] & (s > 1.0)))
        alive &= ~ended & ~blocked
    ok = np.isfinite(inside)
    return idx[ok], inside[ok], z[idx[ok]] / cam.K[0, 0]


def fit_to_rims(
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    masks: Sequence[np.ndarray | None],
    *,
    gain: float = 0.5,
    tolerance_px: float = 0.25,
    rim_cos: float = 0.25,
    reach_px: float = 4.0,
    spread: int = 5,
    mask_margin_px: float | None = None,
) -> RimFit:
    """Move the surface outward where its rims lie inside the masks (the complement of :func:`fit_inside_hull`).

    Each view's silhouette is the outline of the surface's rim there: a vertex whose normal is nearly
    perpendicular to the view's ray (``|n . d| < rim_cos``) projects close to the mask's boundary.
    From each such vertex's projection the mask is followed along its normal's image direction, in
    quarter pixels, to the boundary; where another part of the mesh covers the way (its silhouette
    is not this part's) or the boundary is farther than ``reach_px``, the view does not count. A
    vertex's distance is the median over its views; beyond ``tolerance_px`` it becomes an outward
    move of ``gain`` times the excess (in the ground sampling distance), which is spread over the
    mesh by ``spread`` steps of a normalized neighbour average (the shoulders between the rims move
    with them) and applied along the vertex normals.

    The distances include the rim's own inset (a vertex at ``|n . d| = c`` on a sphere of R pixels
    projects ``R (1 - sqrt(1 - c^2))`` inside its outline), which the true surface has too: on the
    ground-truth meshes of the captures measured, a fit at the defaults moves 0.04-0.05 px on average
    (README, "Shoulders inside the silhouettes"); ``gain`` 0.5 keeps that small.

    Masks drawn generously (dilated for safety, or a segmenter that bleeds) reach past every rim, and
    the fit would push the whole surface out by their margin: on the path-traced bunny a mask dilated
    by one pixel took the accuracy from 0.089 to 0.149e-2. Silhouettes alone cannot tell a margin of
    the masks from a surface that lies inside them everywhere; the offset scans fix such a uniform
    offset from the images' agreement, and what is left for this fit is local. So by default the margin
    is estimated as the ``MARGIN_QUANTILE`` quantile of the vertices' distances (0 with exact masks,
    where part of every rim lies on its outline; 1 px with masks dilated by one pixel) and discounted
    from every distance; a known margin can be given instead (0 trusts the masks as drawn).

    Args:
        vertices, faces: the mesh (faces counter-clockwise seen from outside).
        cameras, masks: the registered views and their object masks (None, empty or full masks do not count).
        gain: the share of the measured excess that is moved (0: nothing moves).
        tolerance_px: how far inside a mask a rim may lie without moving.
        rim_cos: the largest ``|n . d|`` of a vertex counted as on a view's rim.
        reach_px: the farthest boundary followed.
        spread: neighbour-average steps that carry the rims' moves to the vertices around them.
        mask_margin_px: how far the masks reach past the true outline (pixels; 0: exact masks), or None to
            estimate it from the rims.

    Returns:
        :class:`RimFit`.

    Raises:
        ConfigError: options out of range or mismatched inputs.
    """
    if gain < 0.0 or tolerance_px < 0.0 or not 0.0 < rim_cos < 1.0 or reach_px <= 0.0 or spread < 0:
        raise ConfigError(
            f"expected gain >= 0, tolerance_px >= 0, 0 < rim_cos < 1, reach_px > 0 and spread >= 0, got "
            f"{gain}, {tolerance_px}, {rim_cos}, {reach_px} and {spread}"
        )
    if mask_margin_px is not None and not 0.0 <= mask_margin_px < reach_px:
        raise ConfigError(f"expected 0 <= mask_margin_px < reach_px ({reach_px}) or None, got {mask_margin_px}")
    given_margin = 0.0 if mask_margin_px is None else mask_margin_px
    if len(cameras) != len(masks):
        raise ConfigError(f"{len(cameras)} cameras but {len(masks)} masks")
    v0 = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    n = len(v0)
    views = [
        (c, np.asarray(m, bool))
        for c, m in zip(cameras, masks, strict=True)
        if m is not None and np.any(m) and not np.all(m)
    ]
    if not views or n == 0 or gain == 0.0:
        return RimFit(v0.copy(), 0, 0, 0.0, 0.0, gain, tolerance_px, given_margin, False)
    normals = vertex_normals(v0, f).astype(np.float64)
    local = raycasting_scene(v0, f)
    scene, origin = local.scene, local.origin
    found_v, found_d, found_g = [], [], []
    for cam, mask in views:
        idx, inside, gsd = _rim_distances(v0, normals, scene, origin, cam, mask, rim_cos, reach_px)
        found_v.append(idx)
        found_d.append(inside)
        found_g.append(gsd)
    who = np.concatenate(found_v)
    if len(who) == 0:
        return RimFit(v0.copy(), 0, 0, 0.0, 0.0, gain, tolerance_px, given_margin, False)
    inside_px = np.concatenate(found_d)
    gsd_all = np.concatenate(found_g)
    order = np.argsort(who, kind="stable")
    who, inside_px, gsd_all = who[order], inside_px[order], gsd_all[order]
    starts = np.flatnonzero(np.r_[True, who[1:] != who[:-1]])
    rims = who[starts]
    median_px = grouped_medians(inside_px, starts)
    median_gsd = grouped_medians(gsd_all, starts)
    estimate = max(float(np.quantile(median_px, MARGIN_QUANTILE)), 0.0)
    margin = estimate if mask_margin_px is None else given_margin
    excess = median_px - margin - tolerance_px
    move = np.zeros(n)
    weight = np.zeros(n)
    move[rims] = gain * np.maximum(excess, 0.0) * median_gsd
    weight[rims] = 1.0
    edges = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    edges = np.concatenate([edges, edges[:, ::-1]])
    degree = np.bincount(edges[:, 0], minlength=n).astype(np.float64)
    safe = np.maximum(degree, 1.0)

    def average(x: np.ndarray) -> np.ndarray:
        return 0.5 * x + 0.5 * np.bincount(edges[:, 0], weights=x[edges[:, 1]], minlength=n) / safe

    num, den = move * weight, weight
    for _ in range(spread):
        num, den = average(num), average(den)
    spread_move = np.where(den > 1e-3, num / np.maximum(den, 1e-12), 0.0)
    gsd_mean = float(np.median(median_gsd))
    px = spread_move / max(gsd_mean, 1e-300)
    return RimFit(
        vertices=v0 + spread_move[:, None] * normals,
        rim_vertices=len(rims),
        inside=int((excess > 0.0).sum()),
        mean_move_px=float(px.mean()),
        max_move_px=float(px.max()),
        gain=gain,
        tolerance_px=tolerance_px,
        mask_margin_px=margin,
        margin_estimated=mask_margin_px is None,
        margin_estimate_px=estimate,
    )
