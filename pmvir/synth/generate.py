"""``synthesize``: write a synthetic capture with ground truth (shared/spec/capture-format.md).

Output layout::

    capture.json            IMX250MYR 12-bit, shared intrinsics, a cam_from_world per frame
    frames/000.png ...      raw mosaics (16-bit PNG containers, values 0..4095)
    masks/000.png ...       8-bit, 255 = object (pixel-centre ray hits the mesh)
                            (``rig="turntable"``: the object turns before a still, textured backdrop)
                            (``masks=False``: no masks/; the same masks go to gt/masks/)
    gt/mesh.ply             the normalized mesh with its true per-vertex albedo
    gt/illumination.json    per-frame true lighting (SH9 shading; for envmap its projection)
    gt/views/000.npz ...    per-view ground truth (pmvir extension; see below)
    gt/synth.json           how the capture was made (options, gain, sensor, per-view lights)

``gt/views/<stem>.npz`` holds ``depth`` (H, W) float32 camera-frame z (0 on the
background), ``normal_cam`` (H, W, 3) float32 unit shading normals in camera
axes, ``aop`` and ``dop`` (H, W) float32 and ``i_int`` (H, W, 3) float32 (the
noise-free rendered values in decoded units, before the mosaic, noise,
quantization and clipping), ``mask`` (H, W) bool; with ``save_stokes`` also
``stokes`` (H, W, 3, 3) float32: per colour (R, G, B) the noise-free linear
Stokes vector (s0, s1, s2) in full-scale units (gain times radiance), i.e. the
sensor's input: its polarizer intensities are ``(s0 + s1 cos 2t + s2 sin 2t) / 2``.

Units: the decoded ``I_int`` of a Lambertian pixel is ``K * S(N) * rgb_scale``
exactly (before noise) with the ``sh`` and ``rgb_scale`` of
``gt/illumination.json``; for plastic that is the diffuse part of I_int (the
specular reflection adds to it); conductor pixels have no diffuse part.
``scene`` "table" and "turntable" (:mod:`pmvir.synth.table`) render the object
standing on a textured support; the masks, ``gt/mesh.ply`` and the depth and
normals of ``gt/views`` are the object's alone, ``i_int``/``aop``/``dop`` and
``stokes`` are of the whole image. The built-in renderer shows the lighting
environment where a pixel-centre ray of a table scene misses the table (Mitsuba
always shows it).

``capture.json`` is written last: a capture folder without it is incomplete.
"""

from __future__ import annotations

import importlib.util
import io
import json
import shutil
import time
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pmvir.camera import Camera
from pmvir.capture import (
    CamFromWorld,
    CaptureManifest,
    FrameEntry,
    Intrinsics,
    SensorSpec,
    write_capture_manifest,
)
from pmvir.errors import ConfigError
from pmvir.io.frames import write_frame
from pmvir.io.illumination import illumination_from_arrays, write_illumination
from pmvir.io.ply import Mesh, write_mesh_ply
from pmvir.synth.builtin_renderer import render_geometry, render_view
from pmvir.synth.lighting import EnvLight, ViewLight, env_lights, sh_lights
from pmvir.synth.options import SynthOptions, synth_options
from pmvir.synth.raycast import MeshScene, pixel_directions
from pmvir.synth.rig import rig_cameras, turntable_cameras
from pmvir.synth.sensor import SensorModel, capture_mosaic
from pmvir.synth.shapes import builtin_shape, load_mesh
from pmvir.synth.table import combine, handheld_cameras, support_mesh
from pmvir.synth.texture import procedural_albedo, uniform_albedo

#: Auto exposure, as a careful operator sets a polarization camera: the brightest polarizer sample
#: (colour channel and angle) of the foreground pixel at this percentile lands at this fraction of full
#: scale, so highlights clip in at most about 1 % of the object instead of saturating whole regions.
AUTO_EXPOSURE_PERCENTILE = 99.0
AUTO_EXPOSURE_TARGET = 0.85
_OUTPUTS = ("capture.json", "frames", "masks", "gt")


@dataclass(frozen=True)
class ViewDone:
    """Progress report after each view.

    Attributes:
        index: the view just written (0-based).
        total: number of views.
        render_s: seconds spent rendering its Stokes image (ray casting and shading).
        total_s: seconds for the whole view (rendering, sensor, writing files).
    """

    index: int
    total: int
    render_s: float
    total_s: float


def _prepare_output(out: Path, overwrite: bool, *, masks: bool = True) -> None:
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: output exists and is not a folder")
    if out.is_dir() and any(out.iterdir()):
        if not overwrite:
            raise ConfigError(
                f"{out}: output folder is not empty (use overwrite / --force to replace a capture)"
            )
        for name in _OUTPUTS:
            p = out / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    for sub in ("frames", "masks" if masks else "gt/masks", "gt/views"):
        (out / sub).mkdir(parents=True, exist_ok=True)


