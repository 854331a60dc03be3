"""Triangle-mesh helpers (vectorized numpy): normals, edge topology, small measurements, ray casting.

* Normals: :func:`face_normals` and :func:`vertex_normals` (area-weighted).
* Ray casting: :func:`raycasting_scene`, the one way an Open3D ``RaycastingScene`` is built:
  the vertices are shifted to a local origin (by default their mean) before Open3D's float32
  cast, so precision follows the mesh's size, not its distance from the world origin.

Conventions: ``faces`` is (F, 3) int64, counter-clockwise seen from outside;
half-edge ``k`` of face ``f`` runs from ``faces[f, k]`` to ``faces[f, (k + 1) % 3]``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from pmvir.errors import InputError, MeshError, ShapeError


@dataclass(frozen=True)
class EdgeTopology:
    """Undirected edges of a triangle mesh and the faces beside them.

    Attributes:
        edges: (E, 2) int64 vertex indices, ``edges[:, 0] < edges[:, 1]``.
        face_edges: (F, 3) int64 edge index of each face's half-edge k (``f[k] -> f[k+1]``).
        edge_faces: (E, 2) int64 the first two faces using the edge, -1 where absent.
            For a manifold interior edge, ``edge_faces[e, 0]`` holds the half-edge
            ``edges[e, 0] -> edges[e, 1]`` and ``edge_faces[e, 1]`` the reverse one.
        edge_face_count: (E,) int64 number of faces using the edge.
        interior: (E,) bool exactly two faces, traversing the edge in opposite
            directions (consistently oriented, manifold).
        boundary: (E,) bool exactly one face.
    """

    edges: np.ndarray
    face_edges: np.ndarray
    edge_faces: np.ndarray
    edge_face_count: np.ndarray
    interior: np.ndarray
    boundary: np.ndarray

    @property
    def n_edges(self) -> int:
        return len(self.edges)


def check_vertices(vertices: np.ndarray) -> np.ndarray:
    """Validate vertex positions and return them as (N, 3) float64.

    Raises:
        ShapeError: wrong shape.
        InputError: NaN / infinite coordinates.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ShapeError(f"expected (N, 3) vertices, got shape {v.shape}")
    if not np.all(np.isfinite(v)):
        raise InputError("vertices contain NaN or infinity")
    return v


def check_faces(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Validate a face array and return it as (F, 3) int64.

    Raises:
        MeshError: wrong shape, indices out of ``[0, n_vertices)``, or a face that
            repeats a vertex (degenerate).
    """
    f = np.asarray(faces)
    if f.ndim != 2 or f.shape[1] != 3:
        raise MeshError(f"expected (F, 3) triangle indices, got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"expected integer face indices, got dtype {f.dtype}")
    f = f.astype(np.int64, copy=False)
    if len(f) and (f.min() < 0 or f.max() >= n_vertices):
        raise MeshError(f"face indices must lie in [0, {n_vertices}), got [{f.min()}, {f.max()}]")
    if np.any((f[:, 0] == f[:, 1]) | (f[:, 1] == f[:, 2]) | (f[:, 2] == f[:, 0])):
        raise MeshError("degenerate face: a triangle repeats a vertex index")
    return f


def edge_topology(faces: np.ndarray, n_vertices: int) -> EdgeTopology:
    """Build the undirected edge list and face adjacency of a triangle mesh.

    Args:
        faces: (F, 3) integer vertex indices.
        n_vertices: number of vertices N (all indices must be below it).

    Returns:
        The :class:`EdgeTopology`. Edges used by more than two faces, or by two
        faces with the same direction (inconsistent orientation), are neither
        ``interior`` nor ``boundary``.
    """
    f = check_faces(faces, n_vertices)
    n_faces = len(f)
    src = f.reshape(-1)  # half-edge h = 3 * face + k
    dst = f[:, [1, 2, 0]].reshape(-1)
    lo = np.minimum(src, dst)
    hi = np.maximum(src, dst)
    key = lo * np.int64(n_vertices) + hi
    order = np.argsort(key, kind="stable")
    key_sorted = key[order]
    first = np.ones(len(order), dtype=bool)
    first[1:] = key_sorted[1:] != key_sorted[:-1]
    starts = np.flatnonzero(first)
    counts = np.diff(np.append(starts, len(order)))
    edge_of_sorted = np.cumsum(first) - 1
    face_edges = np.empty(3 * n_faces, dtype=np.int64)
    face_edges[order] = edge_of_sorted
    h0 = order[starts]
    edges = np.stack([lo[h0], hi[h0]], axis=1)
    edge_faces = np.full((len(starts), 2), -1, dtype=np.int64)
    edge_faces[:, 0] = h0 // 3
    two = counts >= 2
    h1 = np.full(len(starts), -1, dtype=np.int64)
    h1[two] = order[starts[two] + 1]
    edge_faces[two, 1] = h1[two] // 3
    interior = counts == 2
    interior[interior] = src[h0[interior]] == dst[h1[interior]]  # opposite directions
    # Put the face holding edges[:, 0] -> edges[:, 1] first.
    swap = interior & (src[h0] != edges[:, 0])
    edge_faces[swap] = edge_faces[swap][:, ::-1]
    return EdgeTopology(
        edges=edges,
        face_edges=face_edges.reshape(n_faces, 3),
        edge_faces=edge_faces,
        edge_face_count=counts.astype(np.int64),
        interior=interior,
        boundary=counts == 1,
    )


def face_normals(
    vertices: np.ndarray, faces: np.ndarray, *, normalize: bool = True, eps: float = 1e-30
) -> np.ndarray:
    """(F, 3) float64 face normals (right-hand rule over the face's vertex order).

    With ``normalize=False`` the length is twice the triangle's area; normalized, lengths below
    ``eps`` are divided by ``eps`` (a degenerate face keeps a zero normal).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    # np.take gathers rows 2-4x faster than fancy indexing on large meshes
    a, b, c = (np.take(v, f[:, k], axis=0) for k in range(3))
    n = np.cross(b - a, c - a)
    if normalize:
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), eps)
    return n


def vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (the sum of adjacent face cross products), (N, 3) float64, unit."""
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    fn = face_normals(v, f, normalize=False)
    idx = f.reshape(-1)
    n = np.stack(
        [np.bincount(idx, weights=np.repeat(fn[:, c], 3), minlength=len(v)) for c in range(3)], axis=1
    )
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-20)


def grouped_medians(values: np.ndarray, starts: np.ndarray) -> np.ndarray:
    """The median of each run ``values[starts[i]:starts[i + 1]]`` (the last run to the end), (G,).

    The same as ``np.median`` per run (the mean of the two middle values of an even run), in
    one sort instead of one call per run.
    """
    values = np.asarray(values, dtype=np.float64)
    bounds = np.r_[starts, len(values)]
    group = np.repeat(np.arange(len(starts)), np.diff(bounds))
    ordered = values[np.lexsort((values, group))]
    size = np.diff(bounds)
    lo = ordered[starts + (size - 1) // 2]
    hi = ordered[starts + size // 2]
    return 0.5 * (lo + hi)


@dataclass(frozen=True)
class RaycastScene:
    """An Open3D ``RaycastingScene`` of a mesh held in coordinates relative to ``origin``.

    Attributes:
        scene: the ``open3d.t.geometry.RaycastingScene`` (float32, Embree).
        origin: (3,) the world point at the scene's zero; rays and query points go in through
            :meth:`local`, and hits come back relative to it.
    """

    scene: Any
    origin: np.ndarray

    def local(self, points: np.ndarray) -> np.ndarray:
        """``points - origin`` as contiguous float32, the scene's coordinates (same shape)."""
        return np.ascontiguousarray(np.asarray(points) - self.origin, dtype=np.float32)


def raycasting_scene(vertices: np.ndarray, faces: np.ndarray, *, origin: np.ndarray | None = None) -> RaycastScene:
    """Open3D's ray-casting scene of a triangle mesh, built from vertices shifted to a local origin.

    Args:
        vertices: (N, 3) float positions (their dtype is kept until the float32 cast).
        faces: (F, 3) integer indices; F = 0 gives an empty scene (every ray misses).
        origin: (3,) the local origin; None: the vertices' mean. The world origin (zeros) keeps
            world coordinates, as the offset scan and the synthetic renderer use.

    Returns:
        the scene and its origin.
    """
    import open3d as o3d

    v = np.asarray(vertices)
    centre = v.mean(axis=0) if origin is None else np.asarray(origin)
    scene = o3d.t.geometry.RaycastingScene()
    if len(faces):
        scene.add_triangles(
            o3d.core.Tensor(np.ascontiguousarray(v - centre, dtype=np.float32)),
            o3d.core.Tensor(np.ascontiguousarray(faces, dtype=np.uint32)),
        )
    return RaycastScene(scene, centre)


