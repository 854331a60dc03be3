"""COLMAP text models: ``cameras.txt``, ``images.txt`` (and an empty ``points3D.txt``).

The format is COLMAP's documented text format (colmap.github.io/format.html),
read and written the way COLMAP's own ``reconstruction_io_text.cc`` does:

* ``cameras.txt``: one line per camera, ``CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]``.
* ``images.txt``: two lines per image, ``IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME``
  then ``POINTS2D[]`` as ``X Y POINT3D_ID`` triples (the second line may be empty;
  ``POINT3D_ID`` -1 means "no 3D point"). The pose is ``cam_from_world``: the
  Hamilton unit quaternion (w first) and translation with
  ``x_cam = R @ x_world + t``; the camera centre is ``-R^T t``.
* Lines starting with ``#`` and blank lines between records are ignored; fields
  are separated by single spaces; numbers are written with 17 significant digits
  so that a round trip is lossless.

Image names cannot hold whitespace (COLMAP splits the line on spaces). Models
with ``rigs.txt``/``frames.txt`` (COLMAP >= 3.12) are read too: those two files
are ignored, since every image line still carries its own ``cam_from_world``.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pmvir.camera import Camera
from pmvir.errors import PmvirError

#: Number of parameters of each COLMAP camera model (src/colmap/sensor/models.h).
CAMERA_MODEL_NUM_PARAMS: dict[str, int] = {
    "SIMPLE_PINHOLE": 3,
    "PINHOLE": 4,
    "SIMPLE_RADIAL": 4,
    "RADIAL": 5,
    "OPENCV": 8,
    "OPENCV_FISHEYE": 8,
    "FULL_OPENCV": 12,
    "FOV": 5,
    "SIMPLE_RADIAL_FISHEYE": 4,
    "RADIAL_FISHEYE": 5,
    "THIN_PRISM_FISHEYE": 12,
    "RAD_TAN_THIN_PRISM_FISHEYE": 16,
    "SIMPLE_DIVISION": 4,
    "DIVISION": 5,
    "SIMPLE_FISHEYE": 3,
    "FISHEYE": 4,
    "EQUIRECTANGULAR": 2,
    "EUCM": 6,
}


class ColmapFormatError(PmvirError):
    """A COLMAP text file is missing or does not follow the format."""


@dataclass(frozen=True)
class ColmapCamera:
    """One line of ``cameras.txt``.

    Attributes:
        camera_id: COLMAP's CAMERA_ID (>= 1 by COLMAP's habit, any non-negative int accepted).
        model: model name, a key of ``CAMERA_MODEL_NUM_PARAMS``.
        width, height: image size in pixels.
        params: the model's parameters in COLMAP's order (PINHOLE: fx, fy, cx, cy).
    """

    camera_id: int
    model: str
    width: int
    height: int
    params: tuple[float, ...]

    def __post_init__(self) -> None:
        object.__setattr__(self, "params", tuple(float(p) for p in self.params))
        expected = CAMERA_MODEL_NUM_PARAMS.get(self.model)
        if expected is None:
            raise ColmapFormatError(f"camera {self.camera_id}: unknown COLMAP camera model {self.model!r}")
        if len(self.params) != expected:
            raise ColmapFormatError(
                f"camera {self.camera_id}: model {self.model} takes {expected} parameters, "
                f"got {len(self.params)}"
            )

    def K(self) -> np.ndarray:
        """(3, 3) float64 pinhole matrix of a SIMPLE_PINHOLE or PINHOLE camera."""
        if self.model == "SIMPLE_PINHOLE":
            f, cx, cy = self.params
            fx = fy = f
        elif self.model == "PINHOLE":
            fx, fy, cx, cy = self.params
        else:
            raise ColmapFormatError(f"camera {self.camera_id}: model {self.model} is not a pinhole model")
        return np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class ColmapImage:
    """Two lines of ``images.txt``.

    Attributes:
        image_id: COLMAP's IMAGE_ID.
        qvec: (4,) float64 cam_from_world rotation as a Hamilton quaternion (w, x, y, z).
        tvec: (3,) float64 cam_from_world translation.
        camera_id: the CAMERA_ID of its intrinsics.
        name: image name (no whitespace), e.g. the frame's file as in capture.json.
        points2d: (P, 2) float64 keypoint positions in pixels (COLMAP convention).
        point3d_ids: (P,) int64 POINT3D_ID per keypoint, -1 where none.
    """

    image_id: int
    qvec: np.ndarray
    tvec: np.ndarray
    camera_id: int
    name: str
    points2d: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    point3d_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))

    def __post_init__(self) -> None:
        object.__setattr__(self, "qvec", np.asarray(self.qvec, dtype=np.float64).reshape(4))
        object.__setattr__(self, "tvec", np.asarray(self.tvec, dtype=np.float64).reshape(3))
        object.__setattr__(self, "points2d", np.asarray(self.points2d, dtype=np.float64).reshape(-1, 2))
        object.__setattr__(self, "point3d_ids", np.asarray(self.point3d_ids, dtype=np.int64).reshape(-1))
        if len(self.points2d) != len(self.point3d_ids):
            raise ColmapFormatError(
                f"image {self.image_id}: {len(self.points2d)} points2d "
                f"but {len(self.point3d_ids)} point3d_ids"
            )
        if not self.name or any(c.isspace() for c in self.name):
            raise ColmapFormatError(f"image {self.image_id}: name {self.name!r} is empty or holds whitespace")
        if not np.isfinite(self.qvec).all() or np.linalg.norm(self.qvec) < 1e-12:
            raise ColmapFormatError(
                f"image {self.image_id}: quaternion {self.qvec.tolist()} is not a rotation"
            )

    @property
    def R(self) -> np.ndarray:
        """(3, 3) cam_from_world rotation."""
        return rotmat_from_qvec(self.qvec)

    @property
    def center(self) -> np.ndarray:
        """(3,) camera centre in world coordinates, ``-R^T t``."""
        return -self.R.T @ self.tvec


def rotmat_from_qvec(qvec: np.ndarray) -> np.ndarray:
    """Rotation matrix of a Hamilton quaternion (w, x, y, z); normalized first. Returns (3, 3) float64."""
    w, x, y, z = np.asarray(qvec, dtype=np.float64).reshape(4) / max(float(np.linalg.norm(qvec)), 1e-300)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def qvec_from_rotmat(R: np.ndarray) -> np.ndarray:
    """Hamilton unit quaternion (w, x, y, z) of a (3, 3) rotation, with w >= 0. Returns (4,) float64."""
    R = np.asarray(R, dtype=np.float64).reshape(3, 3)
    # Largest-eigenvector method (Bar-Itzhack 2000): stable for every rotation.
    K = (
        np.array(
            [
                [R[0, 0] - R[1, 1] - R[2, 2], 0.0, 0.0, 0.0],
                [R[1, 0] + R[0, 1], R[1, 1] - R[0, 0] - R[2, 2], 0.0, 0.0],
                [R[2, 0] + R[0, 2], R[2, 1] + R[1, 2], R[2, 2] - R[0, 0] - R[1, 1], 0.0],
                [R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], R[0, 0] + R[1, 1] + R[2, 2]],
            ]
        )
        / 3.0
    )
    vals, vecs = np.linalg.eigh(K)
    x, y, z, w = vecs[:, np.argmax(vals)]
    q = np.array([w, x, y, z])
    return -q if q[0] < 0 else q


def image_from_camera(image_id: int, camera_id: int, name: str, camera: Camera) -> ColmapImage:
    """The ``images.txt`` record of a pmvir Camera's pose (no keypoints)."""
    return ColmapImage(image_id, qvec_from_rotmat(camera.R), camera.t, camera_id, name)


