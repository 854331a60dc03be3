"""pmvir's built-in polarimetric renderer: one linear Stokes image per view.

Per pixel: one ray through the pixel centre (exact visibility by ray casting),
the barycentric shading normal and albedo at the hit, the view's lighting
(:mod:`pmvir.synth.lighting`) and the material's Fresnel polarization
(:mod:`pmvir.synth.materials`). No cast shadows and no inter-reflections (the
method's image model has neither).

Anti-aliasing: pixels on a silhouette or a depth discontinuity (a neighbour
misses while they hit, or the depths of neighbours differ by more than 2 %) are
rendered again with ``supersample x supersample`` rays on a regular sub-pixel
grid and their Stokes vectors averaged (background counts as zero). Depth,
normals and the mask stay those of the pixel-centre ray.

Angle of polarization reference (``aop_frame``):

* ``"ray"`` (default): perspective-exact, as the spec (section 2) requires: the
  plane of incidence of each ray oriented in the ray's reference axes,
  ``alpha = atan2(e . r1, e . r0)`` with ``e = n - (n . d) d``
  (:func:`pmvir.polarization.azimuth.perspective_azimuth`, the frame Mitsuba 3
  reports in), so diffuse light has phi = alpha and specular light phi = alpha + pi/2.
* ``"normal"``: kept only to reproduce captures made with it:
  the orthographic ``alpha = atan2(-n_y, n_x)`` of the camera-frame normal, exact only
  on the optical axis; off it the AoP is wrong by up to about 14 degrees (spec section 2).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import partial
from typing import Literal

import numpy as np

from pmvir.camera import Camera
from pmvir.errors import ConfigError
from pmvir.polarization.azimuth import orthographic_azimuth, perspective_azimuth
from pmvir.synth.lighting import ViewLight
from pmvir.synth.materials import Material, material_stokes
from pmvir.synth.raycast import Hits, MeshScene, pixel_directions, rotate_rows, trace

AopFrame = Literal["normal", "ray"]


@dataclass
class ViewGeometry:
    """Per-pixel geometry of one view, from the pixel-centre rays.

    Attributes:
        mask: (H, W) bool, True where the ray hits the object.
        depth: (H, W) float32 camera-frame z of the hit, 0 on the background.
        normal_cam: (H, W, 3) float32 unit shading normal in camera axes, 0 on the background.
    """

    mask: np.ndarray
    depth: np.ndarray
    normal_cam: np.ndarray


@dataclass
class ViewRender:
    """One rendered view: linear Stokes image and its geometry.

    Attributes:
        stokes: (H, W, 3, 3) float32 [row, col, colour R/G/B, (s0, s1, s2)], renderer radiance units.
        geometry: the pixel-centre geometry.
    """

    stokes: np.ndarray
    geometry: ViewGeometry


def _pixel_grid(camera: Camera) -> tuple[np.ndarray, np.ndarray]:
    cols, rows = np.meshgrid(np.arange(camera.width), np.arange(camera.height))
    return cols.reshape(-1) + 0.5, rows.reshape(-1) + 0.5


def _shade(
    hits: Hits,
    d_world: np.ndarray,
    d_cam: np.ndarray,
    camera: Camera,
    light: ViewLight,
    *,
    material: Material,
    ior: float,
    extinction: float,
    specular: float,
    aop_frame: AopFrame,
) -> np.ndarray:
    """Stokes (M, 3, 3) of the M rays that hit (rows of ``d_world`` where ``hits.hit``)."""
    h = hits.hit
    n_w = hits.normal
    v_w = -d_world[h]
    n_c = rotate_rows(camera.R, n_w)
    cos_z = np.clip((n_w * v_w).sum(1), 0.0, 1.0)
    if aop_frame == "ray":
        azimuth, _ = perspective_azimuth(n_c.astype(np.float64), d_cam[h].astype(np.float64))
    else:
        azimuth = orthographic_azimuth(n_c)
    diffuse = light.diffuse(n_w)
    if material == "lambert":
        mirror = np.zeros_like(diffuse)
    else:
        r = 2.0 * (n_w * v_w).sum(1, keepdims=True) * n_w - v_w
        mirror = light.radiance(r / np.linalg.norm(r, axis=1, keepdims=True))
    return material_stokes(
        material,
        albedo=hits.albedo,
        diffuse_shading=diffuse,
        mirror_radiance=mirror,
        cos_zenith=cos_z,
        azimuth=azimuth,
        ior=ior,
        extinction=extinction,
        specular=specular,
    )


def _edge_pixels(hit: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """(H, W) bool: pixels whose 8-neighbourhood changes hit status or depth by > 2 %."""
    h, w = hit.shape
    pad_hit = np.pad(hit, 1, mode="edge")
    pad_d = np.pad(np.where(hit, depth, 0.0), 1, mode="edge")
    edge = np.zeros((h, w), dtype=bool)
    d0 = np.where(hit, depth, 0.0)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            if dy == 0 and dx == 0:
                continue
            nh = pad_hit[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
            nd = pad_d[1 + dy : 1 + dy + h, 1 + dx : 1 + dx + w]
            edge |= nh != hit
            edge |= hit & nh & (np.abs(nd - d0) > 0.02 * np.maximum(d0, 1e-9))
    return edge


def render_geometry(scene: MeshScene, camera: Camera) -> tuple[ViewGeometry, Hits, np.ndarray, np.ndarray]:
    """Cast the pixel-centre rays of a view.

    Returns:
        the view geometry, the raw hits (H*W rows), and the world and camera ray
        directions (H*W, 3).
    """
    u, v = _pixel_grid(camera)
    d_world, d_cam = pixel_directions(camera, u, v)
    hits = trace(scene, camera.center, d_world)
    shape = (camera.height, camera.width)
    depth = np.where(hits.hit, hits.distance * d_cam[:, 2], 0.0)
    normal_cam = np.zeros((len(d_cam), 3), dtype=np.float32)
    normal_cam[hits.hit] = rotate_rows(camera.R, hits.normal)
    geom = ViewGeometry(
        mask=hits.hit.reshape(shape),
        depth=depth.reshape(shape).astype(np.float32),
        normal_cam=normal_cam.reshape(shape + (3,)).astype(np.float32),
    )
    return geom, hits, d_world, d_cam


def render_view(
    scene: MeshScene,
    camera: Camera,
    light: ViewLight,
    *,
    material: Material = "plastic",
    ior: float = 1.5,
    extinction: float = 1.0,
    specular: float = 1.0,
    supersample: int = 2,
    aop_frame: AopFrame = "ray",
) -> ViewRender:
    """Render one view as a linear Stokes image.

    Args:
        scene: the mesh (normalized, with normals and albedo).
        camera: the view.
        light: the view's lighting.
        material: "lambert", "plastic" or "conductor".
        ior: refractive index (plastic) or real part of the complex index (conductor), > 1 for plastic.
        extinction: imaginary part of the conductor's index, >= 0.
        specular: plastic specular scale (1 = physical), >= 0.
        supersample: sub-pixel grid size for edge pixels (1 = no anti-aliasing).
        aop_frame: "ray" (perspective-exact, default) or "normal" (orthographic; see the module docstring).

    Returns:
        The Stokes image (H, W, 3, 3) float32 and the geometry.
    """
    if supersample < 1:
        raise ConfigError(f"supersample must be >= 1, got {supersample}")
    if aop_frame not in ("normal", "ray"):
        raise ConfigError(f"aop_frame must be 'normal' or 'ray', got {aop_frame!r}")
    shade = partial(
        _shade, material=material, ior=ior, extinction=extinction, specular=specular, aop_frame=aop_frame
    )
    geom, hits, d_world, d_cam = render_geometry(scene, camera)
    h, w = camera.height, camera.width
    stokes = np.zeros((h * w, 3, 3), dtype=np.float32)
    if hits.hit.any():
        stokes[hits.hit] = shade(hits, d_world, d_cam, camera, light)
    if supersample > 1:
        edge = _edge_pixels(geom.mask, geom.depth).reshape(-1)
        idx = np.flatnonzero(edge)
        if len(idx):
            s = supersample
            offs = (np.arange(s) + 0.5) / s - 0.5
            oy, ox = np.meshgrid(offs, offs, indexing="ij")
            u = ((idx % w) + 0.5)[:, None] + ox.reshape(1, -1)
            v = ((idx // w) + 0.5)[:, None] + oy.reshape(1, -1)
            dw, dc = pixel_directions(camera, u.reshape(-1), v.reshape(-1))
            sub_hits = trace(scene, camera.center, dw)
            sub = np.zeros((len(dw), 3, 3), dtype=np.float32)
            if sub_hits.hit.any():
                sub[sub_hits.hit] = shade(sub_hits, dw, dc, camera, light)
            stokes[idx] = sub.reshape(len(idx), s * s, 3, 3).mean(axis=1)
    return ViewRender(stokes=stokes.reshape(h, w, 3, 3), geometry=geom)
