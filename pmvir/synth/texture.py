"""Procedural per-vertex albedo: broad patches plus fine detail.

The albedo is a function of the vertex position on the normalized mesh
(bounding-box diagonal 1), so it is the same wherever the mesh is seen from and
exactly what the renderer interpolates (barycentric, per pixel). Three layers:

* broad patches: Voronoi cells (about 16 seed points) each with its own colour
  from a random palette, so albedo estimation sees large regions of distinct colour;
* mid and fine detail: a 3-D value-noise fBm (lattice spacings from 1/10 down to
  1/77 of the bounding-box diagonal, about 9 pixels at 612x512) modulating
  brightness (log-normal, about +-30 %) and, more weakly, hue, so feature
  matching finds texture everywhere;
* speckles: small dark and light dots at random points (corner-like features).

The result is linear RGB in [0.03, 0.92], float32.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from pmvir.errors import ShapeError


def value_noise(points: np.ndarray, frequency: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth 3-D value noise in [0, 1] at ``points`` (N, 3) inside [-1, 1]^3, (N,) float64.

    Random values on an integer lattice of spacing ``1 / frequency``, interpolated
    trilinearly with smoothstep weights.
    """
    g = int(np.ceil(2.0 * frequency)) + 3
    lattice = rng.random((g, g, g))
    q = (np.asarray(points, dtype=np.float64) + 1.0) * frequency
    i0 = np.clip(np.floor(q).astype(np.int64), 0, g - 2)
    f = np.clip(q - i0, 0.0, 1.0)
    w = f * f * (3.0 - 2.0 * f)
    out = np.zeros(len(q))
    for dx in (0, 1):
        wx = w[:, 0] if dx else 1.0 - w[:, 0]
        for dy in (0, 1):
            wy = w[:, 1] if dy else 1.0 - w[:, 1]
            for dz in (0, 1):
                wz = w[:, 2] if dz else 1.0 - w[:, 2]
                out += wx * wy * wz * lattice[i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz]
    return out


def _fbm(
    points: np.ndarray, frequencies: tuple[float, ...], rng: np.random.Generator, decay: float = 0.5
) -> np.ndarray:
    """Zero-mean fBm, amplitude times ``decay`` per octave, standard deviation about 0.35, (N,)."""
    total, norm = np.zeros(len(points)), 0.0
    for k, freq in enumerate(frequencies):
        amp = decay**k
        total += amp * (2.0 * value_noise(points, freq, rng) - 1.0)
        norm += amp
    return total / norm * 1.6


def procedural_albedo(vertices: np.ndarray, *, seed: int) -> np.ndarray:
    """Spatially varying linear RGB albedo of the vertices of a normalized mesh.

    Args:
        vertices: (N, 3) positions, bounding-box diagonal about 1, centred near the origin.
        seed: random seed; the same seed and vertices give the same albedo.

    Returns:
        (N, 3) float32 albedo in [0.03, 0.92].
    """
    v = np.asarray(vertices, dtype=np.float64)
    if v.ndim != 2 or v.shape[1] != 3:
        raise ShapeError(f"expected (N, 3) vertices, got {v.shape}")
    rng = np.random.default_rng([seed, 7301])
    # Broad patches: Voronoi cells of random sites near the surface, one palette colour each.
    n_sites = 16
    sites = v[rng.choice(len(v), size=min(n_sites, len(v)), replace=False)]
    _, cell = cKDTree(sites).query(v)
    hue = rng.uniform(0.0, 1.0, len(sites))
    sat = rng.uniform(0.4, 0.9, len(sites))
    val = rng.uniform(0.3, 0.8, len(sites))
    palette = _hsv_to_rgb(hue, sat, val)
    base = palette[cell]
    # Mid and fine detail: brightness fBm plus a weaker per-channel variation.
    p = np.clip(v * 1.6, -1.0, 1.0)  # the mesh fits in [-0.5, 0.5]^3
    bright = np.exp(0.9 * _fbm(p, (6.0, 12.0, 24.0, 48.0), rng, decay=0.75))
    tint = np.stack([_fbm(p, (10.0, 40.0), rng) for _ in range(3)], axis=1)
    albedo = base * bright[:, None] * (1.0 + 0.15 * tint)
    # Speckles: small dots, half dark, half light.
    n_dots = 400
    dots = v[rng.choice(len(v), size=min(n_dots, len(v)), replace=False)]
    dist, idx = cKDTree(dots).query(v)
    radius = 0.006 + 0.006 * rng.random(len(dots))
    inside = dist < radius[idx]
    light = (idx % 2 == 0) & inside
    albedo[inside & ~light] *= 0.25
    albedo[light] = 0.5 * albedo[light] + 0.45
    return np.clip(albedo, 0.03, 0.92).astype(np.float32)


#: Albedo of the ``uniform`` texture (linear RGB).
UNIFORM_ALBEDO = (0.6, 0.5, 0.4)


def uniform_albedo(n_vertices: int) -> np.ndarray:
    """The constant albedo :data:`UNIFORM_ALBEDO` for every vertex, (N, 3) float32."""
    return np.tile(np.asarray(UNIFORM_ALBEDO, dtype=np.float32), (n_vertices, 1))


def _hsv_to_rgb(h: np.ndarray, s: np.ndarray, v: np.ndarray) -> np.ndarray:
    """HSV (each (N,), in [0, 1]) to RGB (N, 3)."""
    k = (np.array([5.0, 3.0, 1.0])[None] + 6.0 * h[:, None]) % 6.0
    return v[:, None] - v[:, None] * s[:, None] * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)
