"""Surface the views see through: Poisson's fill across an object's openings, cut with the stereo depths.

Masks drawn without given ones (:mod:`pmvir.geometry.silhouette.isolate`) cover what the object's
points and the columns below them cover, and on a sparse support (a path-traced table, a
turntable's top) that covers a knot's loops or a mug's handle. Screened Poisson then closes the
opening with a membrane that stays within the trimming distance of the few points stereo left
there. No view's depth lies on that membrane, and the views that look through the opening see
the table or the object's far side behind it.

:func:`seen_through` asks every view that sees a vertex (facing it, and not hidden by the surface
itself: a ray cast from the camera) what its own stereo depth at the vertex's pixel holds:

* **at**: a depth within ``margin`` of the vertex's;
* **past**: a depth more than ``margin`` beyond it (the view sees something behind the surface);
* depths in front of the vertex (an occluder the surface lacks) and pixels without a depth do not vote.

Both counts are averaged over the vertex's neighbourhood (:data:`ROUNDS` rounds of 1-ring means, so a
patch votes, not a pixel), and a vertex is seen through where its averaged *at* count is below
:data:`MAX_AT` and its *past* count at least :data:`MIN_PAST`. A vertex of the object's own surface
keeps the views whose depth lands on it, even where stereo errs in others (a textureless mug: about
as many wrong depths behind its wall as right ones on it), so the rule asks for no support at all,
not for a majority. Where a vertex lies farther than :data:`UNSUPPORTED_SPACINGS` point spacings from
every fused point, no views agreed on a depth there and Poisson alone placed it; there a majority
of the views seeing past it (*past* above *at*) is enough. A membrane at the edge of a knot's
opening, on which one or two views' depths land by chance, goes with it, and so does a shadowed
foot that stereo left without points.
:func:`cut_seen_through` removes those vertices with their faces and cleans the rest
(:func:`~pmvir.geometry.surface.clean.clean_mesh`), keeping every piece.

The depths cannot tell the table's own surface from the object's where a sheet lies on the table: under
a knot's centre Poisson keeps a flat patch of the support, and every view's depth lands on it.
:func:`lying_on_support` finds it by its place instead: a vertex within the support's band (where the
isolation takes dense points for the table's) whose normal points away from the plane (within
:data:`SHEET_MIN_COS` of it). An object's own surface in that band is its foot: facing sideways or down.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import scipy.sparse as sp
from scipy.spatial import cKDTree

from pmvir.geometry.mesh_ops import edge_topology, raycasting_scene, vertex_normals
from pmvir.geometry.mvs.fusion import depth_at
from pmvir.geometry.surface.clean import clean_mesh
from pmvir.geometry.surface.initial import _keep_vertices

if TYPE_CHECKING:
    from pmvir.geometry.mvs.sweep import DepthMap

#: A depth within this many point spacings of a vertex's lies on it (the margin the geometric stage
#: passes): on 36 views of 612x512, a knot on a turntable (path-traced) kept 0.22 % of its initial
#: surface's vertices farther than 2 % of the diagonal with 2.5 (2.26 % uncut; 0.20 % with 2, 0.24 %
#: with 3), and a textureless mug's completeness went from 1.09e-2 to 1.14e-2 (1.17e-2 with 2).
MARGIN_SPACINGS = 2.5
#: Rounds of 1-ring averaging of the per-vertex counts (on 36 views of 612x512, an initial surface of
#: about 70k vertices: a patch a few tube radii across on a knot).
ROUNDS = 20
#: A vertex is seen through where fewer than this many views (averaged) have their depth on it ...
MAX_AT = 1.0
#: ... and at least this many (averaged) see past it.
MIN_PAST = 2.0
#: A vertex farther than this many point spacings from every fused point is cut where more views see
#: past it than lie on it. The vertices Poisson bulges out where stereo left a knot's underside
#: without points lie 3.4-5 spacings from the nearest point and 2.0-2.8 % of the diagonal off the
#: object. On 36 views of 612x512 (built-in renderer) the initial surface's vertices farther than 2 %
#: of the diagonal, with 3.5 spacings: a knot on a table 1 (21 with 5), on a turntable 3 (60 with 5);
#: accuracy and completeness per shape on the benchmarks page.
UNSUPPORTED_SPACINGS = 3.5
#: A cut that would take more than this share of the vertices is not made: stereo failed, the
#: surface did not close an opening.
MAX_CUT_SHARE = 0.5
#: A vertex in the support's band lies on the support where the cosine between its normal and the
#: plane's is at least this (45 degrees). Built-in knot on a turntable, 36 views of 612x512: the
#: vertices farther than 2 % of the diagonal 0.46 % -> 0.13 % (0.12 % with 0.5, 0.16 % with 0.85),
#: completeness as before.
SHEET_MIN_COS = 0.7


@dataclass(frozen=True)
class SeenThrough:
    """Per-vertex votes of the views' stereo depths on a surface.

    Attributes:
        at: (N,) float64 views whose depth lies on the vertex (averaged over its neighbourhood).
        past: (N,) float64 views whose depth lies past it (averaged likewise).
        through: (N,) bool the vertices seen through (``at < MAX_AT`` and ``past >= MIN_PAST``, or
            ``unsupported`` and ``past > at``).
        unsupported: (N,) bool the vertices farther than :data:`UNSUPPORTED_SPACINGS` spacings from
            every fused point (all False where none were given).
    """

    at: np.ndarray
    past: np.ndarray
    through: np.ndarray
    unsupported: np.ndarray


def seen_through(
    vertices: np.ndarray,
    faces: np.ndarray,
    depth_maps: Sequence[DepthMap | None],
    *,
    margin: float,
    rounds: int = ROUNDS,
    points: np.ndarray | None = None,
    spacing: float = 0.0,
) -> SeenThrough:
    """The views' votes on each vertex and the vertices they see through (module docstring).

    Args:
        vertices: (N, 3) float world positions. faces: (F, 3) int, counter-clockwise seen from outside.
        depth_maps: per view its stereo depth map (camera on its own grid) or None.
        margin: world units; a depth within it of a vertex's lies on the vertex, beyond it past it (> 0).
        rounds: rounds of 1-ring averaging of the counts (>= 0).
        points: (P, 3) the fused points, or None: no vertex is unsupported.
        spacing: their spacing, world units (:func:`~pmvir.geometry.silhouette.cluster.point_spacing`;
            0: no vertex is unsupported).

    Returns:
        :class:`SeenThrough`.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    at = np.zeros(len(v))
    past = np.zeros(len(v))
    if len(v) and len(f):
        import open3d as o3d

        scene = raycasting_scene(v, f)
        normals = vertex_normals(v, f)
        for dm in depth_maps:
            if dm is None:
                continue
            centre = dm.camera.center
            ray = v - centre
            distance = np.linalg.norm(ray, axis=1)
            direction = ray / np.maximum(distance, 1e-12)[:, None]
            rays = np.hstack([np.broadcast_to(scene.local(centre[None]), (len(v), 3)), direction.astype(np.float32)])
            hit = scene.scene.cast_rays(o3d.core.Tensor(np.ascontiguousarray(rays, np.float32)))["t_hit"].numpy()
            sees = (hit >= distance - 0.5 * margin) & ((direction * normals).sum(1) < 0.0)
            z, _, _, d = depth_at(dm, v)
            known = sees & (d > 0)
            at += known & (np.abs(d - z) <= margin)
            past += known & (d > z + margin)
    at, past = _neighbourhood_means(np.stack([at, past], 1), f, len(v), rounds).T
    unsupported = np.zeros(len(v), bool)
    if points is not None and len(points) and spacing > 0 and len(v):
        unsupported = cKDTree(np.asarray(points, np.float64)).query(v)[0] > UNSUPPORTED_SPACINGS * spacing
    through = ((at < MAX_AT) & (past >= MIN_PAST)) | (unsupported & (past > at))
    return SeenThrough(at=at, past=past, through=through, unsupported=unsupported)