def write_npz(path: Path, arrays: dict[str, np.ndarray], *, compresslevel: int = 1) -> None:
    """Write an ``.npz`` readable by ``np.load``, byte-for-byte reproducible (fixed zip timestamps)."""
    tmp = path.with_name(path.name + ".tmp")
    with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED, compresslevel=compresslevel) as zf:
        for name, arr in arrays.items():
            buf = io.BytesIO()
            np.lib.format.write_array(buf, np.ascontiguousarray(arr), allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, buf.getvalue(), compresslevel=compresslevel)
    tmp.replace(path)


def _write_png8(path: Path, image: np.ndarray) -> None:
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise RuntimeError(f"{path}: PNG encoding failed")
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(buf.tobytes())
    tmp.replace(path)


def polarization_truth(stokes: np.ndarray, gain: float) -> dict[str, np.ndarray]:
    """Noise-free decoded quantities of a Stokes image (spec section 2).

    Args:
        stokes: (H, W, 3, 3) Stokes image, radiance units.
        gain: the sensor gain (full-scale units per radiance unit).

    Returns:
        ``i_int`` (H, W, 3) = gain * s0 / 2, ``aop`` (H, W) in [0, pi) and ``dop`` (H, W) in [0, 1]
        from the colour-averaged Stokes vector (0 where s0 is 0), all float32.
    """
    s = stokes.astype(np.float64)
    mean = s.mean(axis=2)
    s0 = mean[..., 0]
    aop = np.mod(0.5 * np.arctan2(mean[..., 2], mean[..., 1]), np.pi)
    dop = np.clip(np.hypot(mean[..., 1], mean[..., 2]) / np.maximum(s0, 1e-12), 0.0, 1.0)
    dop = np.where(s0 > 0, dop, 0.0)
    aop = np.where(s0 > 0, aop, 0.0)
    return {
        "i_int": (gain * s[..., 0] / 2.0).astype(np.float32),
        "aop": aop.astype(np.float32),
        "dop": dop.astype(np.float32),
    }


def _auto_gain(stokes: np.ndarray, mask: np.ndarray) -> float:
    """Gain putting the AUTO_EXPOSURE_PERCENTILE-th brightest polarizer sample at AUTO_EXPOSURE_TARGET."""
    if not mask.any():
        return 1.0
    s = stokes[mask]  # (n, 3 colours, s0 s1 s2)
    brightest = (s[..., 0] + np.hypot(s[..., 1], s[..., 2])) / 2.0  # I at the polarizer angle = AoP
    level = float(np.percentile(brightest.max(axis=1), AUTO_EXPOSURE_PERCENTILE))
    return AUTO_EXPOSURE_TARGET / level if level > 1e-9 else 1.0


