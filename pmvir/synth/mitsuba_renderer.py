"""Polarized path tracing of synthetic views with Mitsuba 3 (the optional ``mitsuba`` extra).

One view of a triangle mesh with per-vertex albedo, lit by a distant
environment, is path traced with Mitsuba's ``llvm_ad_mono_polarized`` variant,
one monochrome pass per colour channel (so colours follow the per-channel
linear model of the spec exactly, with no spectral up-sampling). The result is
the linear Stokes vector (s0, s1, s2) per pixel and colour, in the spec's
conventions (shared/spec/capture-format.md, section 2).

Conventions:

* Camera: :class:`pmvir.camera.Camera` exactly (fx, fy, cx, cy and skew of K,
  ``cam_from_world``, OpenCV axes, COLMAP pixel centres). Rays are generated
  here, not by a Mitsuba sensor: each sample of pixel [row, col] goes through
  the image point (col + u, row + v), u, v uniform in [0, 1) (a box filter over
  the pixel), from the camera centre.
* Stokes frame: s1 = I0 - I90 and s2 = I45 - I135 for polarizer angles measured
  in the image plane from image +x (right) toward image -y (up). For the ray of
  direction d the reference axis "0 degrees" is ``normalize(d x up)``, with up
  the camera's image-up axis (-y) in world coordinates: image +x for the
  central ray, perpendicular to the camera's y axis for every ray (the
  transmission axis of a 0-degree wire-grid polarizer on the sensor). Mitsuba's
  own per-ray Stokes basis is rotated into this one per sample.
* s0 is radiance: through an ideal polarizer at angle theta the pixel sees
  ``(s0 + s1 cos 2theta + s2 sin 2theta) / 2``, so the spec's ``I_int`` is s0 / 2.
* Environment (``envmap``): a lat-long radiance image (He, We, 3). Texel
  [i, j] holds the radiance arriving from world direction
  ``(sin(phi) sin(theta), cos(theta), -cos(phi) sin(theta))`` with
  ``theta = pi * i / (He - 1)`` and ``phi = 2 pi (j + 0.5) / We`` (Mitsuba's
  ``envmap`` convention with its to_world left at the identity; world +y is
  the pole). :func:`envmap_directions` returns these directions; values are
  interpolated bilinearly between texels.
* SH lighting (``sh`` with ``rgb_scale``): the environment whose Lambertian
  shading is the pmvir-sh9 shading S(N) (:func:`pmvir.sh.radiance_from_shading`)
  times ``rgb_scale``, clamped at 0, rasterized by :func:`envmap_from_sh`. A
  ``diffuse`` surface of albedo K then renders to s0 = K * S(N) * rgb_scale.

Materials (Mitsuba plugins, each inside ``twosided``; the per-vertex albedo is
interpolated barycentrically):

* ``diffuse`` (alias ``lambert``): Lambertian, reflectance = albedo, unpolarized.
* ``pplastic`` (alias ``plastic``): Baek et al.'s polarized plastic, diffuse
  reflectance = albedo (attenuated by the Fresnel transmittances in and out, so
  the diffuse part is p-polarized, phi = alpha), interior index ``ior``,
  Beckmann roughness ``roughness``, specular lobe scaled by ``specular``
  (s-polarized, phi = alpha + pi/2).
* ``conductor``: smooth mirror with complex index ``ior + i * extinction``,
  tinted by the albedo (specular_reflectance), s-polarized.
"""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import numpy as np

from pmvir.camera import Camera
from pmvir.errors import ConfigError, PmvirError
from pmvir.sh import radiance_from_shading, sh9_basis

#: The Mitsuba variant used; it needs Dr.Jit's LLVM backend (a libLLVM shared library).
VARIANT = "llvm_ad_mono_polarized"
#: Oldest libLLVM known to compile Mitsuba 3.9's kernels (LLVM 15 and 16 abort the process).
MIN_LLVM = (19, 0, 0)
MATERIALS: tuple[str, ...] = ("diffuse", "pplastic", "conductor")
#: pmvir.synth material names accepted as aliases of the Mitsuba ones.
MATERIAL_ALIASES: dict[str, str] = {"lambert": "diffuse", "plastic": "pplastic"}
#: Rays traced per Mitsuba call (bounds memory: about 150 bytes of state per ray).
_MAX_WAVEFRONT = 1 << 21
_ALBEDO_ATTRIBUTE = "vertex_albedo"


class StokesImage(NamedTuple):
    """A rendered view.

    Attributes:
        stokes: (H, W, 3, 3) float32: [row, col, colour R/G/B, (s0, s1, s2)], linear radiance.
        alpha: (H, W) float32 in [0, 1], the fraction of each pixel's samples whose camera ray
            hits the mesh (1 inside the object, fractional on its silhouette, 0 on background).
    """

    stokes: np.ndarray
    alpha: np.ndarray


