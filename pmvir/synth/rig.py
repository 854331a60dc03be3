"""Camera placement for synthetic captures: rings on a sphere around the object, or a turntable.

World frame: +z is up; the normalized object sits at the origin. Cameras look at
the origin with world up shown up (:func:`pmvir.camera.look_at`).

* ``rings`` (:func:`ring_cameras`): rings at three elevations (below, level,
  above) once there are at least six views, staggered in azimuth from ring to ring.
* ``turntable`` (:func:`turntable_cameras`): one camera stays still while the
  object turns about +z by 360/views degrees per frame. In the object's frame
  (the world of the capture's poses) that is one ring of cameras at
  :data:`TURNTABLE_ELEVATION_DEG`; the backdrop turns with the camera, so it
  looks the same in every frame (the renderer paints it; see
  :func:`pmvir.synth.generate.synthesize`).
"""

from __future__ import annotations

import numpy as np

from pmvir.camera import Camera, look_at
from pmvir.errors import ConfigError

#: Ring elevations in degrees (below, level, above), used for six or more views.
RING_ELEVATIONS_DEG: tuple[float, ...] = (-25.0, 10.0, 45.0)

#: Elevation of the still camera of a turntable capture, degrees above the table's axis.
TURNTABLE_ELEVATION_DEG = 20.0

RIGS: tuple[str, ...] = ("rings", "turntable")


def ring_positions(views: int, radius: float, *, elevations: tuple[float, ...] | None = None) -> np.ndarray:
    """Camera centres on rings around the origin, (views, 3) float64, world units.

    Six or more views use the three elevations of :data:`RING_ELEVATIONS_DEG`
    (the views split as evenly as possible, the extra ones on the level ring);
    fewer views form one ring at 10 degrees; ``elevations`` (degrees) overrides them.
    """
    if views < 1:
        raise ConfigError(f"views must be at least 1, got {views}")
    elevs = elevations or (RING_ELEVATIONS_DEG if views >= 6 else (RING_ELEVATIONS_DEG[1],))
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
    elevations: tuple[float, ...] | None = None,
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
    for c in ring_positions(views, distance, elevations=elevations):
        R, t = look_at(c, np.zeros(3), np.array([0.0, 0.0, 1.0]))
        cams.append(Camera.from_intrinsics(f, f, width / 2.0, height / 2.0, width, height, R, t))
    return cams


def turntable_cameras(
    views: int,
    width: int,
    height: int,
    *,
    object_radius: float,
    focal_factor: float = 1.2,
    fill: float = 0.85,
) -> list[Camera]:
    """The still camera of a turntable capture as seen from the turning object (module docstring).

    Frame i shows the object turned by ``i * 360 / views`` degrees; its pose in the object's
    frame is the camera turned back by that angle: one ring at :data:`TURNTABLE_ELEVATION_DEG`.
    """
    return ring_cameras(
        views,
        width,
        height,
        object_radius=object_radius,
        focal_factor=focal_factor,
        fill=fill,
        elevations=(TURNTABLE_ELEVATION_DEG,),
    )


def rig_cameras(
    rig: str, views: int, width: int, height: int, *, object_radius: float, focal_factor: float
) -> list[Camera]:
    """Cameras of the named rig (:data:`RIGS`)."""
    if rig == "turntable":
        return turntable_cameras(views, width, height, object_radius=object_radius, focal_factor=focal_factor)
    if rig != "rings":
        raise ConfigError(f"unknown rig {rig!r}; expected one of {', '.join(RIGS)}")
    return ring_cameras(views, width, height, object_radius=object_radius, focal_factor=focal_factor)
