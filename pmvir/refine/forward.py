"""The refinement's image model rendered per pixel: decoded frames of a known scene.

Used to make test data and benchmarks with a known answer (a full mosaic
renderer lives in :mod:`pmvir.synth`). For every pixel the ray hits the mesh
(Open3D ray casting) and, with the normal N and albedo K interpolated
barycentrically from the vertices (smooth shading):

* unpolarized part ``I_min = K * S(N, L_basis) * L_scale`` (the pmvir model, exactly);
* AoP from the normal's perspective-exact azimuth alpha seen along the pixel's ray
  (spec section 2, :func:`pmvir.polarization.azimuth.perspective_azimuth`):
  diffuse-dominant pixels phi = alpha mod pi,
  specular-dominant pixels (the half vector of the view and one of
  ``specular_dirs`` within ``specular_cos`` of N) phi = alpha + pi/2 mod pi;
* DoP from the Fresnel formulas (diffuse or specular, refractive index ``eta``),
  times ``dop_scale`` (0 gives a Lambertian, unpolarized surface);
* ``I_int = I_min / (1 - rho)``, so that ``I_min = (1 - rho) I_int`` as in the spec;
* noise: Gaussian on the normalized Stokes components (s1/s0, s2/s0) with
  ``stokes_noise`` (so AoP noise grows where DoP is small) and on intensities with
  ``intensity_noise``.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pmvir.camera import Camera
from pmvir.geometry.mesh_ops import raycasting_scene, vertex_normals
from pmvir.polarization.azimuth import perspective_azimuth
from pmvir.polarization.fresnel import diffuse_dop, specular_dop
from pmvir.sh import sh_basis, sh_order_of


def render_decoded(
    vertices: np.ndarray,
    faces: np.ndarray,
    albedo: np.ndarray,
    cameras: Sequence[Camera],
    sh: np.ndarray,
    rgb_scale: np.ndarray,
    *,
    eta: float = 1.5,
    dop_scale: float = 1.0,
    specular_dirs: np.ndarray | None = None,
    specular_cos: float = 0.97,
    stokes_noise: float = 0.0,
    intensity_noise: float = 0.0,
    noise_floor: float = 1e-3,
    seed: int = 0,
) -> list[dict[str, np.ndarray]]:
    """Render decoded frames (the keys of ``pmvir decode``'s npz files) of a mesh.

    Args:
        vertices: (N, 3) positions; faces: (F, 3) ccw triangles; albedo: (N, 3) linear RGB.
        cameras: V cameras.
        sh: (V, T) or (T,) shading coefficients: pmvir-sh9 (T = 9) or :func:`pmvir.sh.sh_basis`'s
            richer bases (T = 16, 25); rgb_scale: (V, 3) or (3,).
        eta: refractive index for the DoP formulas.
        dop_scale: multiplies every DoP (0: Lambertian).
        specular_dirs: (M, 3) unit world directions towards lights whose mirror
            directions make pixels specular-dominant; None: none.
        specular_cos: a pixel is specular-dominant when N . h > this for some light.
        stokes_noise, intensity_noise: standard deviations (see the module docstring).
        noise_floor: pixels with mean I_int at or below this are invalid.
        seed: noise seed.

    Returns:
        per view a dict: ``i_min``, ``i_int`` (H, W, 3) float32, ``aop``, ``dop`` (H, W)
        float32, ``valid`` (H, W) bool, ``mask`` (H, W) bool (ray hit the mesh),
        ``depth`` (H, W) float32 ray distance (inf where no hit).
    """
    import open3d as o3d

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    k = np.asarray(albedo, dtype=np.float64)
    n_views = len(cameras)
    sh = np.asarray(sh, dtype=np.float64)
    sh_order = sh_order_of(sh.shape[-1])
    sh = np.broadcast_to(sh, (n_views, sh.shape[-1]))
    rgb_scale = np.broadcast_to(np.asarray(rgb_scale, dtype=np.float64), (n_views, 3))
    vn = vertex_normals(v, f)
    rng = np.random.default_rng(seed)
    local = raycasting_scene(v, f)
    scene, origin = local.scene, local.origin
    out = []
    for c, cam in enumerate(cameras):
        o, d = cam.pixel_rays()
        rays = np.concatenate([o - origin, d], axis=-1).astype(np.float32)
        hit = scene.cast_rays(o3d.core.Tensor(rays))
        t_hit = hit["t_hit"].numpy()
        mask = np.isfinite(t_hit)
        prim = hit["primitive_ids"].numpy()[mask].astype(np.int64)
        uv = hit["primitive_uvs"].numpy()[mask].astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        tri = f[prim]
        nrm = np.einsum("pk,pkj->pj", bary, vn[tri])
        nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-12)
        alb = np.einsum("pk,pkj->pj", bary, k[tri])
        view_dir = -d[mask]
        i_min = alb * np.maximum(sh_basis(nrm, sh_order) @ sh[c], 0.0)[:, None] * rgb_scale[c][None, :]
        alpha, _ = perspective_azimuth(nrm @ cam.R.T, d[mask] @ cam.R.T)
        cosz = np.clip((nrm * view_dir).sum(1), 0.0, 1.0)
        spec = np.zeros(len(nrm), dtype=bool)
        if specular_dirs is not None:
            for light in np.asarray(specular_dirs, dtype=np.float64).reshape(-1, 3):
                hv = view_dir + light / np.linalg.norm(light)
                hv /= np.maximum(np.linalg.norm(hv, axis=1, keepdims=True), 1e-12)
                spec |= (nrm * hv).sum(1) > specular_cos
        rho = np.where(spec, specular_dop(cosz, eta), diffuse_dop(cosz, eta)) * dop_scale
        rho = np.clip(rho, 0.0, 0.95)
        phi = np.mod(alpha + np.where(spec, np.pi / 2, 0.0), np.pi)
        i_int = i_min / (1.0 - rho)[:, None]
        if stokes_noise > 0:
            s1 = rho * np.cos(2 * phi) + rng.normal(0.0, stokes_noise, len(rho))
            s2 = rho * np.sin(2 * phi) + rng.normal(0.0, stokes_noise, len(rho))
            phi = np.mod(0.5 * np.arctan2(s2, s1), np.pi)
            rho = np.clip(np.hypot(s1, s2), 0.0, 1.0)
        if intensity_noise > 0:
            i_int = i_int + rng.normal(0.0, intensity_noise, i_int.shape)
            i_min = (1.0 - rho)[:, None] * i_int
        h, w = cam.height, cam.width
        frame = {
            "i_min": np.zeros((h, w, 3), np.float32),
            "i_int": np.zeros((h, w, 3), np.float32),
            "aop": np.zeros((h, w), np.float32),
            "dop": np.zeros((h, w), np.float32),
        }
        frame["i_min"][mask] = i_min
        frame["i_int"][mask] = i_int
        frame["aop"][mask] = np.minimum(phi, np.nextafter(np.pi, 0))
        frame["dop"][mask] = rho
        frame["valid"] = mask & (frame["i_int"].mean(axis=2) > noise_floor)
        frame["mask"] = mask
        frame["depth"] = np.where(mask, t_hit, np.inf).astype(np.float32)
        out.append(frame)
    return out
