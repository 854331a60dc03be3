"""sqrt(3) subdivision without smoothing (Kobbelt 2000), driven by projected area.

One step (:func:`sqrt3_subdivide`) inserts a vertex at the centroid of every
face, joins it to the face's corners and flips every original interior edge, so
that each new edge joins the centroids of two adjacent faces: F faces become 3F
on a closed mesh. Boundaries follow Kobbelt's two-step rule: an odd step leaves
boundary edges unflipped (the boundary triangle is split 1-to-3); an even step
leaves the triangle beside each boundary edge without a centroid, cuts the
boundary edge in three and joins the two cut points to the triangle's inner
vertex. Two steps thus split every boundary edge in three, like the interior.

Unlike Kobbelt, old vertices are NOT relaxed and new ones are NOT smoothed:
pmvir subdivides only to densify the surface that the refinement moves. One step
puts every new vertex on a face of its input (centroid, or point on a boundary
edge). A flipped edge, though, is a chord across the crease between two input
faces, so from the second step on a centroid lies slightly off the input
surface; :func:`subdivide_until` therefore projects every new vertex onto the
closest point of the mesh it was given, and the result's vertices all lie on it.
Edges used by more than two faces, or by two faces traversing them in the same
direction (inconsistent orientation), are never flipped and never cut (their faces are split 1-to-3 around them), so such
meshes stay conforming.

:func:`subdivide_until` repeats uniform steps until the largest projected
area of a triangle, over the views that see it, is below a threshold in pixels
(paper section 4.2). A new vertex takes its visibility from the face of the
input mesh it lies on ("according to the visibility of each mesh before the
subdivision"): visible in a view when enough of that face's corners are.
Deriving it from the previous step's triangle instead compounds: each step
would erode the visible region near silhouettes by one more ring of triangles.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from pmvir.camera import Camera
from pmvir.config import GeometryOptions
from pmvir.errors import ConfigError, MeshError, ShapeError
from pmvir.geometry.mesh_ops import ReferenceSurface, check_vertices, edge_topology
from pmvir.geometry.projection import project_columns
from pmvir.geometry.visibility import face_visibility, vertex_visibility


@dataclass(frozen=True)
class Sqrt3Step:
    """The result of one sqrt(3) step.

    Attributes:
        vertices: (N + M, 3) float64; the first N are the input vertices, unmoved.
        faces: (F', 3) int64, counter-clockwise like the input.
        parents: (M, 3) int64 input vertex indices each new vertex is inserted
            between: the face's three corners for a centroid, the two ends of the
            boundary edge (third column -1) for a boundary cut point.
    """

    vertices: np.ndarray
    faces: np.ndarray
    parents: np.ndarray


@dataclass(frozen=True)
class SubdivisionResult:
    """The result of :func:`subdivide_until`.

    Attributes:
        vertices: (N', 3) float64 (the input vertices first, unmoved).
        faces: (F', 3) int64, counter-clockwise like the input.
        visibility: (N', V) bool vertex visibility, inherited for new vertices.
        rounds: number of sqrt(3) steps applied.
        max_area_px: largest projected visible face area (pixels^2) of the result.
        converged: True when ``max_area_px`` is below the requested threshold;
            False when ``max_rounds`` or ``max_vertices`` stopped the loop first.
        before_last: (vertices, faces, visibility) of the mesh one step before the result
            (the coarse surface of ``refine.stages.coarse``); None when no step was applied.
    """

    vertices: np.ndarray
    faces: np.ndarray
    visibility: np.ndarray
    rounds: int
    max_area_px: float
    converged: bool
    before_last: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None


def sqrt3_subdivide(vertices: np.ndarray, faces: np.ndarray, *, split_boundary: bool = False) -> Sqrt3Step:
    """One uniform sqrt(3) step without smoothing.

    Args:
        vertices: (N, 3) float positions.
        faces: (F, 3) integer indices, counter-clockwise seen from outside.
        split_boundary: False for Kobbelt's odd step (boundary edges kept, their
            triangles split 1-to-3); True for the even step (boundary edges cut in
            three, their triangles get no centroid). The even step needs every
            face to have at most one boundary edge, which holds after an odd step.

    Returns:
        :class:`Sqrt3Step`. On a closed mesh F faces become 3F and N vertices N + F.

    Raises:
        MeshError: malformed faces, or ``split_boundary`` with a face having two or
            more boundary edges.
    """
    v = check_vertices(vertices)
    topo = edge_topology(faces, len(v))
    f = np.asarray(faces, dtype=np.int64)
    n_v, n_f = len(v), len(f)

    # Faces that get no centroid: those on a boundary edge, in an even step.
    on_boundary = topo.boundary[topo.face_edges]  # (F, 3)
    if split_boundary:
        if np.any(on_boundary.sum(axis=1) > 1):
            raise MeshError(
                "the even sqrt(3) boundary step needs at most one boundary edge per face; "
                "apply an odd step (split_boundary=False) first"
            )
        edge_face = on_boundary.any(axis=1)
    else:
        edge_face = np.zeros(n_f, dtype=bool)
    has_centroid = ~edge_face
    centroid_id = np.full(n_f, -1, dtype=np.int64)
    centroid_id[has_centroid] = n_v + np.arange(int(has_centroid.sum()))
    centroids = v[f[has_centroid]].mean(axis=1)
    parents = [f[has_centroid]]
    new_points = [centroids]

    out = []
    # Flip interior edges whose two faces both got a centroid.
    e0, e1 = topo.edge_faces[:, 0], topo.edge_faces[:, 1]
    flip = topo.interior.copy()
    flip[flip] = has_centroid[e0[flip]] & has_centroid[e1[flip]]
    a, b = topo.edges[flip, 0], topo.edges[flip, 1]  # face e0 holds a -> b, face e1 holds b -> a
    c1, c2 = centroid_id[e0[flip]], centroid_id[e1[flip]]
    out.append(np.stack([a, c2, c1], axis=1))
    out.append(np.stack([b, c1, c2], axis=1))

    # Half-edges of centroid faces whose edge is not flipped: triangle (a, b, centroid).
    he_face = np.repeat(np.arange(n_f), 3).reshape(n_f, 3)
    keep = has_centroid[:, None] & ~flip[topo.face_edges]
    src = f[keep]
    dst = f[:, [1, 2, 0]][keep]
    out.append(np.stack([src, dst, centroid_id[he_face[keep]]], axis=1))

    # Even step: cut each boundary edge in three and fan its face around the inner vertex.
    if split_boundary and np.any(edge_face):
        fb, kb = np.nonzero(on_boundary)
        a = f[fb, kb]
        b = f[fb, (kb + 1) % 3]
        x = f[fb, (kb + 2) % 3]
        first = n_v + len(centroids) + 2 * np.arange(len(fb))
        p, q = first, first + 1
        pa, pb = v[a], v[b]
        cuts = np.empty((2 * len(fb), 3), dtype=np.float64)
        cuts[0::2] = pa + (pb - pa) / 3.0
        cuts[1::2] = pa + 2.0 * (pb - pa) / 3.0
        new_points.append(cuts)
        par = np.full((2 * len(fb), 3), -1, dtype=np.int64)
        par[:, 0] = np.repeat(a, 2)
        par[:, 1] = np.repeat(b, 2)
        parents.append(par)
        out.append(np.stack([a, p, x], axis=1))
        out.append(np.stack([p, q, x], axis=1))
        out.append(np.stack([q, b, x], axis=1))

    new_vertices = np.concatenate([v, *new_points], axis=0)
    new_faces = np.concatenate(out, axis=0).astype(np.int64, copy=False)
    return Sqrt3Step(vertices=new_vertices, faces=new_faces, parents=np.concatenate(parents, axis=0))


def inherit_visibility(
    parent_vis: np.ndarray, parents: np.ndarray, *, min_visible_corners: int = 3
) -> np.ndarray:
    """Visibility of inserted vertices from the vertices they were inserted between.

    Args:
        parent_vis: (N, V) bool visibility of the input vertices.
        parents: (M, 3) int64 parent indices, -1 for an absent third parent.
        min_visible_corners: a centroid is visible in a view when at least this
            many of its 3 parents are; a boundary cut point when at least
            ``min(min_visible_corners, 2)`` of its 2 parents are.

    Returns:
        (M, V) bool.
    """
    if min_visible_corners not in (1, 2, 3):
        raise ConfigError(f"min_visible_corners must be 1, 2 or 3, got {min_visible_corners}")
    vis = np.asarray(parent_vis, dtype=bool)
    par = np.asarray(parents, dtype=np.int64)
    present = par >= 0
    gathered = vis[np.where(present, par, 0)] & present[:, :, None]  # (M, 3, V)
    count = gathered.sum(axis=1)
    need = np.minimum(min_visible_corners, present.sum(axis=1))
    return count >= need[:, None]


def projected_face_areas(
    vertices: np.ndarray, faces: np.ndarray, cameras: Sequence[Camera], face_visible: np.ndarray
) -> np.ndarray:
    """Largest projected area of each face over the views that see it.

    Args:
        vertices: (N, 3) float world positions.
        faces: (F, 3) integer indices.
        cameras: V cameras.
        face_visible: (F, V) bool.

    Returns:
        (F,) float64 area in pixels^2 (pinhole projection of the three corners);
        0 for a face visible in no view.
    """
    v = check_vertices(vertices)
    f = np.asarray(faces, dtype=np.int64)
    fvis = np.asarray(face_visible, dtype=bool)
    if fvis.shape != (len(f), len(cameras)):
        raise ShapeError(f"expected face_visible of shape {(len(f), len(cameras))}, got {fvis.shape}")
    best = np.zeros(len(f), dtype=np.float64)
    v_t = np.ascontiguousarray(v.T)
    for j, cam in enumerate(cameras):
        sel = np.flatnonzero(fvis[:, j])
        if len(sel) == 0:
            continue
        u, w, _ = project_columns(v_t, cam)
        corners = f[sel]
        uc, wc = u[corners], w[corners]  # (S, 3)
        du1, dw1 = uc[:, 1] - uc[:, 0], wc[:, 1] - wc[:, 0]
        du2, dw2 = uc[:, 2] - uc[:, 0], wc[:, 2] - wc[:, 0]
        area = 0.5 * np.abs(du1 * dw2 - dw1 * du2)
        best[sel] = np.maximum(best[sel], area)
    return best


def subdivide_until(
    vertices: np.ndarray,
    faces: np.ndarray,
    visibility: np.ndarray,
    cameras: Sequence[Camera],
    *,
    max_area_px: float,
    max_rounds: int,
    max_vertices: int,
    min_visible_corners: int = 3,
    project: bool = True,
) -> SubdivisionResult:
    """Uniform sqrt(3) steps until every visible triangle projects below ``max_area_px``.

    Before each step the face visibility is derived from the vertex visibility
    (a face is visible in a view when at least ``min_visible_corners`` corners
    are) and :func:`projected_face_areas` is computed. The loop stops when the
    largest area is below ``max_area_px`` (converged), after ``max_rounds``
    steps, or when the next step would exceed ``max_vertices`` vertices.
    Steps alternate odd/even for Kobbelt's boundary rule, starting odd. With
    ``project`` every new vertex is moved to the closest point of the input
    mesh (so all vertices stay on the input surface; the closest face is found
    globally, which could only pick a wrong sheet where two sheets are closer
    than a chord's sagitta). A new vertex is then visible in the views in
    which the input face it lies on is visible; without ``project`` it inherits
    from the previous step's triangle (:func:`inherit_visibility`), which
    erodes visibility near silhouettes by one ring of triangles per step.

    Args:
        vertices: (N, 3) float positions.
        faces: (F, 3) integer indices, counter-clockwise seen from outside.
        visibility: (N, V) bool vertex visibility (see :func:`vertex_visibility`).
        cameras: the V cameras.
        max_area_px: area threshold in pixels^2, > 0.
        max_rounds: most steps to apply, >= 0.
        max_vertices: most vertices the result may hold.
        min_visible_corners: 3 (default, conservative: a new vertex gets a view only
            where all corners of its face are visible), 2 or 1.
        project: move new vertices onto the input surface (default True).

    Returns:
        :class:`SubdivisionResult`.
    """
    v = check_vertices(vertices)
    f = np.asarray(faces, dtype=np.int64)
    vis = np.asarray(visibility, dtype=bool)
    if vis.shape != (len(v), len(cameras)):
        raise ShapeError(f"expected visibility of shape {(len(v), len(cameras))}, got {vis.shape}")
    if not max_area_px > 0:
        raise ConfigError(f"max_area_px must be > 0, got {max_area_px}")
    if max_rounds < 0:
        raise ConfigError(f"max_rounds must be >= 0, got {max_rounds}")
    surface = ReferenceSurface(v, f) if project and len(f) else None
    input_face_vis = face_visibility(f, vis, min_visible_corners=min_visible_corners)
    rounds = 0
    before: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None
    while True:
        fvis = face_visibility(f, vis, min_visible_corners=min_visible_corners)
        areas = projected_face_areas(v, f, cameras, fvis)
        largest = float(areas.max()) if len(areas) else 0.0
        if largest < max_area_px:
            return SubdivisionResult(v, f, vis, rounds, largest, True, before)
        split_boundary = rounds % 2 == 1
        if rounds >= max_rounds or _vertices_after_step(v, f, split_boundary) > max_vertices:
            return SubdivisionResult(v, f, vis, rounds, largest, False, before)
        before = (v, f, vis)  # a step makes new arrays: these stay as they are
        step = sqrt3_subdivide(v, f, split_boundary=split_boundary)
        v, f = step.vertices, step.faces
        if surface is not None:
            projected, on_face = surface.project(v[len(vis):])
            v[len(vis):] = projected
            new_vis = input_face_vis[on_face]
        else:
            new_vis = inherit_visibility(vis, step.parents, min_visible_corners=min_visible_corners)
        vis = np.concatenate([vis, new_vis], axis=0)
        rounds += 1


def densify_for_views(
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    masks: Sequence[np.ndarray | None] | None,
    options: GeometryOptions,
) -> SubdivisionResult:
    """Paper section 4.2 after surface reconstruction: visibility, then sqrt(3) subdivision.

    :func:`vertex_visibility` of the input mesh, then :func:`subdivide_until`,
    with the ``visibility`` and ``subdivision`` groups of ``options``.

    Args:
        vertices: (N, 3) float positions.
        faces: (F, 3) integer indices, counter-clockwise seen from outside.
        cameras: the V cameras.
        masks: None, or per view None or a bool (height, width) object mask.
        options: the pipeline's geometry options.

    Returns:
        :class:`SubdivisionResult` with the (N', V) visibility of the densified mesh.
    """
    vis = vertex_visibility(
        vertices,
        faces,
        cameras,
        masks,
        **options.visibility.model_dump(),
    )
    return subdivide_until(
        vertices,
        faces,
        vis,
        cameras,
        **options.subdivision.model_dump(),
    )


def _vertices_after_step(v: np.ndarray, f: np.ndarray, split_boundary: bool) -> int:
    """Vertex count after one step: a centroid per face, or two cuts per boundary edge instead."""
    if not split_boundary:
        return len(v) + len(f)
    n_boundary = int(edge_topology(f, len(v)).boundary.sum())
    # each boundary face loses its centroid and gains two cut points (one boundary edge per face)
    return len(v) + len(f) + n_boundary