def pinhole_from_camera(camera_id: int, camera: Camera) -> ColmapCamera:
    """The ``cameras.txt`` PINHOLE record of a pmvir Camera (skew must be zero)."""
    K = camera.K
    if abs(K[0, 1]) > 1e-12:
        raise ColmapFormatError(f"camera {camera_id}: PINHOLE cannot hold a skewed K (K[0, 1] = {K[0, 1]})")
    return ColmapCamera(
        camera_id, "PINHOLE", camera.width, camera.height, (K[0, 0], K[1, 1], K[0, 2], K[1, 2])
    )


def camera_from_colmap(camera: ColmapCamera, image: ColmapImage) -> Camera:
    """A pmvir Camera from a pinhole ``cameras.txt`` record and an ``images.txt`` record."""
    return Camera(K=camera.K(), R=image.R, t=image.tvec, width=camera.width, height=camera.height)


def _data_lines(path: Path) -> list[tuple[int, str]]:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError as exc:
        raise ColmapFormatError(f"{path}: no such file") from exc
    except (OSError, UnicodeDecodeError) as exc:
        raise ColmapFormatError(f"{path}: cannot read ({exc})") from exc
    return [(i + 1, line.strip()) for i, line in enumerate(text.splitlines())]


def read_cameras_text(path: str | Path) -> dict[int, ColmapCamera]:
    """Read ``cameras.txt``; returns cameras by CAMERA_ID. Raises ColmapFormatError naming file and line."""
    path = Path(path)
    cameras: dict[int, ColmapCamera] = {}
    for lineno, line in _data_lines(path):
        if not line or line.startswith("#"):
            continue
        tok = line.split()
        try:
            if len(tok) < 4:
                raise ColmapFormatError("expected CAMERA_ID MODEL WIDTH HEIGHT PARAMS[]")
            cam = ColmapCamera(
                int(tok[0]), tok[1], int(tok[2]), int(tok[3]), tuple(float(t) for t in tok[4:])
            )
        except (ValueError, ColmapFormatError) as exc:
            raise ColmapFormatError(f"{path}:{lineno}: {exc}") from exc
        if cam.camera_id in cameras:
            raise ColmapFormatError(f"{path}:{lineno}: duplicate CAMERA_ID {cam.camera_id}")
        cameras[cam.camera_id] = cam
    return cameras


