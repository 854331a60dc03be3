"""Per-view lighting of synthetic captures: second-order SH or an environment map.

Both kinds give, per view, a diffuse shading ``E(N) = S(N) * colour`` for a unit
world-frame normal N (what a Lambertian surface of albedo K shows as ``K * E``)
and the environment radiance ``L(w) * colour`` in a world direction w (what a
mirror reflects). Values are in the renderer's radiance units, before the
sensor's gain; the shading is scaled so its maximum over the sphere is about 1.

* ``sh``: ``S`` is a pmvir-sh9 polynomial (spec section 3) made of an ambient
  term, a key and a fill light (clamped cosines projected to SH9), so the
  ground truth is exact. The radiance the specular reflection sees is the
  environment whose Lambertian shading is S (:func:`pmvir.sh.radiance_from_shading`),
  clamped at zero.
* ``envmap``: a latitude-longitude radiance map (a sky gradient, a darker
  ground and three soft area lights, von Mises-Fisher lobes). ``S`` is its
  cosine-weighted integral, tabulated once on a 48 x 96 lat-long grid of
  normals and interpolated bilinearly (within 0.4 % of the exact integral); the
  ground truth holds its least-squares SH9 projection.

Lat-long convention: row r covers polar angles from +z (world up) theta in
[r, r + 1] * pi / H, column c covers azimuths phi = atan2(y, x) in
-pi + [c, c + 1] * 2 pi / W.

Per-view variation (the method estimates one lighting per image): the key light
direction moves by up to ~15 degrees (SH) or the environment turns about +z by
up to 20 degrees (envmap); the strength varies by +-10 % and the colour by a few
per cent, seeded.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import lru_cache
from typing import Literal

import numpy as np

from pmvir.sh import fibonacci_sphere, project_to_sh9, radiance_from_shading, sh9_basis

LightingKind = Literal["sh", "envmap"]
LIGHTINGS: tuple[str, ...] = ("sh", "envmap")

_BASE_COLOUR = np.array([1.0, 0.96, 0.9])


def _direction(elev_deg: float, az_deg: float) -> np.ndarray:
    e, a = np.radians(elev_deg), np.radians(az_deg)
    return np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])


@dataclass(frozen=True)
class ShLight:
    """One view's SH lighting.

    Attributes:
        sh: (9,) pmvir-sh9 shading coefficients S (world frame).
        colour: (3,) RGB colour of the light.
    """

    sh: np.ndarray
    colour: np.ndarray
    _radiance_sh: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "_radiance_sh", radiance_from_shading(self.sh))

    def diffuse(self, normals: np.ndarray) -> np.ndarray:
        """E(N) = S(N) * colour at (N, 3) unit world normals, (N, 3) float64."""
        return (sh9_basis(normals) @ self.sh)[:, None] * self.colour[None]

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """Environment radiance max(0, L(w)) * colour at (N, 3) unit world directions, (N, 3)."""
        return np.maximum(sh9_basis(directions) @ self._radiance_sh, 0.0)[:, None] * self.colour[None]


def latlong_directions(height: int, width: int) -> np.ndarray:
    """Unit directions of the texel centres of a lat-long map, (height, width, 3) float64."""
    theta = (np.arange(height) + 0.5) * np.pi / height
    phi = -np.pi + (np.arange(width) + 0.5) * 2.0 * np.pi / width
    st = np.sin(theta)[:, None]
    return np.stack(
        [st * np.cos(phi)[None], st * np.sin(phi)[None], np.cos(theta)[:, None] * np.ones((1, width))],
        axis=-1,
    )


def latlong_lookup(image: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a lat-long map (H, W) or (H, W, C) at (N, 3) unit directions.

    Azimuth wraps around; the polar angle clamps at the poles.
    """
    h, w = image.shape[:2]
    d = np.asarray(directions, dtype=np.float64)
    theta = np.arccos(np.clip(d[:, 2], -1.0, 1.0))
    phi = np.arctan2(d[:, 1], d[:, 0])
    r = np.clip(theta / np.pi * h - 0.5, 0.0, h - 1.0)
    c = (phi + np.pi) / (2.0 * np.pi) * w - 0.5
    r0 = np.minimum(np.floor(r).astype(np.int64), h - 2) if h > 1 else np.zeros(len(r), np.int64)
    fr = r - r0
    c0f = np.floor(c)
    fc = c - c0f
    c0 = c0f.astype(np.int64) % w
    c1 = (c0 + 1) % w
    r1 = np.minimum(r0 + 1, h - 1)
    if image.ndim == 3:
        fr, fc = fr[:, None], fc[:, None]
    top = image[r0, c0] * (1 - fc) + image[r0, c1] * fc
    bot = image[r1, c0] * (1 - fc) + image[r1, c1] * fc
    return top * (1 - fr) + bot * fr


