"""Cleaning and evening out triangle meshes: one manifold component, no slivers, bounded face sizes.

* :func:`clean_mesh`: degenerate and duplicated faces, non-manifold edges and
  vertices and inconsistently oriented edges are removed, and of the connected
  components the largest and every one that enough dense points support are kept, except
  small ones inside the largest's convex hull (floaters, :data:`FLOATER_MAX_SHARE`)
  (:func:`clean_topology`); then slivers (a smallest
  interior angle below a threshold) are repaired by :func:`remove_slivers`:
  a *cap* (an angle of at least 120 degrees) by flipping its longest edge, a
  *needle* by collapsing its shortest edge to the midpoint. Both operations
  keep the mesh manifold: a flip needs the new edge to be absent and both new
  triangles to keep the old orientation and improve the smallest angle; a
  collapse needs the link condition (the edge's endpoints share exactly its two
  opposite vertices) and no surrounding triangle to fold over. Slivers that
  cannot be repaired (at the boundary) are deleted and the topology cleaned again.
* :func:`orient_outward`: faces flipped to agree with oriented points' normals.
* :func:`bisect_faces`, :func:`split_large_faces`: conforming longest-edge
  bisection until no face projects larger than a given area in the views it faces.

Faces are (F, 3) int64, counter-clockwise seen from outside.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pmvir.camera import Camera
from pmvir.errors import ReconstructionError
from pmvir.geometry.mesh_ops import edge_topology, face_areas, face_normals
from pmvir.geometry.projection import project_points

_EPS = 1e-12
#: A component besides the largest is a floater, and removed whatever its support, when fewer than this
#: share of the largest's support points lie nearest to it and it lies wholly inside the largest's
#: convex hull: stereo's consistent mistakes in a cavity (a path-traced glossy mug, 36 views of 612x512:
#: a 596-vertex lump inside its opening with 422 of 157k fused points, 6 % of the diagonal from the
#: surface). A part of the object that broke off its body lies outside the body's hull or holds more.
FLOATER_MAX_SHARE = 0.01
#: A sliver whose largest angle is at least this is a cap (repaired by an edge flip), else a needle.
CAP_ANGLE = 2.0 * np.pi / 3.0


def o3d_mesh(vertices: np.ndarray, faces: np.ndarray):
    """An ``open3d.geometry.TriangleMesh`` of (N, 3) vertices and (F, 3) faces."""
    import open3d as o3d

    return o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(np.asarray(vertices, np.float64)),
        o3d.utility.Vector3iVector(np.asarray(faces, np.int32)),
    )


def mesh_arrays(mesh) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (N, 3) float64, faces (F, 3) int64) copied out of an Open3D triangle mesh."""
    return np.asarray(mesh.vertices, np.float64).copy(), np.asarray(mesh.triangles, np.int64).copy()


def _keep_components(mesh, support: np.ndarray | None, min_support: int) -> list[dict[str, object]]:
    """Remove components in place: without ``support`` all but the largest; with it, those that fewer
    than ``min_support`` of the support points lie nearest to, and with ``min_support`` > 0 the
    floaters (:data:`FLOATER_MAX_SHARE`); the largest is always kept.

    Returns:
        Per component (largest first): faces, supporting points, kept, and why.
    """
    clusters, counts, _ = mesh.cluster_connected_triangles()
    clusters, counts = np.asarray(clusters), np.asarray(counts)
    if len(clusters) == 0:
        return []
    largest = int(np.argmax(counts))
    votes = np.zeros(len(counts), np.int64)
    vertices = np.asarray(mesh.vertices, np.float64)
    vertex_cluster = np.full(len(vertices), -1, np.int64)
    vertex_cluster[np.asarray(mesh.triangles).ravel()] = np.repeat(clusters, 3)
    if support is not None and len(support):
        from scipy.spatial import cKDTree

        used = np.flatnonzero(vertex_cluster >= 0)
        _, nearest = cKDTree(vertices[used]).query(support, k=1)
        votes = np.bincount(vertex_cluster[used[nearest]], minlength=len(counts))
    report = []
    keep = np.zeros(len(counts), bool)
    hull = None  # the largest component's convex hull, built when a floater candidate needs it
    for c in np.argsort(-counts):
        if c == largest:
            ok, why = True, "largest component"
        elif support is None:
            ok, why = False, "not the largest (no support points given)"
        else:
            ok = bool(votes[c] >= min_support)
            why = f"{votes[c]} fused points {'>=' if ok else '<'} min_component_points {min_support}"
            if ok and min_support > 0 and votes[c] < FLOATER_MAX_SHARE * votes[largest]:
                hull = _hull_planes(vertices[vertex_cluster == largest]) if hull is None else hull
                if _inside_hull(hull, vertices[vertex_cluster == c]):
                    ok = False
                    why = (f"a floater: {votes[c]} fused points, under {FLOATER_MAX_SHARE:.0%} of the largest "
                           "component's, inside its convex hull")
        keep[c] = ok
        report.append({"faces": int(counts[c]), "points": int(votes[c]), "kept": ok, "why": why})
    mesh.remove_triangles_by_mask(~keep[clusters])
    mesh.remove_unreferenced_vertices()
    return report


