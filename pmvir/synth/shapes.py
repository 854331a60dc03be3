"""Built-in procedural shapes and mesh normalization for synthetic captures.

Every built-in shape is a closed, watertight triangle mesh with outward
(counter-clockwise) faces and 20k-60k faces (200k for the fine-relief shapes),
fixed (not seeded), so a name always means the same surface:

* ``sphere``: a geodesic sphere (tests: normals and azimuths are known exactly).
* ``blob``: a sphere with a broad deformation and 140 bumps of several sizes.
* ``dented``: a blob with deep round dents (concavities that occlude themselves).
* ``knot``: a tube along a (2, 3) torus knot (genus 1, a non-star-shaped surface
  with strong self-occlusion: the tube passes in front of itself three times).
* ``gear``: a flat ring with a bore and 14 rounded teeth (genus 1; the bore is
  seen only from above and below).
* ``mug``: a rounded cup-shaped body with a thin handle (a tube of 0.05 of the
  diagonal; genus 1 as seen from outside). Body and handle are two closed
  components; the handle's capped ends lie 0.4 tube radii inside the body
  (hidden: about 1 % of the ground truth's area cannot be seen).
* ``spring``: a coil spring, a tube along a helix of three turns, capped at both
  ends (genus 0; a thin part: the tube is a tenth of the diagonal across, and
  each turn hides parts of its neighbours across gaps of 0.7 tube widths).
* ``rock``, ``panel``, ``cloth``: fine relief down to wavelengths of a few pixels (a
  fractal rock, a carved round panel, draped cloth; :mod:`pmvir.synth.relief`).

:func:`normalize_mesh` centres a mesh on its bounding-box centre and scales it
to a bounding-box diagonal of 1 (the unit of the spec's metrics).
"""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path
from typing import Literal

import numpy as np

from pmvir.errors import ConfigError, MeshError
from pmvir.geometry.mesh_ops import vertex_normals
from pmvir.io.ply import Mesh, read_mesh

SHAPES: tuple[str, ...] = ("sphere", "blob", "dented", "knot", "gear", "mug", "spring", "rock", "panel", "cloth")
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


def _periodic_grid_faces(n_u: int, n_v: int) -> np.ndarray:
    """Faces of an (n_u, n_v) vertex grid periodic in both directions (a torus), (2 n_u n_v, 3)."""
    i, j = np.meshgrid(np.arange(n_u), np.arange(n_v), indexing="ij")
    a = i * n_v + j
    b = ((i + 1) % n_u) * n_v + j
    c = ((i + 1) % n_u) * n_v + (j + 1) % n_v
    d = i * n_v + (j + 1) % n_v
    return np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])


def _superellipse(t: np.ndarray, exponent: float) -> tuple[np.ndarray, np.ndarray]:
    """(cos-like, sin-like) of a superellipse |x|^e + |y|^e = 1 at parameter angles t."""
    c, s = np.cos(t), np.sin(t)
    return np.sign(c) * np.abs(c) ** (2.0 / exponent), np.sign(s) * np.abs(s) ** (2.0 / exponent)


def _gear(teeth: int = 14, n_u: int = 448, n_v: int = 52) -> tuple[np.ndarray, np.ndarray]:
    """A ring of rounded-rectangle section (bore radius 0.55, outer 1.0, height 0.36) with teeth."""
    u = np.linspace(0.0, 2.0 * np.pi, n_u, endpoint=False)
    v = np.linspace(0.0, 2.0 * np.pi, n_v, endpoint=False)
    cu, cv = np.meshgrid(u, v, indexing="ij")
    x, y = _superellipse(cv, 4.0)
    tooth = np.clip(1.6 * np.sin(teeth * cu), -1.0, 1.0) * 0.5 + 0.5  # flat-topped teeth
    outward = np.clip(x, 0.0, 1.0) ** 2  # teeth grow on the outer wall only
    r = 0.775 + 0.225 * x + 0.14 * tooth * outward
    z = 0.18 * y
    verts = np.stack([r * np.cos(cu), r * np.sin(cu), z], -1).reshape(-1, 3)
    return verts, _orient_outward(verts, _periodic_grid_faces(n_u, n_v))