def face_areas(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(F,) float64 triangle areas in squared world units."""
    return 0.5 * np.linalg.norm(face_normals(vertices, faces, normalize=False), axis=1)


def euler_characteristic(faces: np.ndarray, n_vertices: int | None = None) -> int:
    """V - E + F counting only vertices that some face uses."""
    f = np.asarray(faces, dtype=np.int64)
    n = int(f.max()) + 1 if n_vertices is None else int(n_vertices)
    topo = edge_topology(f, n)
    used = np.zeros(n, dtype=bool)
    used[f.reshape(-1)] = True
    n_used = int(used.sum())
    return n_used - topo.n_edges + len(f)


def is_closed_manifold(faces: np.ndarray, n_vertices: int) -> bool:
    """True when every edge is shared by exactly two consistently oriented faces."""
    return bool(np.all(edge_topology(faces, n_vertices).interior))


def closest_points_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Closest point to each ``p[i]`` on triangle ``(a[i], b[i], c[i])``.

    Ericson, Real-Time Collision Detection, section 5.1.5, vectorized: the
    Voronoi regions (vertices, edges, interior) are disjoint up to their
    borders, where the candidate points coincide.

    Args:
        p, a, b, c: (M, 3) float64.

    Returns:
        (M, 3) float64 points on the (closed) triangles.
    """
    p, a, b, c = (np.asarray(x, dtype=np.float64) for x in (p, a, b, c))
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = _dot(ab, ap), _dot(ac, ap)
    bp = p - b
    d3, d4 = _dot(ab, bp), _dot(ac, bp)
    cp = p - c
    d5, d6 = _dot(ab, cp), _dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    # Interior (face region) by default.
    denom = va + vb + vc
    denom = np.where(np.abs(denom) < 1e-300, 1e-300, denom)
    v = vb / denom
    w = vc / denom
    out = a + ab * v[:, None] + ac * w[:, None]
    # Edge regions (later assignments take precedence only where their region test holds).
    e_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    t = (d4 - d3) / np.maximum((d4 - d3) + (d5 - d6), 1e-300)
    out = np.where(e_bc[:, None], b + (c - b) * t[:, None], out)
    e_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    t = d2 / np.maximum(d2 - d6, 1e-300)
    out = np.where(e_ac[:, None], a + ac * t[:, None], out)
    e_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    t = d1 / np.maximum(d1 - d3, 1e-300)
    out = np.where(e_ab[:, None], a + ab * t[:, None], out)
    # Vertex regions.
    out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)
    return out


def barycentric(points: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(M, 3) barycentric weights of (M, D) points on the triangles (a, b, c) (points on their planes).

    Example:
        >>> barycentric(np.array([[0.25, 0.25, 0.0]]), np.zeros((1, 3)), np.eye(3)[:1], np.eye(3)[1:2])
        array([[0.5 , 0.25, 0.25]])
    """
    e0, e1, d = b - a, c - a, points - a
    d00 = np.einsum("ij,ij->i", e0, e0)
    d01 = np.einsum("ij,ij->i", e0, e1)
    d11 = np.einsum("ij,ij->i", e1, e1)
    d20 = np.einsum("ij,ij->i", d, e0)
    d21 = np.einsum("ij,ij->i", d, e1)
    den = d00 * d11 - d01 * d01
    den = np.where(np.abs(den) > 0, den, 1.0)
    w1 = (d11 * d20 - d01 * d21) / den
    w2 = (d00 * d21 - d01 * d20) / den
    return np.stack([1.0 - w1 - w2, w1, w2], axis=1)


def _dot(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", x, y)


class ReferenceSurface:
    """A fixed triangle mesh that points can be projected onto (closest point).

    Holds an Embree scene (through Open3D) for the float32 closest-face search;
    the closest point on the face found is then computed in float64, so a
    projected point lies on a face of the mesh to float64 precision.

    Args:
        vertices: (N, 3) float positions.
        faces: (F, 3) integer indices, F >= 1.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray) -> None:
        self.vertices = np.asarray(vertices, dtype=np.float64)
        self.faces = check_faces(faces, len(self.vertices))
        if len(self.faces) == 0:
            raise MeshError("a reference surface needs at least one face")
        self._scene = raycasting_scene(self.vertices, self.faces)

    def project(self, points: np.ndarray, near: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Closest points on the surface.

        Args:
            points: (M, 3) float.
            near: (M,) int faces to try first, for points that moved a little since they lay on
                them: a point whose foot on its face's plane falls inside that face, at most
                sqrt(face area) from the point, is projected there without the global search (exact
                unless another part of the surface is nearer than that plane); the others are
                searched as without ``near``.

        Returns:
            projected: (M, 3) float64 points on the surface.
            face_ids: (M,) int64 the face each lies on.
        """
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        if near is None or len(p) == 0:
            return self._closest(p)
        ids = np.array(near, dtype=np.int64).reshape(-1)  # a copy: the far points' faces are written in
        tri = self.faces[ids]
        a, b, c = (self.vertices[tri[:, k]] for k in range(3))
        bary = barycentric(p, a, b, c)
        n = np.cross(b - a, c - a)  # |n| = twice the area
        nn = _dot(n, n)
        height = _dot(p - a, n)  # the distance from the plane times |n|
        # a degenerate face (nn = 0) has no plane to drop a foot on: searched
        inside = (bary >= 0.0).all(axis=1) & (nn > 0.0) & (height * height <= 0.5 * nn * np.sqrt(nn))
        projected = bary[:, :1] * a + bary[:, 1:2] * b + bary[:, 2:] * c
        if not inside.all():
            projected[~inside], ids[~inside] = self._closest(p[~inside])
        return projected, ids

    def _closest(self, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`project` by Embree's closest-face search over the whole mesh."""
        import open3d as o3d

        if len(p) == 0:
            return p.copy(), np.zeros(0, dtype=np.int64)
        query = o3d.core.Tensor(self._scene.local(p))
        ids = self._scene.scene.compute_closest_points(query)["primitive_ids"].numpy().astype(np.int64)
        tri = self.faces[ids]
        v = self.vertices
        return closest_points_on_triangles(p, v[tri[:, 0]], v[tri[:, 1]], v[tri[:, 2]]), ids
