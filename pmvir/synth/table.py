"""Scenes with a support under the object: a textured table or a turntable's disc (``scene`` option).

The object (normalized, bounding-box diagonal 1, centred at the origin, +z up)
stands on a horizontal textured surface that touches its lowest point:

* ``table`` (:func:`support_mesh` with ``kind="table"``): a square of side
  :data:`TABLE_SIDE`, photographed by a hand-held camera
  (:func:`handheld_cameras`) from 15 to 60 degrees above the table's plane; the
  lighting environment shows behind the table's edge.
* ``turntable``: a disc of radius :data:`DISC_RADIUS` that turns with the object
  before the still camera of :func:`pmvir.synth.rig.turntable_cameras` and a
  still textured backdrop.

The support is a regular grid with per-vertex albedo (value noise at several
scales, linear RGB in [0.08, 0.8]), so both renderers see the same texture; it
is part of the rendered scene only: the ground truth (``gt/mesh.ply``, masks,
depth, normals) is the object alone.
"""

from __future__ import annotations

from typing import Literal

import cv2
import numpy as np

from pmvir.camera import Camera, look_at
from pmvir.errors import ConfigError
from pmvir.io.ply import Mesh

SCENES: tuple[str, ...] = ("object", "table", "turntable")
Scene = Literal["object", "table", "turntable"]

#: Side of the square table, in object diagonals.
TABLE_SIDE = 5.0
#: Radius of the turntable's disc, in object diagonals.
DISC_RADIUS = 0.8
#: Grid cells per object diagonal (a cell spans about 7 pixels at 612x512 from the default distance).
CELLS_PER_UNIT = 48
#: Elevation range of the hand-held camera above the table's plane, degrees.
HANDHELD_ELEVATION_DEG = (15.0, 60.0)
#: The support sits this far (object diagonals) below the object's lowest point: touching, without
#: coplanar faces where an object has a flat base.
_GAP = 1e-4


def _grid_texture(n: int, rng: np.random.Generator) -> np.ndarray:
    """(n, n, 3) float32 linear albedo in [0.08, 0.8]: value noise at four scales, hue varying."""
    out = np.zeros((n, n, 3), np.float32)
    for cells, weight in ((4, 0.35), (12, 0.3), (40, 0.2), (n // 3, 0.15)):
        coarse = rng.uniform(0.0, 1.0, (max(2, cells), max(2, cells), 3)).astype(np.float32)
        out += weight * cv2.resize(coarse, (n, n), interpolation=cv2.INTER_CUBIC)
    out = (out - out.mean()) / max(float(out.std()), 1e-6)  # full contrast whatever the octaves' sum
    return np.clip(0.4 + 0.16 * out, 0.08, 0.8)


def support_mesh(object_vertices: np.ndarray, kind: Scene, *, seed: int) -> Mesh:
    """The table or disc under an object, with per-vertex albedo and +z normals.

    Args:
        object_vertices: (N, 3) the normalized object's vertices (world units, +z up).
        kind: "table" (square, :data:`TABLE_SIDE`) or "turntable" (disc, :data:`DISC_RADIUS`).
        seed: seed of the texture.

    Returns:
        A :class:`~pmvir.io.ply.Mesh` at height ``min z - _GAP``, centred under the object's
        bounding-box centre, faces counter-clockwise seen from above.
    """
    if kind not in ("table", "turntable"):
        raise ConfigError(f"no support for scene {kind!r}; expected 'table' or 'turntable'")
    v = np.asarray(object_vertices, np.float64)
    centre = 0.5 * (v.min(0) + v.max(0))
    half = TABLE_SIDE / 2.0 if kind == "table" else DISC_RADIUS
    n = int(np.ceil(2.0 * half * CELLS_PER_UNIT)) + 1
    s = np.linspace(-half, half, n)
    gx, gy = np.meshgrid(s, s, indexing="xy")
    vertices = np.stack(
        [gx.ravel() + centre[0], gy.ravel() + centre[1], np.full(n * n, v[:, 2].min() - _GAP)], axis=1
    )
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    if kind == "turntable":
        centroid = (gx.ravel()[faces].mean(1) ** 2 + gy.ravel()[faces].mean(1) ** 2) ** 0.5
        faces = faces[centroid <= half]
        used = np.unique(faces)
        remap = np.full(n * n, -1, np.int64)
        remap[used] = np.arange(len(used))
        vertices, faces = vertices[used], remap[faces]
        albedo = _grid_texture(n, np.random.default_rng([seed, 41])).reshape(-1, 3)[used]
    else:
        albedo = _grid_texture(n, np.random.default_rng([seed, 41])).reshape(-1, 3)
    normals = np.tile([0.0, 0.0, 1.0], (len(vertices), 1))
    return Mesh(vertices, faces.astype(np.int64), albedo=albedo.astype(np.float32), normals=normals)


def combine(a: Mesh, b: Mesh) -> Mesh:
    """One mesh of two (vertices, faces, albedo and normals concatenated; both need albedo and normals)."""
    if a.albedo is None or b.albedo is None or a.normals is None or b.normals is None:
        raise ConfigError("combining meshes needs albedo and normals on both")
    return Mesh(
        np.concatenate([a.vertices, b.vertices]),
        np.concatenate([a.faces, b.faces + len(a.vertices)]),
        albedo=np.concatenate([a.albedo, b.albedo]).astype(np.float32),
        normals=np.concatenate([a.normals, b.normals]),
    )


def handheld_cameras(
    views: int,
    width: int,
    height: int,
    *,
    object_radius: float,
    focal_factor: float = 1.2,
    fill: float = 0.85,
    seed: int = 0,
) -> list[Camera]:
    """A hand-held camera walked around an object on a table, aimed at it from above the table.

    Elevations are spread over :data:`HANDHELD_ELEVATION_DEG` (stratified, shuffled), azimuths
    step by 360/views degrees with +-10 degrees of jitter; the distance varies by -10 to +15 %
    around the one that makes the object's bounding sphere fill ``fill`` of half the smaller
    image side; the aim wanders by up to 3 % of the object's diagonal and the roll by up to
    5 degrees. Deterministic for a seed.
    """
    if views < 1:
        raise ConfigError(f"views must be at least 1, got {views}")
    rng = np.random.default_rng([seed, 29])
    f = focal_factor * max(width, height)
    base = object_radius / np.sin(np.arctan(fill * min(width, height) / 2.0 / f))
    lo, hi = np.radians(HANDHELD_ELEVATION_DEG)
    elev = lo + (hi - lo) * (rng.permutation(views) + rng.uniform(0.0, 1.0, views)) / views
    az = np.radians(360.0 / views * np.arange(views) + rng.uniform(-10.0, 10.0, views) + 15.0)
    dist = base * rng.uniform(0.9, 1.15, views)
    cams = []
    for i in range(views):
        c = dist[i] * np.array(
            [np.cos(elev[i]) * np.cos(az[i]), np.cos(elev[i]) * np.sin(az[i]), np.sin(elev[i])]
        )
        aim = rng.uniform(-0.03, 0.03, 3)
        R, _ = look_at(c, aim, np.array([0.0, 0.0, 1.0]))
        roll = np.radians(rng.uniform(-5.0, 5.0))
        rz = np.array([[np.cos(roll), -np.sin(roll), 0.0], [np.sin(roll), np.cos(roll), 0.0], [0.0, 0.0, 1.0]])
        R = rz @ R
        cams.append(Camera.from_intrinsics(f, f, width / 2.0, height / 2.0, width, height, R, -R @ c))
    return cams
