"""Cast shadows in E_pho's shading (``refine.pho.shadowing``).

The paper's shading ``S(N)`` is the irradiance of a point that sees the whole
hemisphere above it, as on a convex surface. In a concavity (between a dragon's
coils, inside a bore, under an arm) part of that hemisphere is the surface itself,
so the point is darker than ``S(N)`` says, and E_pho, which can only darken a pair by
turning its normal away from the light or darkening the albedo (which E_psm holds
smooth), bends the surface there. With ``pho.shadowing='cast'`` every (vertex, view)
pair's rendered colour is multiplied by the share of its Lambertian irradiance that
arrives unblocked::

    f = sum_k L(w_k) [V_k + (1 - V_k) b] max(0, N.w_k) / sum_k L(w_k) max(0, N.w_k)

over K Fibonacci directions w_k, where V_k says whether a ray from the vertex
along w_k leaves the current mesh (Open3D ray casting), ``L`` is the radiance whose
Lambertian shading is the view's pmvir-sh9 lighting (:func:`pmvir.sh.radiance_from_shading`,
clamped at zero) and ``b`` (``pho.shadow_bounce``) the share of the blocked light that
the blocking surface sends back (0: none; inter-reflection is not otherwise modelled).
The factor is data fixed at each stage's start, like the pairs and the DoP weights: the
lighting it uses is the stage's starting lighting (after the first stage's lighting
pre-fit) and no gradient flows through it.
"""

from __future__ import annotations

import numpy as np

from pmvir.errors import ShapeError
from pmvir.geometry.mesh_ops import raycasting_scene
from pmvir.sh import fibonacci_sphere, radiance_from_shading, sh9_basis

#: Vertices per ray-casting batch (times the directions: rays per call).
_CHUNK = 16_384


def open_directions(
    vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray, directions: np.ndarray, *, offset: float
) -> np.ndarray:
    """Which directions leave the mesh unblocked from each vertex.

    Args:
        vertices: (N, 3) positions; faces: (F, 3) triangles; normals: (N, 3) unit outward normals.
        directions: (K, 3) unit directions.
        offset: rays start this far along the normal and ignore hits closer than it again (a
            mesh edge length: the one-ring's own facets must not block).

    Returns:
        (N, K) bool: True where the ray along the direction hits nothing. Directions below a
        vertex's horizon (normal . direction <= 0) carry no irradiance and are not cast: True.
    """
    import open3d as o3d

    v = np.asarray(vertices, np.float64)
    if v.ndim != 2 or v.shape[1] != 3 or np.shape(normals) != v.shape:
        raise ShapeError(f"expected (N, 3) vertices and normals, got {v.shape} and {np.shape(normals)}")
    centre = 0.5 * (v.min(0) + v.max(0)) if len(v) else np.zeros(3)
    scene = raycasting_scene(v, faces, origin=centre).scene
    d = np.asarray(directions, np.float32)
    k = len(d)
    out = np.ones((len(v), k), dtype=bool)
    n = np.asarray(normals, np.float64)
    origins = (v - centre + offset * n).astype(np.float32)
    for a in range(0, len(v), _CHUNK):
        o = origins[a : a + _CHUNK]
        facing = (n[a : a + _CHUNK] @ d.T.astype(np.float64)) > 0.0  # about half the directions
        row, col = np.nonzero(facing)
        rays = np.ascontiguousarray(np.concatenate([o[row], d[col]], axis=1))
        hit = scene.test_occlusions(o3d.core.Tensor(rays), tnear=float(offset)).numpy().astype(bool)
        out[a + row, col] = ~hit
    return out


def shadow_factors(
    vertices: np.ndarray,
    faces: np.ndarray,
    normals: np.ndarray,
    sh: np.ndarray,
    *,
    n_directions: int = 128,
    bounce: float = 0.0,
    offset: float,
) -> np.ndarray:
    """The unblocked share f of every vertex's Lambertian irradiance under every view's lighting.

    Args:
        vertices, faces, normals: the current mesh (see :func:`open_directions`).
        sh: (V, T) each view's shading coefficients; the first 9 (pmvir-sh9) are used.
        n_directions: K, the Fibonacci directions over the whole sphere (about half face a vertex).
        bounce: share b of the blocked light that comes back (see the module docstring).
        offset: see :func:`open_directions`.

    Returns:
        (N, V) float64 in [min(b, 1), 1] where the lighting reaches the vertex, 1 where it does not.
    """
    sh = np.asarray(sh, np.float64)
    if sh.ndim != 2 or sh.shape[1] < 9:
        raise ShapeError(f"expected (V, >= 9) shading coefficients, got {sh.shape}")
    dirs = fibonacci_sphere(n_directions)
    radiance = np.maximum(sh9_basis(dirs) @ radiance_from_shading(sh[:, :9]).T, 0.0)  # (K, V)
    cosines = np.maximum(np.asarray(normals, np.float64) @ dirs.T, 0.0)  # (N, K)
    blocked = ~open_directions(vertices, faces, normals, dirs, offset=offset)
    whole = cosines @ radiance  # (N, V)
    lost = (cosines * blocked) @ radiance
    tiny = 1e-9 * max(float(whole.max()), 1e-30) if whole.size else 0.0
    f = np.where(whole > tiny, 1.0 - (1.0 - bounce) * lost / np.where(whole > tiny, whole, 1.0), 1.0)
    return np.clip(f, min(bounce, 1.0), 1.0)