def read_images_text(path: str | Path) -> dict[int, ColmapImage]:
    """Read ``images.txt``; returns images by IMAGE_ID. Raises ColmapFormatError naming file and line.

    As in COLMAP, the line right after an image line is its POINTS2D line, even when empty.
    """
    path = Path(path)
    lines = _data_lines(path)
    images: dict[int, ColmapImage] = {}
    i = 0
    while i < len(lines):
        lineno, line = lines[i]
        i += 1
        if not line or line.startswith("#"):
            continue
        pts_line = lines[i][1] if i < len(lines) else ""
        i += 1
        tok = line.split()
        try:
            if len(tok) != 10:
                raise ColmapFormatError(
                    f"expected IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME (10 fields), got {len(tok)}"
                )
            pts = pts_line.split()
            if len(pts) % 3:
                raise ColmapFormatError(f"POINTS2D line has {len(pts)} fields, not a multiple of 3 (X Y POINT3D_ID)")
            arr = np.array(pts, dtype=np.float64).reshape(-1, 3)
            ids = np.array([int(p) for p in pts[2::3]], dtype=np.int64)
            img = ColmapImage(
                int(tok[0]),
                np.array([float(t) for t in tok[1:5]]),
                np.array([float(t) for t in tok[5:8]]),
                int(tok[8]),
                tok[9],
                arr[:, :2],
                ids,
            )
        except (ValueError, ColmapFormatError) as exc:
            raise ColmapFormatError(f"{path}:{lineno}: {exc}") from exc
        if img.image_id in images:
            raise ColmapFormatError(f"{path}:{lineno}: duplicate IMAGE_ID {img.image_id}")
        images[img.image_id] = img
    return images