def envmap_directions(height: int, width: int) -> np.ndarray:
    """World directions of the texels of a lat-long environment map (module docstring convention).

    Args:
        height, width: texels, height >= 3, width >= 2.

    Returns:
        (height, width, 3) float64 unit directions pointing from the scene toward the light.
    """
    if height < 3 or width < 2:
        raise ConfigError(f"an environment map needs at least 3 x 2 texels, got {height} x {width}")
    theta = np.pi * np.arange(height) / (height - 1)
    phi = 2.0 * np.pi * (np.arange(width) + 0.5) / width
    st, ct = np.sin(theta)[:, None], np.cos(theta)[:, None]
    sp, cp = np.sin(phi)[None, :], np.cos(phi)[None, :]
    return np.stack([sp * st, np.broadcast_to(ct, (height, width)), -cp * st], axis=-1)


def envmap_from_sh(
    coeffs: np.ndarray, rgb_scale: np.ndarray, *, height: int = 64, width: int = 128
) -> np.ndarray:
    """Lat-long environment whose Lambertian shading is the pmvir-sh9 shading times rgb_scale.

    Args:
        coeffs: (9,) pmvir-sh9 shading coefficients S (spec section 3).
        rgb_scale: (3,) per-channel colour of the light.
        height, width: texels of the map.

    Returns:
        (height, width, 3) float32 radiance, clamped at 0 (where the SH radiance is negative
        the shading of the map differs from S(N) * rgb_scale).
    """
    coeffs = np.asarray(coeffs, dtype=np.float64)
    rgb_scale = np.asarray(rgb_scale, dtype=np.float64)
    if coeffs.shape != (9,):
        raise ConfigError(f"expected (9,) SH coefficients, got {coeffs.shape}")
    if rgb_scale.shape != (3,):
        raise ConfigError(f"expected (3,) rgb_scale, got {rgb_scale.shape}")
    radiance = sh9_basis(envmap_directions(height, width)) @ radiance_from_shading(coeffs)
    return np.maximum(radiance[..., None] * rgb_scale, 0.0).astype(np.float32)


@functools.cache
def _mitsuba() -> tuple[Any, Any]:
    """Import Mitsuba, select :data:`VARIANT` and register the vertex-albedo texture (once)."""
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:
        raise PmvirError(
            "the Mitsuba renderer needs the optional extra: pip install 'pmvir[mitsuba]'"
        ) from exc
    if not dr.has_backend(dr.JitBackend.LLVM):
        raise PmvirError(
            "Mitsuba's LLVM backend is unavailable: install libLLVM (Debian: apt-get install libllvm19) "
            "and, if it is not found, set DRJIT_LIBLLVM_PATH to the libLLVM.so file"
        )
    version = tuple(dr.detail.llvm_version())
    if version < MIN_LLVM:
        # Older LLVMs abort the process when compiling Mitsuba's kernels (15 and 16 do).
        raise PmvirError(
            f"Dr.Jit loaded LLVM {'.'.join(map(str, version))}, Mitsuba needs LLVM >= {MIN_LLVM[0]}: "
            "install it (Debian: apt-get install libllvm19) and point DRJIT_LIBLLVM_PATH at its libLLVM.so"
        )
    mi.set_variant(VARIANT)

    class VertexAlbedo(mi.Texture):
        """The mesh's one-channel ``vertex_albedo`` attribute as a texture that also reports its mean.

        Mitsuba's own ``mesh_attribute`` texture has no ``mean()``, which ``pplastic`` needs.
        """

        def __init__(self, props: Any) -> None:
            mi.Texture.__init__(self, props)
            self.mean_value = float(props.get("mean", 0.5))
            self.mesh: Any = None  # set once the mesh is built

        def eval(self, si: Any, active: Any = True) -> Any:
            return mi.UnpolarizedSpectrum(self.mesh.eval_attribute_1(_ALBEDO_ATTRIBUTE, si, active))

        def eval_1(self, si: Any, active: Any = True) -> Any:
            return self.mesh.eval_attribute_1(_ALBEDO_ATTRIBUTE, si, active)

        def mean(self) -> float:  # type: ignore[override]  # Mitsuba takes a Python float here
            return self.mean_value

        def is_spatially_varying(self) -> bool:
            return True

        def to_string(self) -> str:
            return f"VertexAlbedo[mean={self.mean_value}]"

    mi.register_texture("pmvir_vertex_albedo", VertexAlbedo)
    return mi, dr


