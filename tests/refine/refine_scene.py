"""Synthetic scenes with a known answer for the refinement tests.

A unit sphere with ten Gaussian bumps (the true surface, rendered with the
refinement's own image model), seen by a ring of cameras, and an initial mesh
that has the same shape with the bumps at a fraction of their height (as an
over-smoothed MVS surface would).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmvir.camera import Camera, look_at
from pmvir.refine.forward import render_decoded
from pmvir.synth.shapes import geodesic_sphere

_CENTRES = np.array(
    [
        [0.3, 0.5, 0.8],
        [-0.6, 0.2, 0.7],
        [0.8, -0.3, 0.1],
        [-0.2, -0.9, 0.3],
        [0.1, 0.8, -0.4],
        [-0.7, -0.4, -0.5],
        [0.5, 0.1, -0.8],
        [0.0, -0.3, 0.95],
        [0.9, 0.4, -0.2],
        [-0.9, 0.3, -0.1],
    ]
)
_CENTRES /= np.linalg.norm(_CENTRES, axis=1, keepdims=True)
_SIGNS = np.array([1, -1, 1, 1, -1, 1, -1, 1, 1, -1.0])
SH = np.array([0.7, 0.15, 0.3, 0.1, 0.05, 0.05, 0.1, 0.05, 0.03])
RGB_SCALE = np.array([1.0, 0.9, 0.8])
SPECULAR_LIGHT = np.array([[0.3, 0.2, 1.0]])


def bumpy_sphere(frequency: int, factor: float) -> tuple[np.ndarray, np.ndarray]:
    """Geodesic sphere with the bumps scaled by ``factor``: (V, 3) vertices, (F, 3) faces."""
    d, f = geodesic_sphere(frequency)
    ang = np.arccos(np.clip(d @ _CENTRES.T, -1.0, 1.0))
    r = 1.0 + factor * 0.08 * (_SIGNS * np.exp(-((ang / 0.35) ** 2))).sum(1)
    return d * r[:, None], f


def albedo_of(vertices: np.ndarray) -> np.ndarray:
    """Two-colour albedo: orange, with a blue cap around (0, 0.6, 0.8)."""
    d = vertices / np.linalg.norm(vertices, axis=1, keepdims=True)
    a = np.tile([0.6, 0.45, 0.3], (len(d), 1))
    a[d @ np.array([0.0, 0.6, 0.8]) > 0.85] = [0.25, 0.45, 0.6]
    return a


def ring_cameras(
    n_views: int, size: int, *, distance: float = 4.0, focal: float | None = None
) -> list[Camera]:
    """Cameras on a ring around the origin, alternately 20 degrees above and below the equator."""
    f = focal if focal is not None else 1.35 * size
    cams = []
    for i in range(n_views):
        az = 2 * np.pi * i / n_views
        el = 0.35 if i % 2 == 0 else -0.35
        c = distance * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        R, t = look_at(c, np.zeros(3))
        cams.append(Camera.from_intrinsics(f, f, size / 2, size / 2, size, size, R, t))
    return cams


@dataclass
class Scene:
    true_vertices: np.ndarray
    true_faces: np.ndarray
    vertices: np.ndarray  # initial
    faces: np.ndarray
    cameras: list[Camera]
    frames: list[dict[str, np.ndarray]]
    sh: np.ndarray
    rgb_scale: np.ndarray


def make_scene(
    *,
    lambert: bool = False,
    n_views: int = 8,
    size: int = 96,
    true_frequency: int = 32,
    init_frequency: int = 16,
    init_factor: float = 0.3,
    noise: bool = True,
    two_colours: bool = False,
    stokes_noise: float = 0.01,
    seed: int = 0,
) -> Scene:
    """Render the true bumpy sphere and build the initial mesh (see the module docstring)."""
    tv, tf = bumpy_sphere(true_frequency, 1.0)
    cams = ring_cameras(n_views, size)
    rng = np.random.default_rng(seed)
    sh = np.tile(SH, (n_views, 1))
    sh[:, 1:] += rng.normal(0.0, 0.03, (n_views, 8))
    scale = RGB_SCALE * rng.uniform(0.9, 1.1, (n_views, 1))
    albedo = albedo_of(tv) if two_colours else np.tile([0.6, 0.45, 0.3], (len(tv), 1))
    frames = render_decoded(
        tv,
        tf,
        albedo,
        cams,
        sh,
        scale,
        dop_scale=0.0 if lambert else 1.0,
        specular_dirs=None if lambert else SPECULAR_LIGHT,
        stokes_noise=stokes_noise if noise else 0.0,
        intensity_noise=0.003 if noise else 0.0,
        seed=seed,
    )
    v, f = bumpy_sphere(init_frequency, init_factor)
    return Scene(tv, tf, v, f, cams, frames, sh, scale)


def accuracy(vertices: np.ndarray, true_vertices: np.ndarray, true_faces: np.ndarray) -> float:
    """Mean distance from each vertex to the true surface, in true bounding-box diagonals (spec section 5)."""
    import open3d as o3d

    sc = o3d.t.geometry.RaycastingScene()
    sc.add_triangles(true_vertices.astype(np.float32), true_faces.astype(np.uint32))
    d = sc.compute_distance(o3d.core.Tensor(np.asarray(vertices, dtype=np.float32))).numpy()
    return float(d.mean() / np.linalg.norm(true_vertices.max(0) - true_vertices.min(0)))


def render_mitsuba_frames(
    vertices: np.ndarray,
    faces: np.ndarray,
    albedo: np.ndarray,
    cameras: list[Camera],
    sh: np.ndarray,
    rgb_scale: np.ndarray,
    *,
    material: str = "plastic",
    spp: int = 16,
    seed: int = 0,
) -> list[dict[str, np.ndarray]]:
    """Decoded frames (the keys of ``pmvir decode``) of a mesh path-traced by Mitsuba 3 (polarized).

    An independent physical renderer (``pplastic``: Fresnel-attenuated diffuse lobe, glossy
    specular reflection of the environment, perspective-exact Stokes frames), so a model checked
    against it is not checked against its own assumptions. Noise-free apart from Monte Carlo
    noise; no mosaic. ``valid`` is where every sample of the pixel hit the mesh.
    """
    from pmvir.synth.generate import polarization_truth
    from pmvir.synth.mitsuba_renderer import render_view_stokes

    frames = []
    for c, cam in enumerate(cameras):
        image = render_view_stokes(
            vertices, faces, albedo, cam, material=material, sh=sh[c], rgb_scale=rgb_scale[c],
            spp=spp, seed=seed + c,
        )
        truth = polarization_truth(image.stokes, 2.0)  # i_int = s0: the Lambert part is K S(N) rgb_scale
        hit = image.alpha == 1.0
        dop = np.where(hit, truth["dop"], 0.0).astype(np.float32)
        i_int = np.where(hit[..., None], truth["i_int"], 0.0).astype(np.float32)
        frames.append({
            "i_int": i_int,
            "i_min": ((1.0 - dop)[..., None] * i_int).astype(np.float32),
            "aop": np.where(hit, truth["aop"], 0.0).astype(np.float32),
            "dop": dop,
            "valid": hit & (i_int.mean(axis=2) > 1e-3),
            "mask": hit,
        })
    return frames


def make_mitsuba_scene(
    *, material: str = "plastic", n_views: int = 12, size: int = 96, spp: int = 16, seed: int = 0
) -> Scene:
    """The bumpy sphere of :func:`make_scene`, two colours, rendered by Mitsuba 3 instead."""
    tv, tf = bumpy_sphere(32, 1.0)
    cams = ring_cameras(n_views, size)
    rng = np.random.default_rng(seed)
    sh = np.tile(SH, (n_views, 1))
    sh[:, 1:] += rng.normal(0.0, 0.03, (n_views, 8))
    scale = RGB_SCALE * rng.uniform(0.9, 1.1, (n_views, 1))
    frames = render_mitsuba_frames(tv, tf, albedo_of(tv), cams, sh, scale, material=material, spp=spp, seed=seed)
    v, f = bumpy_sphere(16, 0.3)
    return Scene(tv, tf, v, f, cams, frames, sh, scale)