def _hull_planes(points: np.ndarray) -> np.ndarray | None:
    """(H, 4) the facet planes (outward normal, offset) of the points' convex hull, or None when they
    have none (flat or too few points)."""
    from scipy.spatial import ConvexHull, QhullError

    try:
        return np.asarray(ConvexHull(points).equations)
    except (QhullError, ValueError):
        return None


def _inside_hull(planes: np.ndarray | None, points: np.ndarray) -> bool:
    """Whether every point lies inside (or on) the convex hull of facet ``planes``."""
    if planes is None or not len(points):
        return False
    return bool(np.all(points @ planes[:, :3].T + planes[:, 3] <= 1e-9))


def corner_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F, 3) float64 interior angle at each corner ``faces[:, k]``, radians."""
    p = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]  # (F, 3, 3)
    out = np.empty(p.shape[:2])
    for k in range(3):
        a = p[:, (k + 1) % 3] - p[:, k]
        b = p[:, (k + 2) % 3] - p[:, k]
        cos = (a * b).sum(1) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), _EPS)
        out[:, k] = np.arccos(np.clip(cos, -1.0, 1.0))
    return out


def triangle_min_angles(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) float64 smallest interior angle of each triangle, radians (0 for degenerate ones)."""
    return corner_angles(vertices, faces).min(axis=1)


class _Rows:
    """Rows of a compressed sparse layout: ``rows(i)`` is the values of key i."""

    def __init__(self, values: np.ndarray, starts: np.ndarray):
        self.values, self.starts = values, starts

    def __call__(self, i: int) -> np.ndarray:
        return self.values[self.starts[i] : self.starts[i + 1]]


def _csr(keys: np.ndarray, values: np.ndarray, n: int) -> tuple[np.ndarray, np.ndarray]:
    """Compressed rows: ``values[order][starts[i]:starts[i + 1]]`` are the values with key i."""
    order = np.argsort(keys, kind="stable")
    starts = np.searchsorted(keys[order], np.arange(n + 1))
    return values[order], starts


def _third(face: np.ndarray, a: int, b: int) -> int:
    return int(face[(face != a) & (face != b)][0])


def _min_angle(p: np.ndarray) -> float:
    """Smallest interior angle of one triangle given as (3, 3) corner positions, radians."""
    best = np.pi
    for k in range(3):
        x, y = p[(k + 1) % 3] - p[k], p[(k + 2) % 3] - p[k]
        c = float(x @ y) / max(float(np.sqrt((x @ x) * (y @ y))), _EPS)
        best = min(best, float(np.arccos(min(max(c, -1.0), 1.0))))
    return best


def _normal(p: np.ndarray) -> np.ndarray:
    return np.cross(p[..., 1, :] - p[..., 0, :], p[..., 2, :] - p[..., 0, :])


