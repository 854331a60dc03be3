"""Camera placement for synthetic captures: rings on a sphere around the object.

World frame: +z is up; the normalized object sits at the origin. Cameras look at
the origin with world up shown up (:func:`pmvir.camera.look_at`), on rings at
three elevations (below, level, above) once there are at least six views,
staggered in azimuth from ring to ring.
"""

from __future__ import annotations

import numpy as np

from pmvir.camera import Camera, look_at
from pmvir.errors import ConfigError

#: Ring elevations in degrees (below, level, above), used for six or more views.
RING_ELEVATIONS_DEG: tuple[float, ...] = (-25.0, 10.0, 45.0)


def ring_positions(views: int, radius: float) -> np.ndarray:
    """Camera centres on rings around the origin, (views, 3) float64, world units.

    Six or more views use the three elevations of :data:`RING_ELEVATIONS_DEG`
    (the views split as evenly as possible, the extra ones on the level ring);
    fewer views form one ring at 10 degrees.
    """
    if views < 1:
        raise ConfigError(f"views must be at least 1, got {views}")
    elevs = RING_ELEVATIONS_DEG if views >= 6 else (RING_ELEVATIONS_DEG[1],)
    counts = [views // len(elevs)] * len(elevs)
    for k in range(views - sum(counts)):
        counts[(1 + k) % len(elevs)] += 1
    out = []
    for ring, (elev, n) in enumerate(zip(elevs, counts, strict=True)):
        az = np.radians(360.0 / n * (np.arange(n) + ring / len(elevs)) + 15.0)
        e = np.radians(elev)
        out.append(np.stack([np.cos(e) * np.cos(az), np.cos(e) * np.sin(az), np.full(n, np.sin(e))], axis=1))
    return radius * np.concatenate(out, axis=0)


def ring_cameras(
    views: int,
    width: int,
    height: int,
    *,
    object_radius: float,
    focal_factor: float = 1.2,
    fill: float = 0.85,
) -> list[Camera]:
    """Cameras on rings around an object of bounding radius ``object_radius`` at the origin.

    Args:
        views: number of cameras.
        width, height: image size in pixels.
        object_radius: largest distance of a vertex from the origin (world units).
        focal_factor: focal length in pixels divided by ``max(width, height)``.
        fill: fraction of half the smaller image side the object's bounding sphere fills.

    Returns:
        ``views`` cameras, principal point at the image centre (COLMAP convention),
        square pixels.
    """
    f = focal_factor * max(width, height)
    tan_half = fill * min(width, height) / 2.0 / f
    distance = object_radius / np.sin(np.arctan(tan_half))
    cams = []
    for c in ring_positions(views, distance):
        R, t = look_at(c, np.zeros(3), np.array([0.0, 0.0, 1.0]))
        cams.append(Camera.from_intrinsics(f, f, width / 2.0, height / 2.0, width, height, R, t))
    return cams
