"""Exact visibility by ray casting (Open3D ``RaycastingScene``) and surface attributes at the hits.

A :class:`MeshScene` holds a normalized mesh with per-vertex normals and albedo
and its ray-casting acceleration structure. :func:`trace` returns, for each ray,
whether it hits, the hit distance, the barycentrically interpolated shading
normal and albedo, so a renderer sees exactly the per-vertex albedo stored in
``gt/mesh.ply``.

Shading normals: the interpolated vertex normal, flipped where the hit triangle
faces away from the ray (the inside of an open mesh is shaded two-sided), then
bent, where it still faces away from the camera (smooth normals at a silhouette),
just enough to face the camera (n.d = -0.01).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import open3d as o3d

from pmvir.camera import Camera
from pmvir.errors import InputError
from pmvir.geometry.mesh_ops import face_normals, raycasting_scene
from pmvir.io.ply import Mesh


@dataclass
class MeshScene:
    """A mesh ready for ray casting.

    Attributes:
        vertices: (V, 3) float64 positions.
        faces: (F, 3) int64 indices.
        normals: (V, 3) float64 unit vertex normals.
        albedo: (V, 3) float32 linear RGB albedo.
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    _scene: o3d.t.geometry.RaycastingScene = field(init=False, repr=False)
    _face_normals: np.ndarray = field(init=False, repr=False)
    _normals32: np.ndarray = field(init=False, repr=False)
    _albedo32: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        # World coordinates (origin 0): the renderer casts its camera rays as they are.
        self._scene = raycasting_scene(self.vertices, self.faces, origin=np.zeros(3)).scene
        self._face_normals = face_normals(self.vertices, self.faces, eps=1e-20).astype(np.float32)
        self._normals32 = np.asarray(self.normals, dtype=np.float32)
        self._albedo32 = np.asarray(self.albedo, dtype=np.float32)

    @classmethod
    def from_mesh(cls, mesh: Mesh) -> MeshScene:
        """Build from a mesh that has normals and albedo."""
        if mesh.normals is None or mesh.albedo is None:
            raise InputError("MeshScene needs a mesh with normals and albedo")
        return cls(mesh.vertices, mesh.faces, mesh.normals.astype(np.float64), mesh.albedo)


@dataclass
class Hits:
    """What a bundle of N rays sees; M of them hit.

    Attributes:
        hit: (N,) bool.
        distance: (N,) float32 ray parameter of the hit along the unit direction (inf on a miss).
        normal: (M, 3) float32 unit shading normals of the hits (rows where ``hit``), world frame.
        albedo: (M, 3) float32 interpolated albedo of the hits.
    """

    hit: np.ndarray
    distance: np.ndarray
    normal: np.ndarray
    albedo: np.ndarray


def trace(scene: MeshScene, origin: np.ndarray, directions: np.ndarray) -> Hits:
    """Cast rays from one origin and interpolate the surface attributes at the first hits.

    Args:
        scene: the mesh.
        origin: (3,) ray origin (the camera centre), world frame.
        directions: (N, 3) unit directions, world frame.
    """
    d = np.asarray(directions, dtype=np.float32)
    rays = np.empty((len(d), 6), dtype=np.float32)
    rays[:, :3] = np.asarray(origin, dtype=np.float32)
    rays[:, 3:] = d
    ans = scene._scene.cast_rays(o3d.core.Tensor(rays))
    t = ans["t_hit"].numpy()
    hit = np.isfinite(t)
    prim = ans["primitive_ids"].numpy()[hit].astype(np.int64)
    uv = ans["primitive_uvs"].numpy()[hit]
    w = (1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1])  # Open3D: p = (1 - u - v) a + u b + v c
    f = scene.faces[prim]
    nrm = sum(w[k][:, None] * scene._normals32[f[:, k]] for k in range(3))
    albedo = sum(w[k][:, None] * scene._albedo32[f[:, k]] for k in range(3))
    dh = d[hit]
    back = (scene._face_normals[prim] * dh).sum(1) > 0  # seen from behind: two-sided
    nrm[back] *= -1.0
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-20)
    nd = (nrm * dh).sum(1)
    bend = nd > -0.01
    if bend.any():
        nrm[bend] -= (nd[bend] + 0.01)[:, None] * dh[bend]
        nrm[bend] /= np.maximum(np.linalg.norm(nrm[bend], axis=1, keepdims=True), 1e-20)
    return Hits(hit=hit, distance=t, normal=nrm.astype(np.float32), albedo=albedo.astype(np.float32))


def rotate_rows(m: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Rows of ``x`` (N, 3) times ``m.T`` for a 3x3 ``m``, written out (faster than a tiny matmul)."""
    m = m.astype(x.dtype)
    return np.stack([x[:, 0] * m[i, 0] + x[:, 1] * m[i, 1] + x[:, 2] * m[i, 2] for i in range(3)], axis=1)


def pixel_directions(camera: Camera, u: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit ray directions through pixel coordinates (COLMAP convention).

    Args:
        camera: the camera.
        u, v: (N,) pixel coordinates (pixel [row, col] centre is (col + 0.5, row + 0.5)).

    Returns:
        world directions (N, 3) and camera-frame directions (N, 3), float32 unit vectors.
    """
    kinv = np.linalg.inv(camera.K)
    u = np.asarray(u, dtype=np.float32)
    v = np.asarray(v, dtype=np.float32)
    x = kinv[0, 0] * u + kinv[0, 1] * v + kinv[0, 2]
    y = kinv[1, 0] * u + kinv[1, 1] * v + kinv[1, 2]
    z = kinv[2, 0] * u + kinv[2, 1] * v + kinv[2, 2]
    inv = 1.0 / np.sqrt(x * x + y * y + z * z)
    d_cam = np.stack([x * inv, y * inv, z * inv], axis=1).astype(np.float32)
    return rotate_rows(camera.R.T, d_cam), d_cam
