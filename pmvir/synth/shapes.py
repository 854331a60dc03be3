"""Built-in procedural shapes and mesh normalization for synthetic captures.

Every built-in shape is a closed, watertight triangle mesh with outward
(counter-clockwise) faces and 20k-60k faces, fixed (not seeded), so a name
always means the same surface:

* ``sphere``: a geodesic sphere (tests: normals and azimuths are known exactly).
* ``blob``: a sphere with a broad deformation and 140 bumps of several sizes.
* ``dented``: a blob with deep round dents (concavities that occlude themselves).
* ``knot``: a tube along a (2, 3) torus knot (a non-star-shaped surface with
  strong self-occlusion).

:func:`normalize_mesh` centres a mesh on its bounding-box centre and scales it
to a bounding-box diagonal of 1 (the unit of the spec's metrics).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

import numpy as np

from pmvir.errors import ConfigError, MeshError
from pmvir.io.ply import Mesh, read_mesh, vertex_normals

SHAPES: tuple[str, ...] = ("sphere", "blob", "dented", "knot")
UpAxis = Literal["x", "y", "z"]


def _icosahedron() -> tuple[np.ndarray, np.ndarray]:
    p = (1.0 + np.sqrt(5.0)) / 2.0
    v = np.array(
        [
            [-1, p, 0],
            [1, p, 0],
            [-1, -p, 0],
            [1, -p, 0],
            [0, -1, p],
            [0, 1, p],
            [0, -1, -p],
            [0, 1, -p],
            [p, 0, -1],
            [p, 0, 1],
            [-p, 0, -1],
            [-p, 0, 1],
        ],
        dtype=np.float64,
    )
    f = np.array(
        [
            [0, 11, 5],
            [0, 5, 1],
            [0, 1, 7],
            [0, 7, 10],
            [0, 10, 11],
            [1, 5, 9],
            [5, 11, 4],
            [11, 10, 2],
            [10, 7, 6],
            [7, 1, 8],
            [3, 9, 4],
            [3, 4, 2],
            [3, 2, 6],
            [3, 6, 8],
            [3, 8, 9],
            [4, 9, 5],
            [2, 4, 11],
            [6, 2, 10],
            [8, 6, 7],
            [9, 8, 1],
        ],
        dtype=np.int64,
    )
    return v / np.linalg.norm(v, axis=1, keepdims=True), f


def geodesic_sphere(frequency: int) -> tuple[np.ndarray, np.ndarray]:
    """Unit geodesic sphere: each icosahedron face split into ``frequency**2`` triangles.

    Returns:
        vertices (V, 3) float64 on the unit sphere, faces (20 * frequency**2, 3) int64,
        counter-clockwise seen from outside.
    """
    if frequency < 1:
        raise ConfigError(f"frequency must be >= 1, got {frequency}")
    iv, ifaces = _icosahedron()
    n = frequency
    ii, jj = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
    keep = ii + jj <= n
    ii, jj = ii[keep], jj[keep]  # lattice point (i, j): a + i/n (b - a) + j/n (c - a)
    local = -np.ones((n + 1, n + 1), dtype=np.int64)
    local[ii, jj] = np.arange(len(ii))
    corners = []
    for i in range(n):
        for j in range(n - i):
            corners.append((local[i, j], local[i + 1, j], local[i, j + 1]))
            if i + j + 1 < n:
                corners.append((local[i + 1, j], local[i + 1, j + 1], local[i, j + 1]))
    tris = np.asarray(corners, dtype=np.int64)
    a, b, c = iv[ifaces[:, 0]], iv[ifaces[:, 1]], iv[ifaces[:, 2]]
    pts = a[:, None] + (ii / n)[None, :, None] * (b - a)[:, None] + (jj / n)[None, :, None] * (c - a)[:, None]
    pts = pts.reshape(-1, 3)
    pts /= np.linalg.norm(pts, axis=1, keepdims=True)
    faces = (tris[None] + (np.arange(len(ifaces)) * len(ii))[:, None, None]).reshape(-1, 3)
    # Merge the copies of vertices shared by neighbouring icosahedron faces.
    key = np.round(pts * 1e6).astype(np.int64)
    _, first, inverse = np.unique(key, axis=0, return_index=True, return_inverse=True)
    return pts[first], inverse.reshape(-1)[faces]


def _bump_field(dirs: np.ndarray, centres: np.ndarray, heights: np.ndarray, widths: np.ndarray) -> np.ndarray:
    """Sum of Gaussian bumps on the sphere: sum_k h_k exp(-angle_k^2 / (2 w_k^2)), (V,)."""
    cosang = np.clip(dirs @ centres.T, -1.0, 1.0)
    ang2 = 2.0 * (1.0 - cosang)  # chord^2 ~ angle^2 for small angles
    return (heights[None] * np.exp(-ang2 / (2.0 * widths[None] ** 2))).sum(axis=1)


def _radial_shape(dents: bool) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(20240611 if not dents else 20240612)
    dirs, faces = geodesic_sphere(50)
    x, y, z = dirs.T
    r = 1.0 + 0.12 * x * y + 0.10 * (z * z - 1.0 / 3.0) + 0.06 * x  # broad deformation
    n_bumps = 140
    centres = rng.normal(size=(n_bumps, 3))
    centres /= np.linalg.norm(centres, axis=1, keepdims=True)
    heights = rng.uniform(0.025, 0.08, n_bumps) * rng.choice([-1.0, 1.0], n_bumps, p=[0.3, 0.7])
    widths = rng.uniform(0.05, 0.2, n_bumps)
    r = r + _bump_field(dirs, centres, heights, widths)
    if dents:
        dc = rng.normal(size=(9, 3))
        dc /= np.linalg.norm(dc, axis=1, keepdims=True)
        # Flat-bottomed round dents: depth ~0.3 of the radius, steep walls.
        cosang = np.clip(dirs @ dc.T, -1.0, 1.0)
        ang = np.arccos(cosang)
        radius = rng.uniform(0.28, 0.42, 9)
        depth = rng.uniform(0.22, 0.32, 9)
        profile = 1.0 / (1.0 + np.exp((ang - radius[None]) / 0.035))
        r = r - (depth[None] * profile).sum(axis=1)
    return dirs * r[:, None], faces


def _torus_knot(p: int = 2, q: int = 3, n_t: int = 480, n_v: int = 48) -> tuple[np.ndarray, np.ndarray]:
    t = np.linspace(0.0, 2.0 * np.pi, n_t, endpoint=False)
    big_r, small_r, tube = 1.0, 0.45, 0.2

    def curve(s: np.ndarray) -> np.ndarray:
        rr = big_r + small_r * np.cos(q * s)
        return np.stack([rr * np.cos(p * s), rr * np.sin(p * s), small_r * np.sin(q * s)], axis=1)

    h = 1e-4
    c = curve(t)
    d1 = (curve(t + h) - curve(t - h)) / (2 * h)
    d2 = (curve(t + h) - 2 * c + curve(t - h)) / (h * h)
    tangent = d1 / np.linalg.norm(d1, axis=1, keepdims=True)
    normal = d2 - (d2 * tangent).sum(1, keepdims=True) * tangent  # Frenet frame: periodic, curvature > 0
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    binormal = np.cross(tangent, normal)
    v = np.linspace(0.0, 2.0 * np.pi, n_v, endpoint=False)
    ring = np.cos(v)[None, :, None] * normal[:, None] + np.sin(v)[None, :, None] * binormal[:, None]
    verts = (c[:, None] + tube * ring).reshape(-1, 3)
    i, j = np.meshgrid(np.arange(n_t), np.arange(n_v), indexing="ij")
    a = i * n_v + j
    b = ((i + 1) % n_t) * n_v + j
    cc = ((i + 1) % n_t) * n_v + (j + 1) % n_v
    d = i * n_v + (j + 1) % n_v
    faces = np.concatenate([np.stack([a, b, cc], -1).reshape(-1, 3), np.stack([a, cc, d], -1).reshape(-1, 3)])
    return verts, _orient_outward(verts, faces)


def _signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    v0, v1, v2 = (vertices[faces[:, k]] for k in range(3))
    return float(np.einsum("ij,ij->i", v0, np.cross(v1, v2)).sum() / 6.0)


def _orient_outward(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Flip all faces if the (closed or nearly closed) mesh's signed volume is negative."""
    return faces[:, ::-1].copy() if _signed_volume(vertices, faces) < 0 else faces