def _try_flip(
    v: np.ndarray,
    f: np.ndarray,
    f0: int,
    f1: int,
    a: int,
    b: int,
    c0: int,
    c1: int,
    c0_nbrs: np.ndarray,
    ang: np.ndarray,
) -> bool:
    """Flip edge a-b of faces f0 = (a, b, c0), f1 = (b, a, c1) to c0-c1 in place, if valid and better."""
    if c1 in c0_nbrs:
        return False  # the new edge exists already
    new = np.array([[a, c1, c0], [c1, b, c0]])
    old_n = _normal(v[f[[f0, f1]]]).sum(0)
    if (_normal(v[new]) @ old_n <= 0).any():
        return False  # the quad is not convex: the flip would fold it
    if min(_min_angle(v[t]) for t in new) <= min(ang[f0].min(), ang[f1].min()):
        return False
    f[f0], f[f1] = new[0], new[1]
    return True


def _try_collapse(
    v: np.ndarray,
    f: np.ndarray,
    f0: int,
    f1: int,
    a: int,
    b: int,
    c0: int,
    c1: int,
    nbrs: _Rows,
    vfaces: _Rows,
    remap: np.ndarray,
) -> bool:
    """Collapse edge a-b in place (b into a; to the midpoint, else an end) if that is valid.

    Valid: the link condition holds and no surrounding triangle folds over or vanishes.
    """
    if set(nbrs(a).tolist()) & set(nbrs(b).tolist()) != {c0, c1}:
        return False  # link condition
    ring = np.array(sorted((set(vfaces(a).tolist()) | set(vfaces(b).tolist())) - {f0, f1}), np.int64)
    tri = f[ring]
    before = _normal(v[tri])
    moved = np.isin(tri, [a, b])
    for target in (0.5 * (v[a] + v[b]), v[a].copy(), v[b].copy()):  # midpoint, else either end
        p = v[tri]
        p[moved] = target
        after = _normal(p)
        if ((before * after).sum(1) > 0).all() and (np.linalg.norm(after, axis=1) > _EPS).all():
            break  # no surrounding triangle folds over or vanishes
    else:
        return False
    v[a] = target
    remap[b] = a
    f[ring] = np.where(tri == b, a, tri)
    return True


def remove_slivers(
    vertices: np.ndarray, faces: np.ndarray, *, min_angle_deg: float = 2.0, max_passes: int = 8
) -> tuple[np.ndarray, np.ndarray, int]:
    """Repair slivers by edge flips (caps) and link-checked edge collapses (needles).

    Each pass repairs a set of slivers whose neighbourhoods do not overlap (module
    docstring); passes repeat until no sliver is left, none could be repaired, or
    ``max_passes``. The mesh stays manifold and keeps its orientation.

    Args:
        vertices: (N, 3) float. faces: (F, 3) int, an edge-manifold, consistently oriented mesh.
        min_angle_deg: a face whose smallest angle is below this is a sliver.
        max_passes: most passes.

    Returns:
        vertices (N', 3) float64 (unreferenced ones dropped), faces (F', 3) int64 and the
        number of repair operations applied.
    """
    v = np.asarray(vertices, np.float64).copy()
    f = np.asarray(faces, np.int64).copy()
    thr = np.radians(min_angle_deg)
    repaired = 0
    for _ in range(max_passes):
        ang = corner_angles(v, f)
        bad = np.flatnonzero(ang.min(1) < thr)
        if len(bad) == 0:
            break
        n = len(v)
        topo = edge_topology(f, n)
        nbrs = _Rows(
            *_csr(
                np.concatenate([topo.edges[:, 0], topo.edges[:, 1]]),
                np.concatenate([topo.edges[:, 1], topo.edges[:, 0]]),
                n,
            )
        )
        vfaces = _Rows(*_csr(f.ravel(), np.repeat(np.arange(len(f)), 3), n))
        locked = np.zeros(n, bool)
        alive = np.ones(len(f), bool)
        remap = np.arange(n)
        done = 0
        for fi in bad[np.argsort(ang[bad].min(1))]:
            if locked[f[fi]].any():
                continue
            k_max, k_min = int(np.argmax(ang[fi])), int(np.argmin(ang[fi]))
            # a cap's longest edge is flipped, a needle's shortest collapsed; each falls back on the other
            ops = ("flip", "collapse") if ang[fi, k_max] >= CAP_ANGLE else ("collapse", "flip")
            for op in ops:
                k = k_max if op == "flip" else k_min
                e = topo.face_edges[fi, (k + 1) % 3]  # the edge opposite corner k
                if not topo.interior[e]:
                    continue
                a, b = (int(x) for x in topo.edges[e])
                f0, f1 = (int(x) for x in topo.edge_faces[e])  # f0 holds a -> b, f1 holds b -> a
                c0, c1 = _third(f[f0], a, b), _third(f[f1], a, b)
                if locked[[a, b, c0, c1]].any():
                    break
                if op == "flip" and _try_flip(v, f, f0, f1, a, b, c0, c1, nbrs(c0), ang):
                    locked[[a, b, c0, c1]] = True
                    done += 1
                    break
                if op == "collapse" and _try_collapse(v, f, f0, f1, a, b, c0, c1, nbrs, vfaces, remap):
                    alive[[f0, f1]] = False
                    locked[np.concatenate([[a, b], nbrs(a), nbrs(b)])] = True
                    done += 1
                    break
        if done == 0:
            break
        repaired += done
        f = remap[f[alive]]
    used = np.zeros(len(v), bool)
    used[f.ravel()] = True
    index = np.cumsum(used) - 1
    return v[used], index[f], repaired