def environment_map(height: int, width: int) -> np.ndarray:
    """The scalar radiance of the built-in environment.

    A sky brighter toward the zenith, a darker ground, and three soft area lights
    (key, fill, rim) as von Mises-Fisher lobes.

    Returns:
        (height, width) float64 lat-long map, >= 0.
    """
    local = latlong_directions(height, width)
    z = local[..., 2]
    sky = np.where(z > 0, 0.18 + 0.22 * np.power(np.maximum(z, 0.0), 0.6), 0.06 + 0.04 * (1.0 + z))
    lights = (
        (_direction(50.0, 40.0), 90.0, 5.0),
        (_direction(20.0, 200.0), 40.0, 1.0),
        (_direction(8.0, 300.0), 220.0, 3.0),
    )
    out = sky
    for centre, kappa, power in lights:
        # Peak power * kappa / 10: each lobe integrates to about 0.63 * power over the sphere.
        out = out + power * kappa / 10.0 * np.exp(kappa * (local @ centre - 1.0))
    return out


def _texel_solid_angles(height: int, width: int) -> np.ndarray:
    theta0 = np.arange(height) * np.pi / height
    theta1 = theta0 + np.pi / height
    return ((np.cos(theta0) - np.cos(theta1)) * 2.0 * np.pi / width)[:, None] * np.ones((1, width))


def irradiance_shading(env: np.ndarray, normals: np.ndarray) -> np.ndarray:
    """Lambertian shading S(N) = (1/pi) * integral of L(w) max(0, N.w) dw, (N,) float64.

    Integrates over the texels of ``env`` (H, W) (use a block-averaged copy of a
    detailed map: the cosine kernel is smooth).
    """
    h, w = env.shape
    dirs = latlong_directions(h, w).reshape(-1, 3).T.astype(np.float32)
    weights = (env * _texel_solid_angles(h, w)).reshape(-1).astype(np.float32)
    n = np.asarray(normals, dtype=np.float32)
    out = np.empty(len(n))
    for start in range(0, len(n), 512):  # bounded memory: 512 x texels at a time
        cos = np.maximum(n[start : start + 512] @ dirs, 0.0)
        out[start : start + 512] = cos @ weights
    return out / np.pi


