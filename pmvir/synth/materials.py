"""Reflectance and polarization of the synthetic materials, from the Fresnel equations.

Everything here works per pixel on flat arrays and returns linear Stokes
components (s0, s1, s2) in the spec's conventions (shared/spec/capture-format.md,
section 2): a component of intensity I, degree of polarization rho and angle of
polarization phi (radians, counter-clockwise from image +x toward image -y)
adds ``I`` to s0, ``I rho cos 2phi`` to s1 and ``I rho sin 2phi`` to s2.

Materials (all under unpolarized illumination, no circular polarization):

* ``lambert``: unpolarized diffuse reflection, ``s0 = K * E``.
* ``plastic``: a smooth dielectric of refractive index ``ior``.
  - Diffuse part (sub-surface scattering that leaves through the interface):
    intensity ``K * E`` exactly (the Lambertian term of the spec; the angular
    dependence of the entry/exit transmittance is folded into the albedo), with
    the polarization of Fresnel transmission: DoP
    ``(T_p - T_s) / (T_p + T_s)`` at the emission (zenith) angle, p-polarized,
    so phi = alpha (the normal's azimuth), mod pi.
  - Specular part (mirror reflection at the interface of the environment
    radiance ``L`` seen in the mirror direction): intensity
    ``specular * L * (R_s + R_p) / 2``, DoP ``(R_s - R_p) / (R_s + R_p)``,
    s-polarized, so phi = alpha + pi/2, mod pi.
* ``conductor``: a smooth metal-like surface of complex index ``ior + i k``:
  only specular reflection, tinted by the albedo, intensity
  ``K * L * (R_s + R_p) / 2``, DoP ``(R_s - R_p) / (R_s + R_p)``, s-polarized.

Here K is the albedo (linear RGB), E the diffuse shading (the spec's
``S(N) * colour``), L the environment radiance in the mirror direction, R and T
the Fresnel reflectance and transmittance for the two linear polarizations.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from pmvir.errors import ConfigError, ShapeError
from pmvir.polarization.fresnel import diffuse_dop, fresnel_reflectance

Material = Literal["lambert", "plastic", "conductor"]
MATERIALS: tuple[str, ...] = ("lambert", "plastic", "conductor")


def material_stokes(
    material: Material,
    *,
    albedo: np.ndarray,
    diffuse_shading: np.ndarray,
    mirror_radiance: np.ndarray,
    cos_zenith: np.ndarray,
    azimuth: np.ndarray,
    ior: float,
    extinction: float,
    specular: float,
) -> np.ndarray:
    """Linear Stokes vectors of the light a surface point sends toward the camera.

    Args:
        material: "lambert", "plastic" or "conductor" (see the module docstring).
        albedo: (N, 3) linear RGB albedo K in (0, 1).
        diffuse_shading: (N, 3) diffuse shading E (the spec's S(N) times the light colour).
        mirror_radiance: (N, 3) environment radiance L in the mirror direction, >= 0
            (unused for ``lambert``).
        cos_zenith: (N,) cosine of the angle between the normal and the direction to the camera.
        azimuth: (N,) azimuth alpha of the plane of incidence, radians, in the spec's sense
            (section 2: perspective-exact, :func:`pmvir.polarization.azimuth.perspective_azimuth`).
        ior: real refractive index (plastic), or real part of the complex index (conductor).
        extinction: imaginary part k of the conductor's complex index.
        specular: scale of the plastic's specular reflection (1 = physical Fresnel).

    Returns:
        (N, 3, 3) float32 Stokes vectors: [point, colour R/G/B, (s0, s1, s2)].
    """
    n = albedo.shape[0]
    if albedo.shape != (n, 3) or diffuse_shading.shape != (n, 3) or mirror_radiance.shape != (n, 3):
        raise ShapeError(
            f"expected (N, 3) albedo, shading and radiance, got {albedo.shape}, "
            f"{diffuse_shading.shape}, {mirror_radiance.shape}"
        )
    if material not in MATERIALS:
        raise ConfigError(f"unknown material {material!r}; expected one of {MATERIALS}")
    c = np.clip(np.asarray(cos_zenith, dtype=np.float64), 0.0, 1.0)
    out = np.zeros((n, 3, 3), dtype=np.float64)
    k = np.asarray(albedo, dtype=np.float64)
    e = np.asarray(diffuse_shading, dtype=np.float64)
    el = np.asarray(mirror_radiance, dtype=np.float64)
    if material == "lambert":
        out[:, :, 0] = k * e
        return out.astype(np.float32)
    if material == "plastic":
        diffuse = k * e
        r_s, r_p = fresnel_reflectance(c, ior)
        rho_d = diffuse_dop(c, ior)
        spec_i = specular * el * ((r_s + r_p) / 2.0)[:, None]
        spec_pol = specular * el * ((r_s - r_p) / 2.0)[:, None]
        # Diffuse is polarized along alpha, specular along alpha + pi/2 (cos and sin of 2phi flip sign).
        pol = diffuse * rho_d[:, None] - spec_pol
        out[:, :, 0] = diffuse + spec_i
    else:
        r_s, r_p = fresnel_reflectance(c, complex(ior, extinction))
        out[:, :, 0] = k * el * ((r_s + r_p) / 2.0)[:, None]
        pol = -k * el * ((r_s - r_p) / 2.0)[:, None]
    two_a = 2.0 * np.asarray(azimuth, dtype=np.float64)
    out[:, :, 1] = pol * np.cos(two_a)[:, None]
    out[:, :, 2] = pol * np.sin(two_a)[:, None]
    return out.astype(np.float32)