def clean_topology(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    max_passes: int = 6,
    support: np.ndarray | None = None,
    min_support: int = 0,
    components: list[dict[str, object]] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Supported connected components, edge- and vertex-manifold and consistently oriented.

    Each pass removes degenerate and duplicated faces, faces on non-manifold or
    inconsistently oriented edges, faces around non-manifold vertices and the
    components that are not kept: without ``support`` every one but the largest; with
    ``support`` ((P, 3) points, e.g. the fused dense points), those nearest to fewer
    than ``min_support`` of them and, with ``min_support`` > 0, the floaters
    (:data:`FLOATER_MAX_SHARE`; the largest always stays). Passes repeat until
    nothing changes. ``components``, when given, receives the last pass's per-component
    report (faces, supporting points, kept, why) and the components earlier passes removed.

    Raises:
        ReconstructionError: nothing is left.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    for _ in range(max_passes):
        mesh = o3d_mesh(v, f)
        mesh.remove_degenerate_triangles()
        mesh.remove_duplicated_triangles()
        mesh.remove_non_manifold_edges()
        bad_v = np.asarray(mesh.get_non_manifold_vertices())
        if len(bad_v):
            mesh.remove_triangles_by_mask(np.isin(np.asarray(mesh.triangles), bad_v).any(1))
        v2, f2 = mesh_arrays(mesh)
        if len(f2):
            topo = edge_topology(f2, len(v2))
            bad_e = ~topo.interior & ~topo.boundary  # two faces in the same direction, or more than two
            if bad_e.any():
                mesh.remove_triangles_by_mask(bad_e[topo.face_edges].any(1))
        report = _keep_components(mesh, support, min_support)
        if components is not None:  # this pass's components, and those an earlier pass removed
            components[:] = report + [r for r in components if not r["kept"]]
        mesh.remove_unreferenced_vertices()
        v2, f2 = mesh_arrays(mesh)
        if len(f2) == 0:
            raise ReconstructionError("surface cleaning removed every triangle (no manifold surface left)")
        # Stable when another pass would remove nothing: it adds no degenerate or duplicated faces,
        # and a kept component only gains support points, so manifold edges and vertices with
        # consistent orientation are enough (the pass that used to confirm it is not run).
        topo = edge_topology(f2, len(v2))
        stable = (
            bool(np.all(topo.interior | topo.boundary))
            and mesh.is_edge_manifold(allow_boundary_edges=True)
            and mesh.is_vertex_manifold()
        )
        v, f = v2, f2
        if stable:
            break
    return v, f


def clean_mesh(
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    min_angle_deg: float = 2.0,
    max_rounds: int = 3,
    support: np.ndarray | None = None,
    min_support: int = 0,
    components: list[dict[str, object]] | None = None,
) -> tuple[np.ndarray, np.ndarray, int]:
    """One manifold component without slivers (module docstring).

    Args:
        vertices: (N, 3) float. faces: (F, 3) int.
        min_angle_deg: sliver threshold, degrees (0: slivers are kept).
        max_rounds: most rounds of topology cleaning, sliver repair and deletion of the
            slivers left.
        support, min_support, components: which components are kept, and the report of them
            (:func:`clean_topology`).

    Returns:
        vertices (N', 3) float64, faces (F', 3) int64, number of slivers repaired or deleted.

    Raises:
        ReconstructionError: nothing is left.
    """
    keep = {"support": support, "min_support": min_support, "components": components}
    v, f = clean_topology(vertices, faces, **keep)  # type: ignore[arg-type]
    count = 0
    for _ in range(max_rounds):
        if min_angle_deg <= 0:
            break
        v, f, n = remove_slivers(v, f, min_angle_deg=min_angle_deg)
        count += n
        left = triangle_min_angles(v, f) < np.radians(min_angle_deg)
        if not left.any():
            break
        count += int(left.sum())
        v, f = clean_topology(v, f[~left], **keep)  # type: ignore[arg-type]
    return v, f, count


def facing_projected_areas(vertices: np.ndarray, faces: np.ndarray, cameras: Sequence[Camera]) -> np.ndarray:
    """(F,) float64 largest projected area (pixels^2) of each face over the views it faces.

    A face counts in a view when it lies in front of the camera, its centroid projects
    inside the image and its normal points towards the camera; occlusion is ignored
    (an occluded face may be over-estimated, never under-estimated among the views it faces).
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    i0, i1, i2 = (np.ascontiguousarray(f[:, k]) for k in range(3))
    n = face_normals(v, f, normalize=False)
    nc = (n * (v[i0] + v[i1] + v[i2]) / 3.0).sum(1)  # n . centroid
    best = np.zeros(len(f))
    for cam in cameras:
        uv, z = project_points(cam, v)
        u, w = np.ascontiguousarray(uv[:, 0]), np.ascontiguousarray(uv[:, 1])
        u0, u1, u2, w0, w1, w2 = u[i0], u[i1], u[i2], w[i0], w[i1], w[i2]
        cu, cw = (u0 + u1 + u2) / 3.0, (w0 + w1 + w2) / 3.0
        ok = (z[i0] > 0) & (z[i1] > 0) & (z[i2] > 0)
        ok &= (cu >= 0) & (cu < cam.width) & (cw >= 0) & (cw < cam.height)
        ok &= n @ cam.center - nc > 0  # n . (centre - centroid) > 0: facing the camera
        area = 0.5 * np.abs((u1 - u0) * (w2 - w0) - (w1 - w0) * (u2 - u0))
        np.maximum(best, np.where(ok, area, 0.0), out=best)
    return best


def bisect_faces(
    vertices: np.ndarray, faces: np.ndarray, split: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One conforming longest-edge bisection pass (Rivara) of the faces marked in ``split``.

    The longest edge of every marked face is cut at its midpoint; a face with a cut edge
    also gets its own longest edge cut (repeated until stable), so every face is split by
    one of three templates that always include its longest edge: 1-to-2, 1-to-3 or
    1-to-4. The mesh stays conforming (no T-junctions) and keeps its orientation.

    Args:
        vertices: (N, 3) float. faces: (F, 3) int, counter-clockwise. split: (F,) bool.

    Returns:
        vertices (N + cut edges, 3) float64 (the input ones first), faces (F', 3) int64 and
        parent (F',) int64, the input face each output face lies in.
    """
    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    topo = edge_topology(f, len(v))
    fe = topo.face_edges  # (F, 3): edge k runs f[k] -> f[k + 1]
    length = np.linalg.norm(v[topo.edges[:, 1]] - v[topo.edges[:, 0]], axis=1)
    longest = np.argmax(length[fe], axis=1)  # (F,) local index of each face's longest edge
    longest_edge = fe[np.arange(len(f)), longest]
    cut = np.zeros(topo.n_edges, bool)
    cut[longest_edge[np.asarray(split, bool)]] = True
    while True:
        touched = cut[fe].any(1)
        need = touched & ~cut[longest_edge]
        if not need.any():
            break
        cut[longest_edge[need]] = True
    mid_id = np.full(topo.n_edges, -1, np.int64)
    mid_id[cut] = len(v) + np.arange(int(cut.sum()))
    mids = 0.5 * (v[topo.edges[cut, 0]] + v[topo.edges[cut, 1]])
    # roll each face so its longest edge is local edge 0: (a, b, c) with a -> b longest
    roll = (np.arange(3)[None, :] + longest[:, None]) % 3
    rf = np.take_along_axis(f, roll, 1)
    re = np.take_along_axis(fe, roll, 1)
    c = cut[re]  # (F, 3)
    a, b, cc = rf[:, 0], rf[:, 1], rf[:, 2]
    m0, m1, m2 = mid_id[re[:, 0]], mid_id[re[:, 1]], mid_id[re[:, 2]]
    one = c[:, 0] & ~c[:, 1] & ~c[:, 2]
    bc = c[:, 0] & c[:, 1] & ~c[:, 2]  # longest and b -> c
    ca = c[:, 0] & ~c[:, 1] & c[:, 2]  # longest and c -> a
    al = c[:, 0] & c[:, 1] & c[:, 2]
    pieces: list[tuple[np.ndarray, list[np.ndarray | tuple[np.ndarray, ...]]]] = [
        (~c[:, 0], [f]),  # untouched (a face with any cut edge has its longest edge cut)
        (one, [(a, m0, cc), (m0, b, cc)]),
        (bc, [(a, m0, cc), (m0, b, m1), (m0, m1, cc)]),
        (ca, [(m0, b, cc), (a, m0, m2), (m0, cc, m2)]),
        (al, [(a, m0, m2), (m0, b, m1), (m2, m1, cc), (m0, m1, m2)]),
    ]
    out, parent = [], []
    ids = np.arange(len(f))
    for sel, tris in pieces:
        for tri in tris:
            t = tri if isinstance(tri, np.ndarray) else np.stack(tri, 1)
            out.append(t[sel])
            parent.append(ids[sel])
    return np.concatenate([v, mids]), np.concatenate(out).astype(np.int64), np.concatenate(parent)


def split_large_faces(
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    *,
    max_area_px: float,
    max_passes: int = 12,
) -> tuple[np.ndarray, np.ndarray]:
    """Bisect faces (:func:`bisect_faces`) until none projects larger than ``max_area_px`` in a view it faces.

    Evens out triangle sizes in image space before the uniform sqrt(3) subdivision, whose
    number of steps the largest triangle decides. Projected areas
    (:func:`facing_projected_areas`) are propagated while splitting (a piece of a split face
    gets its parent's area times its share of the parent's surface area) and recomputed
    exactly when no face is left above the threshold, until none is (or ``max_passes``
    bisection passes in all).

    Returns:
        vertices (N', 3) float64, faces (F', 3) int64.
    """
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    passes = 0
    while passes < max_passes:
        area_px = facing_projected_areas(v, f, cameras)  # exact; then propagated while splitting
        if not (area_px > max_area_px).any():
            break
        while passes < max_passes:
            big = area_px > max_area_px
            if not big.any():
                break
            parent_world = face_areas(v, f)
            v, f, parent = bisect_faces(v, f, big)
            share = face_areas(v, f) / np.maximum(parent_world[parent], _EPS)
            area_px = area_px[parent] * share
            passes += 1
    return v, f


def orient_outward(
    vertices: np.ndarray, faces: np.ndarray, points: np.ndarray, normals: np.ndarray
) -> np.ndarray:
    """Faces flipped, if need be, so their normals agree with the nearest oriented points' normals."""
    from scipy.spatial import cKDTree

    if len(faces) == 0 or len(points) == 0:
        return faces
    fn = face_normals(vertices, faces)
    centroids = np.asarray(vertices)[faces].mean(1)
    _, idx = cKDTree(points).query(centroids, k=1)
    agree = float((face_areas(vertices, faces) * (fn * normals[idx]).sum(1)).sum())
    return faces[:, ::-1].copy() if agree < 0 else faces