@lru_cache(maxsize=8)
def _builtin(name: str) -> tuple[np.ndarray, np.ndarray]:
    if name == "sphere":
        return geodesic_sphere(40)
    if name == "blob":
        return _radial_shape(dents=False)
    if name == "dented":
        return _radial_shape(dents=True)
    return _torus_knot()


def builtin_shape(name: str) -> Mesh:
    """A built-in shape, normalized (bounding-box diagonal 1, centred at the origin).

    Raises:
        ConfigError: ``name`` is not one of :data:`SHAPES`.
    """
    if name not in SHAPES:
        raise ConfigError(f"unknown shape {name!r}; expected one of {', '.join(SHAPES)}")
    v, f = _builtin(name)
    return normalize_mesh(Mesh(v.copy(), f.copy()))


_UP_ROTATION = {
    "z": np.eye(3),
    "y": np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),  # y -> z, z -> -y
    "x": np.array([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]]),  # x -> z, z -> -x
}


def normalize_mesh(mesh: Mesh, *, up: UpAxis = "z") -> Mesh:
    """Rotate ``up`` to world +z, centre on the bounding-box centre, scale to diagonal 1.

    Faces are flipped if the signed volume is negative (inside-out files); vertex
    normals are recomputed (area-weighted). Albedo is dropped (the synthesizer
    paints its own).

    Raises:
        MeshError: the mesh has no faces or zero extent.
        ConfigError: unknown ``up``.
    """
    if up not in _UP_ROTATION:
        raise ConfigError(f"up axis must be one of x, y, z, got {up!r}")
    if len(mesh.faces) == 0:
        raise MeshError("mesh has no faces")
    used = np.unique(mesh.faces)
    v = mesh.vertices @ _UP_ROTATION[up].T
    lo, hi = v[used].min(axis=0), v[used].max(axis=0)
    diag = float(np.linalg.norm(hi - lo))
    if not np.isfinite(diag) or diag <= 1e-12:
        raise MeshError(f"mesh has zero or non-finite extent (bounding-box diagonal {diag})")
    v = (v - (lo + hi) / 2.0) / diag
    faces = _orient_outward(v, mesh.faces)
    return Mesh(v, faces, albedo=None, normals=vertex_normals(v, faces).astype(np.float32))


def load_mesh(path: str | Path, *, up: UpAxis = "z") -> Mesh:
    """Read a PLY/OBJ mesh and normalize it (see :func:`normalize_mesh`); raises MeshError."""
    return normalize_mesh(read_mesh(path), up=up)
