"""COLMAP's dense stereo through pycolmap: workspace, PatchMatch (CUDA) and stereo fusion.

When ``pycolmap.has_cuda`` is true (and ``GeometryOptions.mvs_backend`` is
'auto' or 'colmap-cuda'), COLMAP's PatchMatch stereo replaces pmvir's CPU
plane sweep. pmvir writes the COLMAP dense workspace itself (the cameras are
already undistorted pinholes)::

    ROOT/images/<name>.png            8-bit tone-mapped I_int (sRGB-like curve)
    ROOT/masks/<name>.png.png         object masks, named as COLMAP's fusion expects
    ROOT/sparse/cameras.txt ...       the poses (COLMAP text model, PINHOLE)
    ROOT/stereo/patch-match.cfg       each image and its source images (pmvir's view selection)
    ROOT/stereo/fusion.cfg            the images to fuse
    ROOT/stereo/depth_maps/<name>.geometric.bin, normal_maps/..., consistency_graphs/

then runs ``pycolmap.patch_match_stereo`` and ``pycolmap.stereo_fusion``. The
fusion step also runs on the CPU: :func:`write_depth_maps` puts depth and normal
maps computed elsewhere (e.g. by :mod:`pmvir.geometry.mvs.sweep`) into the workspace in
COLMAP's binary array format, so the same fusion can be used (and tested)
without CUDA.

COLMAP's array format (``src/colmap/mvs/mat.h``): an ASCII header
``width&height&channels&`` then float32 little-endian values, channel by
channel, each channel row by row.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import cv2
import numpy as np

from pmvir.camera import Camera
from pmvir.errors import ReconstructionError, ShapeError
from pmvir.geometry.projection import project_points
from pmvir.io.colmap_text import ColmapImage, image_from_camera, pinhole_from_camera, write_colmap_text_model

_EPS = 1e-12


def write_colmap_array(path: str | Path, array: np.ndarray) -> None:
    """Write an (h, w) or (h, w, c) array in COLMAP's dense binary format (float32)."""
    a = np.asarray(array, np.float32)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3:
        raise ShapeError(f"expected an (h, w) or (h, w, c) array, got shape {a.shape}")
    h, w, c = a.shape
    with open(path, "wb") as f:
        f.write(f"{w}&{h}&{c}&".encode("ascii"))
        f.write(np.ascontiguousarray(a.transpose(2, 0, 1)).astype("<f4").tobytes())


def read_colmap_array(path: str | Path) -> np.ndarray:
    """Read a COLMAP dense binary array; (h, w) for one channel, else (h, w, c) float32."""
    data = Path(path).read_bytes()
    fields, pos = [], 0
    for _ in range(3):
        end = data.index(b"&", pos)
        fields.append(int(data[pos:end]))
        pos = end + 1
    w, h, c = fields
    a = np.frombuffer(data, dtype="<f4", count=w * h * c, offset=pos).reshape(c, h, w).transpose(1, 2, 0)
    return a[..., 0].copy() if c == 1 else a.copy()


