"""The geometric stage's files for other tools: a COLMAP model, viewable images, point clouds.

* :func:`write_colmap_model`: ``poses/`` written by ``pycolmap.Reconstruction``,
  binary (``cameras.bin``, ``images.bin``, ``points3D.bin``, ``rigs.bin``,
  ``frames.bin``) and text (``cameras.txt``, ``images.txt``, ``points3D.txt``):
  one PINHOLE camera per registered view, its pose, its 2D observations, and
  the sparse points with their colours and tracks. Image names are the files of
  ``images/``, so COLMAP, nerfstudio, 3D Gaussian splatting and OpenMVS open
  the folder with ``images/`` as the image path.
* :func:`viewable_images`: per view I_int as an 8-bit sRGB RGB image, one
  exposure for all views (the 99.5th percentile of the brightest channel over
  every view's object pixels maps to white), so colours agree between views.
* :func:`write_points_ply`: a coloured (optionally oriented) point cloud as
  binary PLY (``sparse.ply``, ``dense.ply``).
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import numpy as np
import pycolmap
from plyfile import PlyData, PlyElement

from pmvir.camera import Camera
from pmvir.polarization.preview import EXPOSURE_PERCENTILE, intensity_preview, write_png


def image_file(name: str) -> str:
    """The file (under ``images/``) and COLMAP image name of the frame called ``name``."""
    return f"{name}.png"


def viewable_images(
    images: Sequence[np.ndarray], masks: Sequence[np.ndarray | None] | None = None
) -> list[np.ndarray]:
    """8-bit sRGB renderings of linear I_int images with one shared exposure (module docstring).

    Args:
        images: per view (H, W, 3) float32 linear I_int (normalized units).
        masks: per view None or an (H, W) bool object mask (the exposure is set on the objects).

    Returns:
        per view (H, W, 3) uint8 RGB.
    """
    masks = list(masks) if masks is not None else [None] * len(images)
    rgb = [np.repeat(im[..., None], 3, axis=2) if im.ndim == 2 else im for im in images]
    peaks = [
        im.max(axis=2)[m] if m is not None and m.any() else im.max(axis=2).ravel()
        for im, m in zip(rgb, masks, strict=True)
    ]
    values = np.concatenate(peaks) if peaks else np.zeros(0, np.float32)
    values = values[np.isfinite(values)]
    level = float(np.percentile(values, EXPOSURE_PERCENTILE)) if values.size else 0.0
    scale = 1.0 / level if level > 1e-12 else 1.0
    return [intensity_preview(np.asarray(im, np.float32), scale=scale) for im in rgb]


def colours_at(
    points: np.ndarray, views: np.ndarray, cameras: Sequence[Camera | None], images: Sequence[np.ndarray]
) -> np.ndarray:
    """(P, 3) uint8: each point's colour in the 8-bit image of the view it came from (nearest pixel)."""
    out = np.full((len(points), 3), 128, np.uint8)
    for v in np.unique(views):
        cam = cameras[int(v)]
        if cam is None:
            continue
        sel = np.flatnonzero(views == v)
        uv, _ = cam.project(points[sel])
        img = images[int(v)]
        col = np.clip(np.floor(uv[:, 0]).astype(np.int64), 0, img.shape[1] - 1)
        row = np.clip(np.floor(uv[:, 1]).astype(np.int64), 0, img.shape[0] - 1)
        out[sel] = img[row, col]
    return out


def write_images(directory: str | Path, names: Sequence[str], images: Sequence[np.ndarray | None]) -> None:
    """``directory/<name>.png`` for every view whose 8-bit RGB image is given."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    for name, image in zip(names, images, strict=True):
        if image is not None:
            write_png(directory / image_file(name), image)


def colmap_reconstruction(
    cameras: Sequence[Camera | None],
    names: Sequence[str],
    points: np.ndarray,
    colors: np.ndarray | None,
    observations: Sequence[np.ndarray] | None,
) -> pycolmap.Reconstruction:
    """A ``pycolmap.Reconstruction`` of the registered views and the sparse points.

    Args:
        cameras: per view its camera or None (unregistered: left out).
        names: per view its frame name; the image is called :func:`image_file` of it.
        points: (P, 3) world points.
        colors: (P, 3) uint8 sRGB or None (grey).
        observations: per point a (k, 3) float64 array of (view index, x, y) pixel observations
            (COLMAP convention), or None (points without tracks are then left out: COLMAP needs
            every point observed).

    Returns:
        The reconstruction; camera, image and frame ids are view index + 1.
    """
    rec = pycolmap.Reconstruction()
    keypoints: dict[int, list[tuple[float, float]]] = {i: [] for i, c in enumerate(cameras) if c is not None}
    tracks: list[list[tuple[int, int]]] = []
    for obs in observations or []:
        track = []
        for view, x, y in np.asarray(obs, np.float64).reshape(-1, 3):
            v = int(view)
            if v in keypoints:
                track.append((v, len(keypoints[v])))
                keypoints[v].append((float(x), float(y)))
        tracks.append(track)
    for i, cam in enumerate(cameras):
        if cam is None:
            continue
        camera = pycolmap.Camera(
            model="PINHOLE",
            width=int(cam.width),
            height=int(cam.height),
            params=[cam.K[0, 0], cam.K[1, 1], cam.K[0, 2], cam.K[1, 2]],
            camera_id=i + 1,
        )
        rec.add_camera_with_trivial_rig(camera)
        xy = np.asarray(keypoints[i], np.float64).reshape(-1, 2)
        image = pycolmap.Image(name=image_file(names[i]), keypoints=xy, camera_id=i + 1, image_id=i + 1)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(pycolmap.Rotation3d(cam.R), cam.t))
    colour = np.full((len(points), 3), 128, np.uint8) if colors is None else np.asarray(colors, np.uint8)
    for k, track in enumerate(tracks):
        if len(track) < 2:
            continue
        t = pycolmap.Track()
        for view, idx in track:
            t.add_element(view + 1, idx)
        rec.add_point3D(np.asarray(points[k], np.float64), t, colour[k])
    rec.update_point_3d_errors()
    return rec


def write_colmap_model(directory: str | Path, reconstruction: pycolmap.Reconstruction) -> Path:
    """``directory`` with the model in COLMAP's binary and text formats (module docstring)."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    reconstruction.write_binary(str(directory))
    reconstruction.write_text(str(directory))
    return directory


def write_points_ply(
    path: str | Path, points: np.ndarray, colors: np.ndarray | None = None, normals: np.ndarray | None = None
) -> Path:
    """Binary little-endian PLY of (P, 3) points, optional (P, 3) uint8 colours and (P, 3) normals."""
    pts = np.asarray(points, np.float32).reshape(-1, 3)
    fields = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    if normals is not None:
        fields += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
    if colors is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    data = np.empty(len(pts), dtype=fields)
    data["x"], data["y"], data["z"] = pts.T
    if normals is not None:
        n = np.asarray(normals, np.float32).reshape(-1, 3)
        data["nx"], data["ny"], data["nz"] = n.T
    if colors is not None:
        c = np.asarray(colors, np.uint8).reshape(-1, 3)
        data["red"], data["green"], data["blue"] = c.T
    PlyData([PlyElement.describe(data, "vertex")], text=False, byte_order="<").write(str(path))
    return Path(path)