def _block_mean(image: np.ndarray, factor: int) -> np.ndarray:
    h, w = image.shape
    return image.reshape(h // factor, factor, w // factor, factor).mean(axis=(1, 3))


@dataclass(frozen=True)
class EnvTable:
    """An environment map and its tabulated Lambertian shading (shared by all views).

    Attributes:
        env: (H, W) scalar lat-long radiance (module docstring convention), float64.
        shading: (Hs, Ws) lat-long table of S(N) = (1/pi) integral L max(0, N.w) dw, float64.
    """

    env: np.ndarray
    shading: np.ndarray

    @classmethod
    def from_map(cls, env: np.ndarray, *, grid: tuple[int, int] = (48, 96), block: int = 4) -> EnvTable:
        """Tabulate the shading of ``env``, integrated over a ``block`` x ``block`` averaged copy."""
        coarse = _block_mean(env, block) if env.shape[0] % block == 0 and env.shape[1] % block == 0 else env
        normals = latlong_directions(*grid).reshape(-1, 3)
        return cls(env=env, shading=irradiance_shading(coarse, normals).reshape(grid))


@lru_cache(maxsize=1)
def _sh9_projector(n: int = 4000) -> tuple[np.ndarray, np.ndarray]:
    """Fibonacci directions (n, 3) and the least-squares SH9 projector (9, n) on them."""
    dirs = fibonacci_sphere(n)
    return dirs, np.linalg.pinv(sh9_basis(dirs))


def _turn_z(directions: np.ndarray, angle: float) -> np.ndarray:
    """Directions (N, 3) turned by ``angle`` radians about +z."""
    c, s = np.cos(angle), np.sin(angle)
    d = np.asarray(directions, dtype=np.float64)
    return np.stack([c * d[:, 0] - s * d[:, 1], s * d[:, 0] + c * d[:, 1], d[:, 2]], axis=1)


@dataclass(frozen=True)
class EnvLight:
    """One view's environment lighting: a shared map turned about +z and scaled.

    Radiance ``L(w) = strength * env(R_z(-rotation) w) * colour``; shading likewise
    from the shared table, so ``S(N) = strength * table(R_z(-rotation) N)``.

    Attributes:
        table: the shared map and shading table.
        rotation: turn about world +z, radians.
        strength: scalar factor.
        colour: (3,) RGB colour of the whole environment.
        sh: (9,) pmvir-sh9 least-squares projection of this view's S (the ground truth).
    """

    table: EnvTable
    rotation: float
    strength: float
    colour: np.ndarray
    sh: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        dirs, projector = _sh9_projector()
        object.__setattr__(self, "sh", projector @ self.shading(dirs))

    def shading(self, normals: np.ndarray) -> np.ndarray:
        """Scalar S(N) at (N, 3) unit world normals, (N,) float64."""
        return self.strength * latlong_lookup(self.table.shading, _turn_z(normals, -self.rotation))

    def diffuse(self, normals: np.ndarray) -> np.ndarray:
        """E(N) = S(N) * colour at (N, 3) unit world normals, (N, 3) float64."""
        return self.shading(normals)[:, None] * self.colour[None]

    def radiance(self, directions: np.ndarray) -> np.ndarray:
        """Environment radiance L(w) * colour at (N, 3) unit world directions, (N, 3)."""
        lum = self.strength * latlong_lookup(self.table.env, _turn_z(directions, -self.rotation))
        return lum[:, None] * self.colour[None]


ViewLight = ShLight | EnvLight


def _rotation_towards(v: np.ndarray, angle: float, rng: np.random.Generator) -> np.ndarray:
    """``v`` turned by ``angle`` radians toward a random perpendicular direction."""
    p = np.cross(v, rng.normal(size=3))
    p /= np.linalg.norm(p)
    return np.cos(angle) * v + np.sin(angle) * p


def sh_lights(views: int, *, seed: int) -> list[ShLight]:
    """Per-view SH lighting: ambient + key + fill clamped cosines, projected to pmvir-sh9.

    The shading is positive over the whole sphere (min >= 10 % of max) and scaled
    to a maximum of 1 before the per-view strength (+-10 %).
    """
    rng = np.random.default_rng([seed, 4242])
    dirs = fibonacci_sphere(4096)
    key0, fill0 = _direction(55.0, 40.0), _direction(20.0, 220.0)
    out = []
    for _ in range(views):
        key = _rotation_towards(key0, np.radians(rng.uniform(0.0, 15.0)), rng)
        fill = _rotation_towards(fill0, np.radians(rng.uniform(0.0, 15.0)), rng)
        shading = 0.3 + 1.0 * np.maximum(dirs @ key, 0.0) + 0.35 * np.maximum(dirs @ fill, 0.0)
        sh = project_to_sh9(dirs, shading)
        s = sh9_basis(dirs) @ sh
        sh[0] += max(0.0, 0.1 * s.max() - s.min())  # keep S >= 10 % of its maximum
        sh = sh / (sh9_basis(dirs) @ sh).max() * rng.uniform(0.9, 1.1)
        colour = _BASE_COLOUR * (1.0 + 0.04 * rng.normal(size=3))
        out.append(ShLight(sh=sh, colour=colour))
    return out


def env_lights(views: int, *, seed: int, resolution: tuple[int, int] = (128, 256)) -> list[EnvLight]:
    """Per-view environment lighting: the built-in map turned about +z by up to 20 degrees, seeded.

    The shading is scaled to a maximum of 1 before the per-view strength (+-10 %).
    """
    rng = np.random.default_rng([seed, 4343])
    table = EnvTable.from_map(environment_map(*resolution))
    norm = float(table.shading.max())
    lights = []
    for _ in range(views):
        rotation = float(np.radians(rng.uniform(-20.0, 20.0)))
        strength = float(rng.uniform(0.9, 1.1) / norm)
        colour = _BASE_COLOUR * (1.0 + 0.04 * rng.normal(size=3))
        lights.append(EnvLight(table=table, rotation=rotation, strength=strength, colour=colour))
    return lights
