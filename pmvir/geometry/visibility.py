"""Per-vertex visibility in every view (paper section 4.2), by ray casting.

A vertex ``p`` is visible in a view when all of these hold:

1. it projects in front of the camera (depth > 0) and inside the image,
   ``0 <= u < width``, ``0 <= v < height`` (COLMAP pixel convention);
2. if the view has a mask, the mask is true at the pixel holding it, i.e. at
   array index ``[floor(v), floor(u)]``;
3. it faces the camera: ``n . (c - p) / |c - p| > min_cos`` with ``n`` the
   area-weighted vertex normal (:func:`pmvir.geometry.mesh_ops.vertex_normals`) and ``c``
   the camera centre;
4. no triangle of the mesh crosses the segment from ``c`` to ``p`` before
   ``c + (1 - rel_tol) (p - c)``. Triangles that contain ``p`` meet the line
   only at ``p`` itself, so ``rel_tol`` only has to absorb the float32
   rounding of the ray caster (Embree through Open3D); an occluder closer to
   ``p`` than ``rel_tol * |c - p|`` along the ray is ignored.

The ray caster works in float32 on the mesh shifted to its centroid, so
visibility does not degrade for scenes far from the world origin.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pmvir.camera import Camera
from pmvir.errors import ConfigError, ShapeError
from pmvir.geometry.mesh_ops import check_faces, check_vertices, raycasting_scene, vertex_normals
from pmvir.geometry.projection import project_columns


def vertex_visibility(
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    masks: Sequence[np.ndarray | None] | None = None,
    *,
    min_cos: float = 0.05,
    rel_tol: float = 1e-4,
    normals: np.ndarray | None = None,
) -> np.ndarray:
    """Which vertex is visible in which view.

    Args:
        vertices: (N, 3) float world positions.
        faces: (F, 3) integer vertex indices, counter-clockwise seen from outside.
        cameras: V cameras (cam_from_world, COLMAP pixel convention).
        masks: None, or V entries each None (no mask) or a bool (height, width)
            array, true on the object.
        min_cos: a vertex whose normal makes a cosine at most ``min_cos`` with the
            direction to the camera counts as back-facing (0.05 is about 87 degrees).
        rel_tol: relative tolerance of the occlusion test along the ray, in (0, 0.5).
        normals: optional (N, 3) unit vertex normals; default area-weighted ones
            (a vertex used by no face then has a zero normal and is never visible
            for ``min_cos >= 0``).

    Returns:
        (N, V) bool, true where the vertex is visible in the view.

    Raises:
        MeshError: malformed faces.
        ShapeError: wrong shapes, masks not matching cameras.
        ConfigError: options out of range.
    """
    import open3d as o3d

    v = check_vertices(vertices)
    f = check_faces(faces, len(v))
    if not 0.0 < rel_tol < 0.5:
        raise ConfigError(f"rel_tol must lie in (0, 0.5), got {rel_tol}")
    if not -1.0 <= min_cos < 1.0:
        raise ConfigError(f"min_cos must lie in [-1, 1), got {min_cos}")
    masks = _check_masks(masks, cameras)
    if normals is None:
        n = vertex_normals(v, f)
    else:
        n = np.asarray(normals, dtype=np.float64)
        if n.shape != v.shape:
            raise ShapeError(f"expected normals of shape {v.shape}, got {n.shape}")

    vis = np.zeros((len(v), len(cameras)), dtype=bool)
    if len(v) == 0 or len(cameras) == 0:
        return vis
    scene = raycasting_scene(v, f)
    v_local = scene.local(v)
    v_t, n_t = np.ascontiguousarray(v.T), np.ascontiguousarray(n.T)
    for j, cam in enumerate(cameras):
        cand = _view_candidates(v_t, n_t, cam, masks[j], min_cos=min_cos)
        idx = np.flatnonzero(cand)
        if len(idx) == 0 or len(f) == 0:
            vis[idx, j] = True
            continue
        c_local = scene.local(cam.center)
        rays = np.empty((len(idx), 6), dtype=np.float32)
        rays[:, :3] = c_local
        rays[:, 3:] = v_local[idx] - c_local
        occluded = scene.scene.test_occlusions(o3d.core.Tensor(rays), tnear=0.0, tfar=1.0 - rel_tol).numpy()
        vis[idx[~occluded], j] = True
    return vis




def _view_candidates(
    v_t: np.ndarray, n_t: np.ndarray, cam: Camera, mask: np.ndarray | None, *, min_cos: float
) -> np.ndarray:
    """(N,) bool: in front, inside the image, inside the mask and front-facing (no occlusion test)."""
    u, w, depth = project_columns(v_t, cam)
    ok = (depth > 0) & (u >= 0) & (u < cam.width) & (w >= 0) & (w < cam.height)
    if mask is not None:
        idx = np.flatnonzero(ok)
        col = np.floor(u[idx]).astype(np.int64)
        row = np.floor(w[idx]).astype(np.int64)
        ok[idx] = mask[np.minimum(row, cam.height - 1), np.minimum(col, cam.width - 1)]
    c = cam.center
    dx, dy, dz = c[0] - v_t[0], c[1] - v_t[1], c[2] - v_t[2]
    dist = np.sqrt(dx * dx + dy * dy + dz * dz)
    cos = (n_t[0] * dx + n_t[1] * dy + n_t[2] * dz) / np.maximum(dist, 1e-30)
    ok &= cos > min_cos
    return ok


def face_visibility(faces: np.ndarray, vertex_vis: np.ndarray, *, min_visible_corners: int = 3) -> np.ndarray:
    """Per-face visibility from per-vertex visibility.

    Args:
        faces: (F, 3) integer vertex indices.
        vertex_vis: (N, V) bool vertex visibility.
        min_visible_corners: a face is visible in a view when at least this many
            of its three corners are (3: all, 2: majority, 1: any).

    Returns:
        (F, V) bool.
    """
    if min_visible_corners not in (1, 2, 3):
        raise ConfigError(f"min_visible_corners must be 1, 2 or 3, got {min_visible_corners}")
    vis = np.asarray(vertex_vis, dtype=bool)
    if vis.ndim != 2:
        raise ShapeError(f"expected (N, V) vertex visibility, got shape {vis.shape}")
    f = check_faces(faces, len(vis))
    if min_visible_corners == 3:
        return vis[f[:, 0]] & vis[f[:, 1]] & vis[f[:, 2]]
    if min_visible_corners == 1:
        return vis[f[:, 0]] | vis[f[:, 1]] | vis[f[:, 2]]
    count = vis[f[:, 0]].astype(np.int8) + vis[f[:, 1]] + vis[f[:, 2]]
    return count >= 2


def _check_masks(masks: Sequence[np.ndarray | None] | None, cameras: Sequence[Camera]) -> list:
    if masks is None:
        return [None] * len(cameras)
    if len(masks) != len(cameras):
        raise ShapeError(f"expected one mask entry per camera ({len(cameras)}), got {len(masks)}")
    out: list[np.ndarray | None] = []
    for j, (m, cam) in enumerate(zip(masks, cameras, strict=True)):
        if m is None:
            out.append(None)
            continue
        m = np.asarray(m)
        if m.shape != (cam.height, cam.width):
            raise ShapeError(f"mask {j}: expected shape ({cam.height}, {cam.width}), got {m.shape}")
        out.append(m.astype(bool, copy=False))
    return out