def backdrop_texture(width: int, height: int, *, seed: int) -> np.ndarray:
    """A turntable's backdrop as the still camera sees it: (H, W, 3) float32 linear colour in [0.1, 1].

    Value noise at four scales with hue variation: plenty of SIFT features, the same in every frame.
    """
    rng = np.random.default_rng([seed, 23])
    out = np.zeros((height, width, 3), np.float32)
    for cells, weight in ((6, 0.4), (16, 0.3), (40, 0.2), (100, 0.1)):
        coarse = rng.uniform(0.0, 1.0, (max(2, cells * height // width), cells, 3)).astype(np.float32)
        out += weight * cv2.resize(coarse, (width, height), interpolation=cv2.INTER_CUBIC)
    return np.clip(0.1 + 0.9 * out, 0.1, 1.0)


def _with_backdrop(stokes: np.ndarray, mask: np.ndarray, backdrop: np.ndarray, *, level: float) -> np.ndarray:
    """Stokes (H, W, 3 colours, 3) with an unpolarized backdrop of radiance ``level * backdrop`` off the object."""
    out = stokes.copy()
    out[~mask, :, 0] = level * 2.0 * backdrop[~mask]
    out[~mask, :, 1:] = 0.0
    return out


def _mitsuba_view(mesh: Mesh, camera: Camera, light: ViewLight, opts: SynthOptions, index: int) -> np.ndarray:
    """Stokes image from the optional Mitsuba renderer (imported only here)."""
    from pmvir.synth import mitsuba_renderer  # imports Mitsuba itself only when rendering

    if mesh.albedo is None:
        raise ConfigError("the Mitsuba renderer needs a mesh with per-vertex albedo")

    kwargs: dict[str, Any]
    if isinstance(light, EnvLight):
        dirs = mitsuba_renderer.envmap_directions(128, 256)  # Mitsuba's lat-long convention (y up)
        kwargs = {"envmap": light.radiance(dirs.reshape(-1, 3)).reshape(128, 256, 3).astype(np.float32)}
    else:
        kwargs = {"sh": light.sh, "rgb_scale": light.colour}
    result = mitsuba_renderer.render_view_stokes(
        mesh.vertices,
        mesh.faces,
        mesh.albedo,
        camera,
        material=opts.material,
        ior=opts.ior,
        extinction=opts.extinction if opts.material == "conductor" else 0.0,
        roughness=opts.roughness,
        specular=opts.specular,
        normals=mesh.normals,
        spp=opts.spp,
        max_depth=opts.max_depth,
        seed=opts.seed * 100_003 + index,
        **kwargs,
    )
    return result.stokes


def _cameras(opts: SynthOptions, radius: float) -> list[Camera]:
    """The views of the options' scene and rig."""
    size = (opts.views, opts.width, opts.height)
    if opts.scene == "table":
        return handheld_cameras(*size, object_radius=radius, focal_factor=opts.focal_factor, seed=opts.seed)
    if opts.scene == "turntable":
        return turntable_cameras(*size, object_radius=radius, focal_factor=opts.focal_factor)
    return rig_cameras(opts.rig, *size, object_radius=radius, focal_factor=opts.focal_factor)


def _environment_behind(stokes: np.ndarray, hit: np.ndarray, camera: Camera, light: ViewLight) -> np.ndarray:
    """Stokes (H, W, 3, 3) with the unpolarized lighting environment where the pixel-centre ray misses."""
    rows, cols = np.nonzero(~hit)
    if not len(rows):
        return stokes
    d_world, _ = pixel_directions(camera, cols + 0.5, rows + 0.5)
    out = stokes.copy()
    out[rows, cols, :, 0] = light.radiance(d_world.astype(np.float64))
    out[rows, cols, :, 1:] = 0.0
    return out


def _lights(opts: SynthOptions) -> tuple[list[ViewLight], list[dict[str, Any]]]:
    if opts.lighting == "sh":
        lights = sh_lights(opts.views, seed=opts.seed)
        return list(lights), [{"sh": lt.sh.tolist(), "colour": lt.colour.tolist()} for lt in lights]
    env = env_lights(opts.views, seed=opts.seed)
    info = [
        {
            "rotation_deg": float(np.degrees(lt.rotation)),
            "strength": lt.strength,
            "colour": lt.colour.tolist(),
            "sh_projection": lt.sh.tolist(),
        }
        for lt in env
    ]
    return list(env), info


def synthesize(
    out: str | Path,
    *,
    mesh: str | Path | None = None,
    shape: str | None = None,
    overwrite: bool = False,
    progress: Callable[[ViewDone], None] | None = None,
    **options: Any,
) -> Path:
    """Render a synthetic capture of a mesh file or a built-in shape (module docstring: the layout).

    Args:
        out: capture folder to create (must be absent or empty unless ``overwrite``).
        mesh: a PLY/OBJ mesh (normalized to bounding-box diagonal 1); or
        shape: a built-in shape name (:data:`pmvir.synth.shapes.SHAPES`).
        overwrite: replace the capture files of a non-empty ``out``.
        progress: called with a :class:`ViewDone` after each view.
        **options: fields of :class:`pmvir.synth.options.SynthOptions` (views, size, material,
            lighting, noise, seed, renderer, ...).

    Returns:
        The capture folder.

    Raises:
        ConfigError: bad options, both or neither of mesh/shape, unknown shape, output not empty.
        MeshError: the mesh file is missing or unreadable.
    """
    opts = synth_options(**options)
    if (mesh is None) == (shape is None):
        raise ConfigError("give exactly one of mesh (a PLY/OBJ file) and shape (a built-in name)")
    if opts.renderer == "mitsuba" and importlib.util.find_spec("mitsuba") is None:
        raise ConfigError(
            "--renderer mitsuba needs Mitsuba 3, the optional extra: pip install 'pmvir[mitsuba]'"
        )
    if shape is not None:
        geometry = builtin_shape(shape)
    else:
        assert mesh is not None  # exactly one of them is given (checked above)
        geometry = load_mesh(mesh, up=opts.mesh_up)
    out = Path(out)
    if opts.texture == "procedural":
        albedo = procedural_albedo(geometry.vertices, seed=opts.seed)
    else:
        albedo = uniform_albedo(len(geometry.vertices))
    truth = Mesh(geometry.vertices, geometry.faces, albedo=albedo, normals=geometry.normals)
    # ``rendered``: what the cameras see (the object, or the object on its support); ``truth``: the object.
    rendered = truth if opts.scene == "object" else combine(truth, support_mesh(truth.vertices, opts.scene, seed=opts.seed))
    scene = MeshScene.from_mesh(rendered)
    object_scene = scene if rendered is truth else MeshScene.from_mesh(truth)
    radius = float(np.linalg.norm(truth.vertices[np.unique(truth.faces)], axis=1).max())
    cameras = _cameras(opts, radius)
    turntable = opts.rig == "turntable" or opts.scene == "turntable"
    backdrop = backdrop_texture(opts.width, opts.height, seed=opts.seed) if turntable else None
    lights, light_info = _lights(opts)
    sensor = SensorModel(black_level=opts.black_level, full_well=opts.full_well, read_noise=opts.noise)
    _prepare_output(out, overwrite, masks=opts.masks)
    mask_dir = "masks" if opts.masks else "gt/masks"

    gain: float | None = opts.exposure  # None: chosen on the first view
    entries, names = [], []
    for i, (cam, light) in enumerate(zip(cameras, lights, strict=True)):
        t0 = time.perf_counter()
        if opts.renderer == "builtin":
            view = render_view(
                scene,
                cam,
                light,
                material=opts.material,
                ior=opts.ior,
                extinction=opts.extinction,
                specular=opts.specular,
                supersample=opts.supersample,
                aop_frame=opts.aop_frame,
            )
            stokes, seen = view.stokes, view.geometry
            if opts.scene == "table":
                stokes = _environment_behind(stokes, seen.mask, cam, light)
        else:
            seen = render_geometry(scene, cam)[0]
            stokes = _mitsuba_view(rendered, cam, light, opts, i)
        geom = seen if rendered is truth else render_geometry(object_scene, cam)[0]
        t_render = time.perf_counter() - t0
        if gain is None:
            gain = _auto_gain(stokes, geom.mask)
        if backdrop is not None:
            stokes = _with_backdrop(stokes, seen.mask, backdrop, level=0.6 / (2.0 * gain))
        stem = f"{i:03d}"
        samples = capture_mosaic(
            stokes, gain=gain, sensor=sensor, rng=np.random.default_rng([opts.seed, 17, i])
        )
        write_frame(out / "frames" / f"{stem}.png", samples, bit_depth=sensor.bit_depth)
        _write_png8(out / mask_dir / f"{stem}.png", geom.mask.astype(np.uint8) * 255)
        if opts.gt_views:
            write_npz(
                out / "gt" / "views" / f"{stem}.npz",
                {
                    "depth": geom.depth,
                    "normal_cam": geom.normal_cam,
                    **polarization_truth(stokes, gain),
                    "mask": geom.mask,
                    **({"stokes": (stokes * gain).astype(np.float32)} if opts.save_stokes else {}),
                },
            )
        entries.append(
            FrameEntry(
                file=f"frames/{stem}.png",
                mask=f"masks/{stem}.png" if opts.masks else None,
                cam_from_world=CamFromWorld.from_arrays(cam.R, cam.t),
            )
        )
        names.append(f"frames/{stem}.png")
        if progress is not None:
            progress(ViewDone(index=i, total=opts.views, render_s=t_render, total_s=time.perf_counter() - t0))
    gain = float(gain) if gain is not None else 1.0  # views >= 1, so the first view has set it

    write_mesh_ply(out / "gt" / "mesh.ply", truth)
    sh = np.stack([lt.sh for lt in lights])
    rgb_scale = np.stack([lt.colour for lt in lights]) * gain / 2.0
    write_illumination(out / "gt" / "illumination.json", illumination_from_arrays(names, sh, rgb_scale))
    if not opts.gt_views:
        (out / "gt" / "views").rmdir()
    info = {
        "format": "pmvir-synth/1",
        "source": {"shape": shape} if shape is not None else {"mesh": str(mesh)},
        "options": opts.model_dump(mode="json"),
        "gain": gain,
        "sensor": {
            "layout": "IMX250MYR",
            "bit_depth": sensor.bit_depth,
            "black_level": sensor.black_level,
            "white_level": sensor.white_level,
            "full_well": sensor.full_well,
            "read_noise": sensor.read_noise,
        },
        "lights": light_info,
    }
    (out / "gt" / "synth.json").write_text(json.dumps(info, indent=1))
    if isinstance(lights[0], EnvLight):
        write_npz(out / "gt" / "envmap.npz", {"radiance": lights[0].table.env.astype(np.float32)})
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
    write_capture_manifest(out, manifest)
    return out