def _neighbourhood_means(values: np.ndarray, faces: np.ndarray, n: int, rounds: int) -> np.ndarray:
    """``values`` (N, C) replaced ``rounds`` times by the mean over each vertex and its 1-ring."""
    out = np.asarray(values, np.float64)
    if rounds <= 0 or len(faces) == 0:
        return out
    edges = edge_topology(faces, n).edges
    rows = np.concatenate([edges[:, 0], edges[:, 1], np.arange(n)])
    cols = np.concatenate([edges[:, 1], edges[:, 0], np.arange(n)])
    ring = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    size = np.asarray(ring.sum(axis=1)).ravel()[:, None]
    for _ in range(rounds):
        out = ring @ out / size
    return out


def lying_on_support(vertices: np.ndarray, faces: np.ndarray, plane: np.ndarray, band: float) -> np.ndarray:
    """(N,) bool: the vertices less than ``band`` above ``plane`` ((4,) a, b, c, d with the unit normal
    toward the cameras; world units) whose normal points away from it (module docstring)."""
    v = np.asarray(vertices, np.float64)
    if not len(v) or not len(faces):
        return np.zeros(len(v), bool)
    normal = np.asarray(plane[:3], np.float64)
    height = v @ normal + float(plane[3])
    return np.asarray((height < band) & (vertex_normals(v, np.asarray(faces, np.int64)) @ normal >= SHEET_MIN_COS))


def cut_seen_through(
    vertices: np.ndarray,
    faces: np.ndarray,
    depth_maps: Sequence[DepthMap | None],
    *,
    margin: float,
    support: np.ndarray,
    min_angle_deg: float,
    sheet: np.ndarray | None = None,
    spacing: float = 0.0,
) -> tuple[np.ndarray, np.ndarray, int]:
    """The surface without the vertices the views see through, cleaned (module docstring).

    Every piece the cut leaves stays: the pieces it separates from the rest are not held to the
    initial surface's least support (``surface.min_component_points``). On a rock on a turntable
    (36 views of 612x512) such pieces at its shadowed foot, 5-139 vertices each, carried its
    completeness: 1.24e-2 with them, 1.38e-2 without.

    Args:
        vertices, faces, depth_maps, margin: as for :func:`seen_through`.
        support: (P, 3) the fused points (the cleaning's: :func:`~pmvir.geometry.surface.clean.clean_mesh`).
        min_angle_deg: the cleaning's sliver threshold, degrees.
        sheet: (N,) bool vertices cut as well (:func:`lying_on_support`), or None.
        spacing: the spacing of ``support``, world units; a vertex farther than
            :data:`UNSUPPORTED_SPACINGS` of them from it is cut where more views see past it than lie on it
            (0: only the votes decide).

    Returns:
        vertices (N', 3) float64, faces (F', 3) int64, and the number of vertices seen through (0 when
        none were, or when more than :data:`MAX_CUT_SHARE` of them were: then only ``sheet`` is cut; the
        surface is returned as given when neither cuts a vertex).
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    through = seen_through(v, f, depth_maps, margin=margin, points=support, spacing=spacing).through
    count = int(through.sum())
    if count > MAX_CUT_SHARE * len(v):
        through[:], count = False, 0
    cut = through if sheet is None else through | sheet
    if not cut.any():
        return v, f, 0
    v2, f2 = _keep_vertices(v, f, ~cut)
    v2, f2, _ = clean_mesh(v2, f2, min_angle_deg=min_angle_deg, support=support, min_support=0)
    return v2, f2, count