def _num(x: float) -> str:
    """17 significant digits, as COLMAP writes (``stream.precision(17)``)."""
    x = float(x)
    if not math.isfinite(x):
        raise ColmapFormatError(f"cannot write non-finite value {x}")
    return f"{x:.17g}"


def _write_atomic(path: Path, text: str) -> None:
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text, encoding="utf-8")
    os.replace(tmp, path)


def write_cameras_text(path: str | Path, cameras: dict[int, ColmapCamera] | list[ColmapCamera]) -> None:
    """Write ``cameras.txt`` (sorted by CAMERA_ID), atomically."""
    cams = sorted(cameras.values() if isinstance(cameras, dict) else cameras, key=lambda c: c.camera_id)
    out = [
        "# Camera list with one line of data per camera:",
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
        f"# Number of cameras: {len(cams)}",
    ]
    for c in cams:
        out.append(
            " ".join([str(c.camera_id), c.model, str(c.width), str(c.height), *(_num(p) for p in c.params)])
        )
    _write_atomic(Path(path), "\n".join(out) + "\n")


def write_images_text(path: str | Path, images: dict[int, ColmapImage] | list[ColmapImage]) -> None:
    """Write ``images.txt`` (sorted by IMAGE_ID, two lines per image), atomically."""
    imgs = sorted(images.values() if isinstance(images, dict) else images, key=lambda m: m.image_id)
    n_obs = sum(int((m.point3d_ids >= 0).sum()) for m in imgs)
    mean_obs = n_obs / len(imgs) if imgs else 0.0
    out = [
        "# Image list with two lines of data per image:",
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
        "#   POINTS2D[] as (X, Y, POINT3D_ID)",
        f"# Number of images: {len(imgs)}, mean observations per image: {mean_obs:g}",
    ]
    for m in imgs:
        q = m.qvec / np.linalg.norm(m.qvec)
        out.append(
            " ".join(
                [str(m.image_id), *(_num(v) for v in q), *(_num(v) for v in m.tvec), str(m.camera_id), m.name]
            )
        )
        out.append(
            " ".join(
                f"{_num(x)} {_num(y)} {int(pid)}"
                for (x, y), pid in zip(m.points2d, m.point3d_ids, strict=True)
            )
        )
    _write_atomic(Path(path), "\n".join(out) + "\n")


def write_colmap_text_model(
    directory: str | Path,
    cameras: dict[int, ColmapCamera] | list[ColmapCamera],
    images: dict[int, ColmapImage] | list[ColmapImage],
) -> None:
    """Write ``cameras.txt``, ``images.txt`` and an empty ``points3D.txt`` so COLMAP can import the folder.

    Every image's CAMERA_ID must name one of ``cameras``.
    """
    directory = Path(directory)
    cam_ids = {c.camera_id for c in (cameras.values() if isinstance(cameras, dict) else cameras)}
    for m in images.values() if isinstance(images, dict) else images:
        if m.camera_id not in cam_ids:
            raise ColmapFormatError(
                f"image {m.image_id} ({m.name}) refers to unknown CAMERA_ID {m.camera_id}"
            )
    directory.mkdir(parents=True, exist_ok=True)
    write_cameras_text(directory / "cameras.txt", cameras)
    write_images_text(directory / "images.txt", images)
    _write_atomic(
        directory / "points3D.txt",
        "# 3D point list with one line of data per point:\n"
        "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)\n"
        "# Number of points: 0, mean track length: 0\n",
    )


def read_colmap_text_model(directory: str | Path) -> tuple[dict[int, ColmapCamera], dict[int, ColmapImage]]:
    """Read ``cameras.txt`` and ``images.txt`` from a folder; checks every CAMERA_ID is defined."""
    directory = Path(directory)
    cameras = read_cameras_text(directory / "cameras.txt")
    images = read_images_text(directory / "images.txt")
    for m in images.values():
        if m.camera_id not in cameras:
            raise ColmapFormatError(
                f"{directory / 'images.txt'}: image {m.name} refers to unknown CAMERA_ID {m.camera_id}"
            )
    return cameras, images
