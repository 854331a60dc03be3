"""Synthetic captures for the geometric stage's tests, made once per test session.

* ``blob_capture``: pmvir synth's textured ``blob`` (plastic), 36 views of 432 x 360 pixels, with
  ground truth (mesh, per-view true depth); ``blob_views`` its decoded frames and ``blob_geometry``
  the geometric stage run on it with its known poses (shared by the sfm, mvs and stage tests).
  432 x 360 is the smallest size at which SfM registered all 36 views with centre errors well
  inside the test's tolerance in our measurements (384 x 320: up to 2.5 % of the object's size).
* ``textureless_capture``: a Lambertian sphere with one constant albedo, 12 views of 256 x 216:
  nothing to match but smooth shading and noise.
* ``textureless_views``, ``unrelated_views``: those two decoded; ``textureless_set``, ``unrelated_set``
  (and ``blob_set``): their I_int images, masks, true cameras, names and true-surface points.
* ``unrelated_capture``: the blob's geometry, 8 views of 256 x 216, but every frame painted with a
  different random albedo texture, so no two frames share image content (they "do not overlap").

The last two are written with synth's own renderer and sensor model (only the albedo differs
from ``synthesize``), each with masks, shared intrinsics and a pose per frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from pmvir.camera import Camera
from pmvir.capture import (
    CamFromWorld,
    CaptureManifest,
    FrameEntry,
    Intrinsics,
    SensorSpec,
    open_capture,
    write_capture_manifest,
)
from pmvir.config import GeometryOptions
from pmvir.decode import decode_frame
from pmvir.evaluate import sample_surface
from pmvir.geometry.stage import GeometryResult, run_geometry
from pmvir.io.frames import write_frame
from pmvir.io.ply import Mesh, read_mesh, write_mesh_ply
from pmvir.polarization.stokes import PolarizationImages
from pmvir.progress import Progress
from pmvir.synth.builtin_renderer import render_view
from pmvir.synth.generate import synthesize
from pmvir.synth.lighting import sh_lights
from pmvir.synth.raycast import MeshScene
from pmvir.synth.rig import ring_cameras
from pmvir.synth.sensor import SensorModel, capture_mosaic
from pmvir.synth.shapes import builtin_shape
from pmvir.synth.texture import procedural_albedo

SIZE = (256, 216)
BLOB_SIZE = (432, 360)
BLOB_VIEWS = 36


def make_capture(
    out: Path,
    mesh: Mesh,
    albedo_of_view: Callable[[int], np.ndarray],
    *,
    views: int,
    size: tuple[int, int] = SIZE,
    material: str = "plastic",
    seed: int = 0,
) -> Path:
    """A capture folder as ``synthesize`` writes it (frames, masks, gt/mesh.ply, manifest), per-view albedo"""
    (out / "frames").mkdir(parents=True)
    (out / "masks").mkdir()
    radius = float(np.linalg.norm(mesh.vertices, axis=1).max())
    cameras = ring_cameras(views, size[0], size[1], object_radius=radius)
    lights = sh_lights(views, seed=seed)
    sensor = SensorModel()
    entries, gain = [], None
    for i, (cam, light) in enumerate(zip(cameras, lights, strict=True)):
        scene = MeshScene.from_mesh(
            Mesh(mesh.vertices, mesh.faces, albedo=albedo_of_view(i), normals=mesh.normals)
        )
        view = render_view(scene, cam, light, material=material)
        if gain is None:
            level = float(np.median(view.stokes[view.geometry.mask][:, :, 0].max(axis=1) / 2.0))
            gain = 0.45 / level
        samples = capture_mosaic(view.stokes, gain=gain, sensor=sensor, rng=np.random.default_rng([seed, i]))
        write_frame(out / "frames" / f"{i:03d}.png", samples, bit_depth=sensor.bit_depth)
        write_frame(out / "masks" / f"{i:03d}.png", view.geometry.mask.astype(np.uint8) * 255, bit_depth=8)
        entries.append(
            FrameEntry(
                file=f"frames/{i:03d}.png",
                mask=f"masks/{i:03d}.png",
                cam_from_world=CamFromWorld.from_arrays(cam.R, cam.t),
            )
        )
    manifest = CaptureManifest(
        sensor=SensorSpec(
            layout="IMX250MYR",
            bit_depth=sensor.bit_depth,
            black_level=sensor.black_level,
            white_level=sensor.white_level,
            aop_reference="ccw",
        ),
        intrinsics=Intrinsics.from_camera(cameras[0]),
        frames=entries,
    )
    (out / "gt").mkdir()
    write_mesh_ply(out / "gt" / "mesh.ply", Mesh(mesh.vertices, mesh.faces, albedo=albedo_of_view(0)))
    write_capture_manifest(out, manifest)
    return out


def decode_all(path: Path) -> list[PolarizationImages]:
    """Every frame of a capture decoded (default options)."""
    with open_capture(path) as cap:
        out = []
        for i in range(len(cap)):
            raw = cap.read_raw(i)
            out.append(decode_frame(raw.mosaic, cap.layout, saturated=raw.saturated, mask=cap.read_mask(i)))
        return out


@pytest.fixture(scope="session")
def decode_capture() -> Callable[[Path], list[PolarizationImages]]:
    """:func:`decode_all`, for tests that make their own capture."""
    return decode_all


@pytest.fixture(scope="session")
def geometry_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("geometry-data")


@pytest.fixture(scope="session")
def blob_capture(geometry_data: Path) -> Path:
    return synthesize(geometry_data / "blob", shape="blob", views=BLOB_VIEWS, size=BLOB_SIZE, seed=3)


@pytest.fixture(scope="session")
def blob_views(blob_capture: Path) -> list[PolarizationImages]:
    return decode_all(blob_capture)


#: Options of the stage run on the blob: faster than the defaults where the tests do not need them
#: (no affine-adapted SIFT: known poses need few features; 64 planes instead of 96).
BLOB_OPTIONS = {"sfm": {"sift_affine_shape": False}, "mvs": {"planes": 64}}


@pytest.fixture(scope="session")
def blob_progress() -> list[tuple[float, str]]:
    """The progress calls of the ``blob_geometry`` run."""
    return []


@pytest.fixture(scope="session")
def blob_geometry(
    blob_capture: Path, blob_views: list[PolarizationImages], geometry_data: Path, blob_progress: list
) -> GeometryResult:
    with open_capture(blob_capture) as cap:
        return run_geometry(
            cap,
            blob_views,
            options=GeometryOptions(**BLOB_OPTIONS),
            workdir=geometry_data / "blob-work",
            progress=Progress(lambda stage, fraction, message: blob_progress.append((fraction, message))),
        )


@pytest.fixture(scope="session")
def textureless_capture(geometry_data: Path) -> Path:
    sphere = builtin_shape("sphere")
    flat = np.full((len(sphere.vertices), 3), 0.6, np.float32)
    return make_capture(geometry_data / "textureless", sphere, lambda i: flat, views=12, material="lambert")


@pytest.fixture(scope="session")
def unrelated_capture(geometry_data: Path) -> Path:
    blob = builtin_shape("blob")
    return make_capture(
        geometry_data / "unrelated", blob, lambda i: procedural_albedo(blob.vertices, seed=100 + i), views=8
    )


@dataclass(frozen=True)
class ViewSet:
    """Decoded I_int images, masks, true cameras, names and true-surface points (as sparse points)."""

    images: list[np.ndarray]
    masks: list[np.ndarray | None]
    cameras: list[Camera]
    names: list[str]
    points: np.ndarray


def view_set(path: Path, views: list[PolarizationImages], n_points: int = 500) -> ViewSet:
    with open_capture(path) as cap:
        masks = [cap.read_mask(i) for i in range(len(cap))]
        cams = [f.camera for f in cap.frames]
        names = [f.name for f in cap.frames]
    gt = read_mesh(path / "gt" / "mesh.ply")
    pts, _, _ = sample_surface(gt.vertices, gt.faces, n_points, seed=0)
    return ViewSet([v.i_int for v in views], masks, cams, names, pts)


@pytest.fixture(scope="session")
def textureless_views(textureless_capture: Path) -> list[PolarizationImages]:
    return decode_all(textureless_capture)


@pytest.fixture(scope="session")
def unrelated_views(unrelated_capture: Path) -> list[PolarizationImages]:
    return decode_all(unrelated_capture)


@pytest.fixture(scope="session")
def textureless_set(textureless_capture: Path, textureless_views: list[PolarizationImages]) -> ViewSet:
    return view_set(textureless_capture, textureless_views)


@pytest.fixture(scope="session")
def blob_set(blob_capture: Path, blob_views: list[PolarizationImages]) -> ViewSet:
    return view_set(blob_capture, blob_views)


@pytest.fixture(scope="session")
def unrelated_set(unrelated_capture: Path, unrelated_views: list[PolarizationImages]) -> ViewSet:
    return view_set(unrelated_capture, unrelated_views)