def _bsdf_dict(albedo_texture: Any, *, material: str, ior: float, extinction: float,
               roughness: float, specular: float) -> dict[str, Any]:
    """The Mitsuba BSDF dictionary of a material, its albedo slot filled with ``albedo_texture``."""
    if material == "diffuse":
        inner = {"type": "diffuse", "reflectance": albedo_texture}
    elif material == "pplastic":
        inner = {"type": "pplastic", "diffuse_reflectance": albedo_texture, "int_ior": ior,
                 "alpha": roughness, "specular_reflectance": {"type": "uniform", "value": specular}}
    else:
        inner = {"type": "conductor", "eta": {"type": "uniform", "value": ior},
                 "k": {"type": "uniform", "value": extinction}, "specular_reflectance": albedo_texture}
    return {"type": "twosided", "material": inner}


def _build_scene(mi: Any, vertices: np.ndarray, faces: np.ndarray, normals: np.ndarray | None,
                 albedo: np.ndarray, material: dict[str, Any]) -> Any:
    """A Mitsuba scene of the mesh (with a one-channel albedo attribute) and an environment emitter.

    The scene starts with colour channel 0 of ``albedo`` (N, 3) and a constant environment; the
    caller sets each channel's albedo and environment through ``mi.traverse``.
    """
    texture = mi.load_dict({"type": "pmvir_vertex_albedo", "mean": float(albedo.mean())})
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(_bsdf_dict(texture, **material))
    mesh = mi.Mesh("pmvir_mesh", len(vertices), len(faces), props=props, has_vertex_normals=True)
    texture.mesh = mesh
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(vertices.astype(np.float32).ravel())
    params["faces"] = mi.UInt32(faces.astype(np.uint32).ravel())
    if normals is not None:
        params["vertex_normals"] = mi.Float(normals.astype(np.float32).ravel())
    params.update()
    if normals is None:
        mesh.recompute_vertex_normals()
    mesh.add_attribute(_ALBEDO_ATTRIBUTE, 1, mi.Float(albedo[:, 0].astype(np.float32)))
    env = {"type": "envmap", "bitmap": mi.Bitmap(np.ones((3, 4, 3), dtype=np.float32))}
    return mi.load_dict({"type": "scene", "mesh": mesh, "env": env})


def _envmap_data(mi: Any, radiance: np.ndarray) -> Any:
    """Mitsuba's internal ``data`` tensor of an ``envmap`` of one channel's radiance (He, We).

    Built by the plugin itself, so its padding of the periodic columns (which differs between
    Mitsuba versions) is whatever the installed version expects.
    """
    bitmap = mi.Bitmap(np.repeat(radiance[..., None], 3, axis=-1).astype(np.float32))
    return mi.traverse(mi.load_dict({"type": "envmap", "bitmap": bitmap}))["data"]


def _check_inputs(vertices: np.ndarray, faces: np.ndarray, albedo: np.ndarray,
                  normals: np.ndarray | None, camera: Camera, material: str, spp: int,
                  max_depth: int, roughness: float, ior: float, extinction: float, specular: float) -> None:
    """Raise ConfigError for inputs that do not match :func:`render_view_stokes`'s contract."""
    n = len(vertices)
    if vertices.ndim != 2 or vertices.shape[1] != 3 or n < 3:
        raise ConfigError(f"expected (N, 3) vertices with N >= 3, got {vertices.shape}")
    if faces.ndim != 2 or faces.shape[1] != 3 or len(faces) < 1:
        raise ConfigError(f"expected (F, 3) faces with F >= 1, got {faces.shape}")
    if faces.min() < 0 or faces.max() >= n:
        raise ConfigError(f"face indices must lie in [0, {n}), got [{faces.min()}, {faces.max()}]")
    if albedo.shape != (n, 3):
        raise ConfigError(f"expected ({n}, 3) albedo, got {albedo.shape}")
    if not np.all(np.isfinite(vertices)) or not np.all(np.isfinite(albedo)):
        raise ConfigError("vertices and albedo must be finite")
    if normals is not None and normals.shape != (n, 3):
        raise ConfigError(f"expected ({n}, 3) normals, got {normals.shape}")
    if material not in MATERIALS:
        names = MATERIALS + tuple(MATERIAL_ALIASES)
        raise ConfigError(f"unknown material {material!r}; expected one of {names}")
    if spp < 1 or max_depth < 1:
        raise ConfigError(f"spp and max_depth must be >= 1, got {spp} and {max_depth}")
    if camera.width < 1 or camera.height < 1:
        raise ConfigError(f"camera image must be at least 1 x 1, got {camera.width} x {camera.height}")
    if material == "pplastic" and not roughness > 0.0:
        raise ConfigError(f"pplastic needs roughness > 0, got {roughness}")
    if material != "diffuse" and (not ior > 0.0 or ior == 1.0):
        raise ConfigError(f"ior must be positive and differ from 1, got {ior}")
    if not (extinction >= 0.0 and specular >= 0.0):
        raise ConfigError(f"extinction and specular must be >= 0, got {extinction} and {specular}")


