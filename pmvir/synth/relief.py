"""Built-in shapes with fine relief: slopes of tens of degrees at wavelengths of a few pixels.

Each is a radial function on one fine geodesic sphere (frequency 100: 200,000 faces, edges of
about 2 px at 612 x 512 with the rig's default distance), so it is closed, star-shaped, free of
self-intersections and outward-oriented by construction; fixed (not seeded), so a name always
means the same surface. Wavelengths below are in the unnormalized frame, where the largest
radius is about 1 (about 215 px in a 612 x 512 view of the default rig):

* ``rock``: a sphere displaced by five octaves of isotropic noise (wavelengths 0.64 down to
  0.04, about 9 px), the amplitude proportional to the wavelength, so every octave adds
  slopes of the same size (a fractal of dimension 2).
* ``panel``: a round relief panel standing upright, a flat rounded slab (a superellipsoid)
  whose two faces carry raised rings, radial grooves and a fine knurl (wavelength 0.05,
  about 11 px).
* ``cloth``: cloth draped over a ball: folds that hang from the top and deepen towards the
  hem, with fine creases across them (wavelength 0.06, about 10 px).
"""

from __future__ import annotations

import numpy as np

from pmvir.synth.shapes import geodesic_sphere

RELIEF_SHAPES: tuple[str, ...] = ("rock", "panel", "cloth")
#: Geodesic frequency of the relief shapes' sphere: 20 * 100**2 = 200,000 faces.
FREQUENCY = 100


def _noise(points: np.ndarray, wavelength: float, rng: np.random.Generator, waves: int = 12) -> np.ndarray:
    """Band-limited isotropic noise of one wavelength: ``waves`` plane waves of random directions
    and phases, unit RMS, (N,)."""
    dirs = rng.normal(size=(waves, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    phases = rng.uniform(0.0, 2.0 * np.pi, waves)
    return np.sqrt(2.0 / waves) * np.cos(2.0 * np.pi / wavelength * points @ dirs.T + phases).sum(axis=1)


def _rock() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(20261128)
    dirs, faces = geodesic_sphere(FREQUENCY)
    x, y, z = dirs.T
    r = 1.0 + 0.08 * x * y - 0.06 * (z * z - 1.0 / 3.0) + 0.05 * y  # a broad, lumpy body
    for wavelength in (0.64, 0.32, 0.16, 0.08, 0.04):
        # an RMS slope of about 8 degrees per octave, 18 degrees together
        r = r + 0.03 * wavelength * _noise(dirs, wavelength, rng)
    return dirs * r[:, None], faces


def _superellipsoid_radius(dirs: np.ndarray, half_thickness: float, exponent: float) -> np.ndarray:
    """Radius along each unit direction of ``rho^e + |z / c|^e = 1`` (rho the distance from z)."""
    rho = np.hypot(dirs[:, 0], dirs[:, 1])
    return (rho**exponent + np.abs(dirs[:, 2] / half_thickness) ** exponent) ** (-1.0 / exponent)


def _panel() -> tuple[np.ndarray, np.ndarray]:
    dirs, faces = geodesic_sphere(FREQUENCY)
    r = _superellipsoid_radius(dirs, half_thickness=0.3, exponent=4.0)
    p = dirs * r[:, None]
    rho, angle = np.hypot(p[:, 0], p[:, 1]), np.arctan2(p[:, 1], p[:, 0])
    face = np.clip((np.abs(dirs[:, 2]) - 0.2) / 0.15, 0.0, 1.0)  # the carving fades out before the rim
    face = face * face * (3.0 - 2.0 * face) * (rho < 0.9)
    rings = 0.012 * np.cos(2.0 * np.pi * rho / 0.16) ** 2  # raised rings, period 0.08
    grooves = -0.008 * np.exp(-(np.sin(12.0 * angle) ** 2) / 0.05) * (rho > 0.3)  # 24 radial grooves
    u, v = (p[:, 0] + p[:, 1]) * 0.7071, (p[:, 0] - p[:, 1]) * 0.7071
    knurl = 0.004 * np.sin(2.0 * np.pi * u / 0.05) * np.sin(2.0 * np.pi * v / 0.05)  # wavelength 0.05
    depth = face * (rings + grooves + knurl * (rho < 0.3))
    p[:, 2] += np.sign(dirs[:, 2]) * depth  # both faces carved, outwards
    return p @ np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]]), faces  # stood up: faces to +-y


def _cloth() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(20261129)
    dirs, faces = geodesic_sphere(FREQUENCY)
    z, azimuth = dirs[:, 2], np.arctan2(dirs[:, 1], dirs[:, 0])
    hang = np.clip((0.7 - z) / 1.7, 0.0, 1.0)  # 0 on the top, 1 at the hem
    # folds: rounded ridges and narrow valleys, 9 and 17 around, their phase drifting downwards
    folds = np.zeros_like(z)
    for count, amplitude in ((9, 0.09), (17, 0.035)):
        phase = rng.uniform(0, 2 * np.pi) + 0.8 * np.sin(2.0 * z + rng.uniform(0, 2 * np.pi))
        folds += amplitude * (np.abs(np.cos(0.5 * (count * azimuth + phase))) - 0.64)
    creases = 0.005 * _noise(dirs * np.array([1.0, 1.0, 3.0]), 0.18, rng)  # fine creases across the folds
    r = 1.0 - 0.15 * z * z + hang * folds + np.clip((0.9 - z) / 0.6, 0.0, 1.0) * creases
    return dirs * r[:, None], faces


def relief_shape(name: str) -> tuple[np.ndarray, np.ndarray]:
    """Unnormalized (vertices, faces) of one of :data:`RELIEF_SHAPES` (not checked here)."""
    return {"rock": _rock, "panel": _panel, "cloth": _cloth}[name]()
