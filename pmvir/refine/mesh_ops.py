"""Mesh connectivity and differentiable normals for the refinement.

Connectivity (edges, edge-adjacent face pairs) is computed once per stage with
NumPy; normals are computed with PyTorch on every energy evaluation so that
autograd differentiates through them.
"""

from __future__ import annotations

import warnings

import numpy as np
import torch

from pmvir.errors import MeshError

#: Lengths below this are treated as zero when normalizing (world units).
NORMAL_EPS = 1e-20


def check_mesh(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Validate a triangle mesh.

    Args:
        vertices: (N, 3) finite positions.
        faces: (F, 3) integer vertex indices in [0, N).

    Returns:
        vertices as (N, 3) float64 and faces as (F, 3) int64.

    Raises:
        MeshError: wrong shapes, non-finite positions, no faces, or indices out of range.
    """
    v = np.asarray(vertices)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0:
        raise MeshError(f"expected (N, 3) vertices with N >= 1, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise MeshError(f"expected (F, 3) triangle faces with F >= 1, got shape {f.shape}")
    if not np.issubdtype(f.dtype, np.integer):
        raise MeshError(f"expected integer face indices, got dtype {f.dtype}")
    if not np.all(np.isfinite(v)):
        raise MeshError("vertex positions contain NaN or infinity")
    if f.min() < 0 or f.max() >= len(v):
        raise MeshError(f"face indices must lie in [0, {len(v)}), got [{f.min()}, {f.max()}]")
    return v.astype(np.float64), f.astype(np.int64)


def unique_edges(faces: np.ndarray) -> np.ndarray:
    """Undirected edges of a triangle mesh.

    Args:
        faces: (F, 3) int vertex indices.

    Returns:
        (E, 2) int64 edges (i, j) with i < j, each once, sorted.
    """
    f = np.asarray(faces, dtype=np.int64)
    src, dst = f.reshape(-1), f[:, [1, 2, 0]].reshape(-1)
    lo, hi = np.minimum(src, dst), np.maximum(src, dst)
    keep = lo != hi
    # One int64 key per edge, ordered as the rows (lo, hi) are, sorted and deduplicated by hand:
    # np.unique on rows (axis=0), and numpy 2's hashing np.unique on int64, take 50x longer.
    n = np.int64(hi.max() + 1) if len(hi) else np.int64(1)
    key = np.sort(lo[keep] * n + hi[keep])
    key = key[np.r_[True, key[1:] != key[:-1]]] if len(key) else key
    return np.stack([key // n, key % n], axis=1)


def face_adjacency(faces: np.ndarray) -> np.ndarray:
    """Pairs of faces that share an edge.

    Every pair appears in both orders, so ``pairs[:, 0]`` lists, for each face,
    all its edge-adjacent faces (at non-manifold edges: every other face on the edge).

    Args:
        faces: (F, 3) int vertex indices.

    Returns:
        (M, 2) int64 face index pairs (r, s), r != s.
    """
    f = np.asarray(faces, dtype=np.int64)
    n_faces = len(f)
    e = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]], axis=0)
    e = np.sort(e, axis=1)
    face_of = np.tile(np.arange(n_faces, dtype=np.int64), 3)
    key = e[:, 0] * (int(e.max()) + 1) + e[:, 1]
    order = np.argsort(key, kind="stable")
    key, face_of = key[order], face_of[order]
    # Group equal keys: for groups of two (manifold edges) emit one pair; larger groups emit all pairs.
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    sizes = np.diff(np.r_[starts, len(key)])
    pairs = []
    two = starts[sizes == 2]
    if len(two):
        pairs.append(np.stack([face_of[two], face_of[two + 1]], axis=1))
    for s, n in zip(starts[sizes > 2], sizes[sizes > 2], strict=True):
        grp = face_of[s : s + n]
        a, b = np.triu_indices(n, 1)
        pairs.append(np.stack([grp[a], grp[b]], axis=1))
    if not pairs:
        return np.zeros((0, 2), dtype=np.int64)
    p = np.concatenate(pairs, axis=0)
    p = p[p[:, 0] != p[:, 1]]
    return np.concatenate([p, p[:, ::-1]], axis=0)


def mean_edge_length(vertices: np.ndarray, edges: np.ndarray) -> float:
    """Mean length of the given (E, 2) edges, world units (0.0 without edges)."""
    if len(edges) == 0:
        return 0.0
    v = np.asarray(vertices, dtype=np.float64)
    return float(np.linalg.norm(v[edges[:, 0]] - v[edges[:, 1]], axis=1).mean())


def face_cross(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Un-normalized face normals (e1 x e2, length = twice the area), (F, 3)."""
    a = vertices.index_select(0, faces[:, 0])
    b = vertices.index_select(0, faces[:, 1])
    c = vertices.index_select(0, faces[:, 2])
    return torch.linalg.cross(b - a, c - a, dim=1)


def normalize(v: torch.Tensor, eps: float = NORMAL_EPS) -> torch.Tensor:
    """Rows of ``v`` scaled to unit length; rows shorter than sqrt(eps) stay (near) zero."""
    return v * torch.rsqrt((v * v).sum(-1, keepdim=True).clamp_min(eps))


def face_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit face normals N'_r, (F, 3); counter-clockwise faces point outward."""
    return normalize(face_cross(vertices, faces))


def vertex_normals(vertices: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Area-weighted vertex normals N(X): the normalized sum of adjacent face cross products.

    Args:
        vertices: (N, 3) positions, float tensor.
        faces: (F, 3) int64 tensor.

    Returns:
        (N, 3) unit normals, same dtype/device as ``vertices``.
    """
    fc = face_cross(vertices, faces)
    n = torch.zeros_like(vertices)
    for k in range(3):
        n = n.index_add(0, faces[:, k], fc)
    return normalize(n)


def adjacency_csr(
    edges: np.ndarray,
    weights: np.ndarray,
    n_vertices: int,
    *,
    device: torch.device,
    dtype: torch.dtype,
    row_scale: np.ndarray | None = None,
) -> torch.Tensor:
    """Symmetric (N, N) sparse CSR matrix with ``weights[e]`` at (i, j) and (j, i) of every edge (i, j);
    with ``row_scale`` (N,), row i is multiplied by ``row_scale[i]`` (then no longer symmetric)."""
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    vals = np.concatenate([weights, weights]).astype(np.float64)
    if row_scale is not None:
        vals = vals * np.asarray(row_scale, dtype=np.float64)[rows]
    order = np.lexsort((cols, rows))
    crow = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=n_vertices))])
    with warnings.catch_warnings():  # sparse CSR is "beta" in torch; matrix-vector products are all we use
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(
            torch.from_numpy(crow).to(device),
            torch.from_numpy(cols[order]).to(device),
            torch.from_numpy(vals[order]).to(device=device, dtype=dtype),
            size=(n_vertices, n_vertices),
        )


class GraphSmoother:
    """A symmetric positive-definite smoothing operator on per-vertex values.

    ``M = sum_{j=0}^{K} (D^-1 lam W)^j D^-1`` with ``W`` the vertex adjacency matrix and
    ``D = I + lam * diag(degree)``: the first K + 1 terms of the Neumann series of
    ``(I + lam L)^-1`` (L the combinatorial graph Laplacian). Every truncation is
    symmetric positive definite and linear, so it can serve as the L-BFGS
    preconditioner (Sobolev-like steps: low-frequency surface motion is not damped
    the way high-frequency motion is; cf. Nicolet et al. 2021, "Large steps in
    inverse rendering of geometry").

    Args:
        edges: (E, 2) int64 undirected edges.
        n_vertices: N.
        lam: smoothing strength (0: the identity).
        iterations: K.
        device, dtype: of the values it will be applied to.
    """

    def __init__(
        self,
        edges: np.ndarray,
        n_vertices: int,
        *,
        lam: float,
        iterations: int,
        device: torch.device,
        dtype: torch.dtype,
    ):
        self.lam, self.iterations = lam, iterations
        deg = np.bincount(edges.reshape(-1), minlength=n_vertices).astype(np.float64)
        dinv = 1.0 / (1.0 + lam * deg)
        self.dinv = torch.from_numpy(dinv).to(device=device, dtype=dtype)
        # D^-1 lam W as one matrix (row i scaled by dinv_i): one sparse product per term, no extra scaling.
        self.w = adjacency_csr(edges, np.full(len(edges), lam), n_vertices, device=device, dtype=dtype,
                               row_scale=dinv)

    def __call__(self, x: torch.Tensor) -> torch.Tensor:
        """M @ x for x of shape (N,) or (N, k)."""
        if self.lam == 0.0:
            return x
        vec = x.ndim == 1
        y = x[:, None] if vec else x
        term = self.dinv[:, None] * y
        acc = term.clone()
        for _ in range(self.iterations):
            term = self.w @ term
            acc.add_(term)
        return acc[:, 0] if vec else acc