def _lighting(sh: np.ndarray | None, rgb_scale: np.ndarray | None, envmap: np.ndarray | None) -> np.ndarray:
    """The environment map (He, We, 3) float32 from exactly one of (sh, rgb_scale) and envmap."""
    if (sh is None) == (envmap is None):
        raise ConfigError("give exactly one of sh (with rgb_scale) and envmap")
    if sh is not None:
        if rgb_scale is None:
            raise ConfigError("sh lighting needs rgb_scale (3,)")
        return envmap_from_sh(sh, rgb_scale)
    env = np.asarray(envmap, dtype=np.float32)
    if env.ndim != 3 or env.shape[2] != 3 or env.shape[0] < 3 or env.shape[1] < 2:
        raise ConfigError(f"expected an (He >= 3, We >= 2, 3) envmap, got {env.shape}")
    if not np.all(np.isfinite(env)) or env.min() < 0.0:
        raise ConfigError("envmap radiance must be finite and >= 0")
    return env


def render_view_stokes(
    vertices: np.ndarray,
    faces: np.ndarray,
    albedo: np.ndarray,
    camera: Camera,
    *,
    material: str = "pplastic",
    ior: float = 1.5,
    extinction: float = 0.0,
    roughness: float = 0.1,
    specular: float = 1.0,
    sh: np.ndarray | None = None,
    rgb_scale: np.ndarray | None = None,
    envmap: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    spp: int = 64,
    max_depth: int = 6,
    seed: int = 0,
) -> StokesImage:
    """Path-trace the linear Stokes image of one view with Mitsuba 3 (conventions: module docstring).

    Args:
        vertices: (N, 3) world positions.
        faces: (F, 3) vertex indices, counter-clockwise seen from outside.
        albedo: (N, 3) linear RGB albedo in [0, 1].
        camera: the view (intrinsics, cam_from_world, image size).
        material: "diffuse" | "pplastic" | "conductor" (or the aliases "lambert", "plastic").
        ior: pplastic's interior refractive index, or the conductor's real index part.
        extinction: the conductor's imaginary index part k (0: a dielectric mirror).
        roughness: pplastic's Beckmann RMS slope (> 0).
        specular: pplastic's specular-lobe scale (1 = physical; 0 leaves diffuse polarization only).
        sh: (9,) pmvir-sh9 shading coefficients, with ``rgb_scale`` (3,); or
        envmap: (He, We, 3) lat-long radiance (direction convention: module docstring).
        normals: optional (N, 3) vertex shading normals; by default Mitsuba's smooth normals.
        spp: samples per pixel.
        max_depth: longest path (1 = emitters only, 2 = direct lighting, ...).
        seed: random seed; the same inputs and seed give the same image.

    Returns:
        StokesImage(stokes (H, W, 3, 3) float32, alpha (H, W) float32).

    Raises:
        ConfigError: an input has the wrong shape or an option is out of range.
        PmvirError: Mitsuba or its LLVM backend is unavailable.
    """
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    albedo = np.asarray(albedo, dtype=np.float32)
    normals = None if normals is None else np.asarray(normals, dtype=np.float64)
    material = MATERIAL_ALIASES.get(material, material)
    _check_inputs(vertices, faces, albedo, normals, camera, material, spp, max_depth, roughness, ior,
                  extinction, specular)
    env = _lighting(sh, rgb_scale, envmap)
    mi, dr = _mitsuba()
    if mi.variant() != VARIANT:  # another caller in this process switched Mitsuba's variant
        mi.set_variant(VARIANT)

    width, height = camera.width, camera.height
    n_pix = width * height
    per_call = max(1, min(spp, _MAX_WAVEFRONT // n_pix))
    integrator = mi.load_dict({"type": "path", "max_depth": int(max_depth), "hide_emitters": False})
    options = dict(material=material, ior=ior, extinction=extinction, roughness=roughness, specular=specular)
    scene = _build_scene(mi, vertices, faces, normals, albedo, options)
    params = mi.traverse(scene)
    # The three channels are rendered by one scene whose albedo and environment are swapped, so
    # they share one compiled kernel (Dr.Jit also reuses it across calls and caches it on disk).
    channel_data = [(mi.Float(albedo[:, c]), _envmap_data(mi, env[..., c])) for c in range(3)]

    pixel_to_world = camera.R.T @ np.linalg.inv(camera.K)  # world ray direction of pixel (u, v, 1)
    up = -camera.R[1]  # image -y (up) in world coordinates
    acc = np.zeros((3, 3, n_pix), dtype=np.float64)
    hits = np.zeros(n_pix, dtype=np.float64)
    done = chunk = 0
    while done < spp:
        k = min(per_call, spp - done)
        # Sample j of pixel p is lane p * k + j, so each pixel's samples form one block.
        pixel = dr.arange(mi.UInt32, k * n_pix) // k
        row = pixel // width
        col = pixel - row * width
        for c in range(3):
            params["mesh." + _ALBEDO_ATTRIBUTE], params["env.data"] = channel_data[c]
            params.update()
            sampler = mi.load_dict({"type": "independent"})
            # Same seed for every channel: same pixel jitter and, mostly, the same paths.
            sampler.seed((seed * 1_000_003 + chunk) & 0x7FFFFFFF, k * n_pix)
            ray, cos2g, sin2g = _camera_rays(mi, dr, sampler, col, row, camera.center, pixel_to_world, up)
            if c == 0:
                hit = dr.select(scene.ray_intersect_preliminary(ray).is_valid(), 1.0, 0.0)
                hits += np.asarray(dr.block_sum(mi.Float(hit), k), dtype=np.float64)
            spec, _, _ = integrator.sample(scene, sampler, ray)
            s0, s1, s2 = (mi.Float(spec[i, 0][0]) for i in range(3))
            # (s1, s2) from Mitsuba's basis to the target basis, a rotation by 2 gamma.
            stokes = [s0, cos2g * s1 + sin2g * s2, cos2g * s2 - sin2g * s1]
            stokes = [dr.select(dr.isfinite(x), x, 0.0) for x in stokes]
            dr.eval(*stokes)  # one path-tracing kernel for the three components
            sums = [dr.block_sum(x, k) for x in stokes]
            acc[c] += np.stack([np.asarray(x, dtype=np.float64) for x in sums])
        done += k
        chunk += 1
    stokes_image = (acc / spp).reshape(3, 3, height, width).transpose(2, 3, 0, 1)
    alpha = (hits / spp).reshape(height, width)
    return StokesImage(stokes_image.astype(np.float32), alpha.astype(np.float32))


def _camera_rays(mi: Any, dr: Any, sampler: Any, col: Any, row: Any, center: np.ndarray,
                 pixel_to_world: np.ndarray, up: np.ndarray) -> tuple[Any, Any, Any]:
    """Camera rays through jittered points of the pixels, and the Stokes basis rotation of each.

    Args:
        sampler: Mitsuba sampler; its next 2D sample jitters the ray inside its pixel.
        col, row: pixel indices per lane (UInt32).
        center: (3,) camera centre (world).
        pixel_to_world: (3, 3) R^T K^-1: world direction of the image point (u, v, 1).
        up: (3,) the camera's image-up axis (world).

    Returns:
        (ray, cos 2gamma, sin 2gamma). Light travels along ``w = -d`` toward the camera; Mitsuba
        expresses its Stokes vector in the right-handed frame (x = stokes_basis(w), y = w x x, w),
        the target x axis is ``normalize(d x up)``, and gamma is the angle from Mitsuba's x axis
        to the target one, counter-clockwise about w: (s1, s2) then rotate by -2 gamma.
    """
    jitter = sampler.next_2d()
    u = mi.Float(col) + jitter.x
    v = mi.Float(row) + jitter.y
    # Opaque constants: the compiled kernel does not depend on the camera and is reused across views.
    m = [[dr.opaque(mi.Float, float(x)) for x in r] for r in pixel_to_world]
    d = dr.normalize(mi.Vector3f(m[0][0] * u + m[0][1] * v + m[0][2],
                                 m[1][0] * u + m[1][1] * v + m[1][2],
                                 m[2][0] * u + m[2][1] * v + m[2][2]))
    ray = mi.Ray3f(mi.Point3f(*(dr.opaque(mi.Float, float(x)) for x in center)), d)
    w = -d
    current = mi.mueller.stokes_basis(w)
    target = dr.normalize(dr.cross(d, mi.Vector3f(*(dr.opaque(mi.Float, float(x)) for x in up))))
    sin_g = dr.dot(w, dr.cross(current, target))
    cos_g = dr.dot(current, target)
    return ray, cos_g * cos_g - sin_g * sin_g, 2.0 * sin_g * cos_g