def tone_map_8bit(image: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """(H, W, 3) uint8 of a linear image: 99th percentile (in the mask) scaled to white, then ** (1/2.2)."""
    a = np.maximum(np.asarray(image, np.float32), 0.0)
    sel = a[mask] if mask is not None and mask.any() else a.reshape(-1, a.shape[-1])
    top = float(np.percentile(sel, 99.0)) if sel.size else 1.0
    a = np.clip(a / max(top, _EPS), 0.0, 1.0) ** (1.0 / 2.2)
    return np.round(a * 255.0).astype(np.uint8)


def _observations(
    points: np.ndarray, cameras: Sequence[Camera], masks: Sequence[np.ndarray | None]
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per view, the (uv, point index) of the sparse points projecting inside its image and mask."""
    out = []
    for cam, mask in zip(cameras, masks, strict=True):
        uv, z = project_points(cam, points)
        c, r = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        ok = (z > 0) & (c >= 0) & (c < cam.width) & (r >= 0) & (r < cam.height)
        if mask is not None:
            ok[ok] &= np.asarray(mask, bool)[r[ok], c[ok]]
        idx = np.flatnonzero(ok)
        out.append((uv[idx], idx))
    return out


def _write_points3d(path: Path, points: np.ndarray, obs: list[tuple[np.ndarray, np.ndarray]]) -> None:
    """``points3D.txt`` with each point's track (IMAGE_ID = view + 1, POINT2D_IDX in that image's list)."""
    tracks: list[list[str]] = [[] for _ in range(len(points))]
    for view, (_, idx) in enumerate(obs):
        for k, p in enumerate(idx):
            tracks[p].append(f"{view + 1} {k}")
    lines = ["# 3D point list: POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)"]
    for p, (xyz, track) in enumerate(zip(points, tracks, strict=True)):
        if track:
            lines.append(
                f"{p + 1} " + " ".join(f"{float(x):.17g}" for x in xyz) + " 128 128 128 0 " + " ".join(track)
            )
    path.write_text("\n".join(lines) + "\n")


def write_workspace(
    root: str | Path,
    images: Sequence[np.ndarray],
    masks: Sequence[np.ndarray | None],
    cameras: Sequence[Camera],
    names: Sequence[str],
    neighbours: Sequence[Sequence[int]],
    points: np.ndarray,
) -> Path:
    """Write a COLMAP dense workspace (module docstring) for the given views.

    Args:
        root: the workspace folder (created).
        images: per view (H, W, 3) float32 linear I_int.
        masks: per view a bool (H, W) mask or None.
        cameras: per view its camera (PINHOLE, no distortion).
        names: per view a file stem without whitespace; images are ``<name>.png``.
        neighbours: per view the source views PatchMatch compares it with.
        points: (P, 3) sparse points; each is observed in the views it projects into (inside
            the mask). COLMAP's fusion finds overlapping images through them.

    Returns:
        ``root``.
    """
    root = Path(root)
    for sub in (
        "images",
        "masks",
        "sparse",
        "stereo/depth_maps",
        "stereo/normal_maps",
        "stereo/consistency_graphs",
    ):
        (root / sub).mkdir(parents=True, exist_ok=True)
    files = [f"{n}.png" for n in names]
    for img, mask, file in zip(images, masks, files, strict=True):
        cv2.imwrite(str(root / "images" / file), tone_map_8bit(img, mask)[..., ::-1])
        m = np.ones(img.shape[:2], bool) if mask is None else np.asarray(mask, bool)
        cv2.imwrite(str(root / "masks" / f"{file}.png"), m.astype(np.uint8) * 255)
    pts = np.asarray(points, np.float64).reshape(-1, 3)
    obs = _observations(pts, cameras, masks)
    records = []
    for i, (f, c) in enumerate(zip(files, cameras, strict=True)):
        rec = image_from_camera(i + 1, i + 1, f, c)
        uv, idx = obs[i]
        records.append(ColmapImage(rec.image_id, rec.qvec, rec.tvec, rec.camera_id, f, uv, idx + 1))
    write_colmap_text_model(
        root / "sparse", [pinhole_from_camera(i + 1, c) for i, c in enumerate(cameras)], records
    )
    _write_points3d(root / "sparse" / "points3D.txt", pts, obs)
    lines = []
    for i, file in enumerate(files):
        if neighbours[i]:
            lines += [file, ", ".join(files[j] for j in neighbours[i])]
    (root / "stereo" / "patch-match.cfg").write_text("\n".join(lines) + "\n")
    fused = [f for i, f in enumerate(files) if neighbours[i]]
    (root / "stereo" / "fusion.cfg").write_text("\n".join(fused) + "\n")
    return root


def depth_normals(camera: Camera, depth: np.ndarray) -> np.ndarray:
    """Camera-frame unit normals of a depth map (cross product of central differences), facing the camera.

    Args:
        camera: the depth map's camera (its grid).
        depth: (h, w) float camera-frame z, 0 where unknown.

    Returns:
        (h, w, 3) float32, zero where the depth or a neighbour in the differences is unknown.
    """
    h, w = depth.shape
    cols, rows = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    rays = np.stack([cols, rows, np.ones_like(cols)], -1) @ np.linalg.inv(camera.K).T
    P = rays * depth[..., None]
    dx = np.zeros_like(P)
    dy = np.zeros_like(P)
    dx[:, 1:-1] = P[:, 2:] - P[:, :-2]
    dy[1:-1] = P[2:] - P[:-2]
    n = np.cross(dx, dy)
    known = depth > 0
    ok = known.copy()
    ok[:, 1:-1] &= known[:, 2:] & known[:, :-2]
    ok[1:-1] &= known[2:] & known[:-2]
    ok[[0, -1], :] = False
    ok[:, [0, -1]] = False
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), _EPS)
    flip = (n * P).sum(-1) > 0  # must face the camera: n . (point - centre) < 0
    n[flip] *= -1.0
    n[~ok] = 0.0
    return n.astype(np.float32)


def write_depth_maps(
    root: str | Path, names: Sequence[str], depth_maps: Sequence, *, kind: str = "geometric"
) -> None:
    """Write depth and normal maps (DepthMap or None per view) into a workspace: ``<name>.png.<kind>.bin``."""
    root = Path(root)
    for name, dm in zip(names, depth_maps, strict=True):
        if dm is None:
            continue
        depth = np.where(dm.depth > 0, dm.depth, 0.0).astype(np.float32)
        normals = depth_normals(dm.camera, depth)
        depth = np.where(np.abs(normals).sum(-1) > 0, depth, 0.0)
        write_colmap_array(root / "stereo" / "depth_maps" / f"{name}.png.{kind}.bin", depth)
        write_colmap_array(root / "stereo" / "normal_maps" / f"{name}.png.{kind}.bin", normals)


def colmap_patch_match(
    root: str | Path,
    *,
    depth_range: tuple[float, float],
    window_radius: int = 5,
    max_image_size: int = -1,
    geom_consistency: bool = True,
) -> None:
    """Run COLMAP's PatchMatch stereo (CUDA) on a workspace from :func:`write_workspace`.

    Raises:
        ReconstructionError: pycolmap has no CUDA, or PatchMatch failed.
    """
    import pycolmap

    if not pycolmap.has_cuda:
        raise ReconstructionError(
            "COLMAP PatchMatch stereo needs pycolmap built with CUDA (pycolmap.has_cuda is False)"
        )
    opts = pycolmap.PatchMatchOptions()
    opts.depth_min, opts.depth_max = float(depth_range[0]), float(depth_range[1])
    opts.window_radius = int(window_radius)
    opts.max_image_size = int(max_image_size)
    opts.geom_consistency = bool(geom_consistency)
    try:
        pycolmap.patch_match_stereo(str(root), workspace_format="COLMAP", options=opts)
    except Exception as exc:  # pycolmap raises plain RuntimeError / ValueError
        raise ReconstructionError(f"COLMAP PatchMatch stereo failed: {exc}") from exc


def colmap_fusion(
    root: str | Path,
    *,
    kind: str = "geometric",
    min_num_pixels: int = 3,
    max_reproj_error: float = 2.0,
    max_depth_error: float = 0.01,
    max_normal_error_deg: float = 10.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Fuse a workspace's depth maps with COLMAP's stereo fusion (CPU).

    Returns:
        points (P, 3) float64 and unit normals (P, 3) float64 (as COLMAP fused them).

    Raises:
        ReconstructionError: fusion failed.
    """
    import pycolmap
    from plyfile import PlyData

    root = Path(root)
    opts = pycolmap.StereoFusionOptions()
    opts.min_num_pixels = int(min_num_pixels)
    opts.max_reproj_error = float(max_reproj_error)
    opts.max_depth_error = float(max_depth_error)
    opts.max_normal_error = float(max_normal_error_deg)
    opts.mask_path = str(root / "masks")
    out = root / "fused.ply"
    try:
        pycolmap.stereo_fusion(
            str(out), str(root), workspace_format="COLMAP", input_type=kind, options=opts, output_type="PLY"
        )
    except Exception as exc:
        raise ReconstructionError(f"COLMAP stereo fusion failed: {exc}") from exc
    if not out.is_file():
        raise ReconstructionError(f"COLMAP stereo fusion wrote no {out.name}")
    v = PlyData.read(str(out))["vertex"].data
    points = np.stack([v["x"], v["y"], v["z"]], 1).astype(np.float64)
    normals = np.stack([v["nx"], v["ny"], v["nz"]], 1).astype(np.float64)
    normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), _EPS)
    return points, normals