def _capped_tube(
    centre: np.ndarray, tangent: np.ndarray, normal: np.ndarray, radius: float, n_s: int
) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube of ``radius`` round an open centre line (n_t, 3) with unit tangents and normals:
    ``n_s`` vertices a ring, flat caps fanned round the two end centres, faces outward."""
    n_t = len(centre)
    binormal = np.cross(tangent, normal)
    w = np.linspace(0.0, 2.0 * np.pi, n_s, endpoint=False)
    ring = np.cos(w)[None, :, None] * normal[:, None] + np.sin(w)[None, :, None] * binormal[:, None]
    tube = (centre[:, None] + radius * ring).reshape(-1, 3)
    ti, tj = np.meshgrid(np.arange(n_t - 1), np.arange(n_s), indexing="ij")
    p, q = ti * n_s + tj, (ti + 1) * n_s + tj
    rr, ss = (ti + 1) * n_s + (tj + 1) % n_s, ti * n_s + (tj + 1) % n_s
    side = np.concatenate([np.stack([p, q, rr], -1).reshape(-1, 3), np.stack([p, rr, ss], -1).reshape(-1, 3)])
    # outward: the faces must point away from the centre line (the first face's corners are on ring 0)
    e1, e2 = tube[side[0, 1]] - tube[side[0, 0]], tube[side[0, 2]] - tube[side[0, 0]]
    if float(np.cross(e1, e2) @ (tube[side[0, 0]] - centre[0])) < 0:
        side = side[:, ::-1].copy()
    ends = len(tube) + np.arange(2)
    first, last = np.arange(n_s), (n_t - 1) * n_s + np.arange(n_s)
    nxt = np.roll(np.arange(n_s), -1)
    caps = np.concatenate(
        [
            np.stack([np.full(n_s, ends[0]), first[nxt], first], 1),
            np.stack([np.full(n_s, ends[1]), last, last[nxt]], 1),
        ]
    )
    if float(np.cross(*(tube[caps[0, 1:]] - centre[0])) @ tangent[0]) > 0:  # cap 0 must face -tangent
        caps = caps[:, ::-1].copy()
    return np.concatenate([tube, centre[[0, -1]]]), np.concatenate([side, caps])


def _mug(n_u: int = 160, n_v: int = 120, n_t: int = 160, n_s: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """A rounded cup-shaped body (superellipse of revolution) and a thin handle tube on its side."""
    a, b = 0.5, 0.6  # body radius and half-height
    u = np.linspace(0.0, 2.0 * np.pi, n_u, endpoint=False)
    v = np.linspace(0.0, np.pi, n_v)[1:-1]  # poles added separately
    cu, cv = np.meshgrid(u, v, indexing="ij")
    r, z = a * np.abs(np.sin(cv)) ** 0.5, b * np.sign(np.cos(cv)) * np.abs(np.cos(cv)) ** 0.5
    body = np.stack([r * np.cos(cu), r * np.sin(cu), z], -1).reshape(-1, 3)
    body = np.concatenate([body, [[0.0, 0.0, b], [0.0, 0.0, -b]]])
    m = n_v - 2
    faces: list[tuple[int, int, int]] = []
    for i in range(n_u):
        i2 = (i + 1) % n_u
        for j in range(m - 1):
            a0, b0, c0, d0 = i * m + j, i2 * m + j, i2 * m + j + 1, i * m + j + 1
            faces += [(a0, b0, c0), (a0, c0, d0)]
        faces += [(len(body) - 2, i2 * m, i * m), (len(body) - 1, i * m + m - 1, i2 * m + m - 1)]
    body_faces = _orient_outward(body, np.asarray(faces, np.int64))
    # handle: a tube of radius tau along an arc of radius rho centred on the body's wall (x = a)
    rho, tau = 0.36, 0.065
    reach = np.arcsin(min(0.99, 0.4 * tau / rho))  # the ends sink 0.4 tube radii into the wall
    t = np.linspace(-np.pi / 2 - reach, np.pi / 2 + reach, n_t)
    centre = np.stack([a + rho * np.cos(t), np.zeros_like(t), rho * np.sin(t)], 1)
    tangent = np.stack([-np.sin(t), np.zeros_like(t), np.cos(t)], 1)
    normal = np.stack([np.cos(t), np.zeros_like(t), np.sin(t)], 1)
    # its capped ends lie inside the body: two closed components
    tube, tube_faces = _capped_tube(centre, tangent, normal, tau, n_s)
    return np.concatenate([body, tube]), np.concatenate([body_faces, tube_faces + len(body)])


def _spring(turns: float = 3.0, n_t: int = 720, n_s: int = 32) -> tuple[np.ndarray, np.ndarray]:
    """A tube of radius 0.22 along a helix of radius 1 and pitch 0.75, closed by flat caps."""
    radius, pitch, tube_radius = 1.0, 0.75, 0.22
    t = np.linspace(0.0, 2.0 * np.pi * turns, n_t)
    centre = np.stack([radius * np.cos(t), radius * np.sin(t), pitch * t / (2.0 * np.pi)], 1)
    tangent = np.stack([-radius * np.sin(t), radius * np.cos(t), np.full_like(t, pitch / (2.0 * np.pi))], 1)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.stack([np.cos(t), np.sin(t), np.zeros_like(t)], 1)  # radial: already normal to the tangent
    return _capped_tube(centre, tangent, normal, tube_radius, n_s)


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
    if name == "gear":
        return _gear()
    if name == "mug":
        return _mug()
    if name == "spring":
        return _spring()
    if name in ("rock", "panel", "cloth"):
        from pmvir.synth.relief import relief_shape  # relief builds on geodesic_sphere above

        return relief_shape(name)
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
