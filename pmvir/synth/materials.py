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

Material = Literal["lambert", "plastic", "conductor"]
MATERIALS: tuple[str, ...] = ("lambert", "plastic", "conductor")


def fresnel_reflectance(cos_i: np.ndarray, eta: complex | float) -> tuple[np.ndarray, np.ndarray]:
    """Fresnel power reflectances for light arriving from air onto a medium of index ``eta``.

    Args:
        cos_i: cosine of the angle of incidence (from the surface normal), any shape,
            values in [0, 1].
        eta: relative refractive index n (dielectric, real) or n + i k (conductor).

    Returns:
        (R_s, R_p), each shaped like ``cos_i``, float64 in [0, 1]: reflectance of the
        s (perpendicular to the plane of incidence) and p (parallel) polarizations.
    """
    c = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0)
    eta_c = complex(eta)
    sin2 = 1.0 - c * c
    cos_t = np.sqrt(1.0 - sin2 / (eta_c * eta_c) + 0j)
    r_s = (c - eta_c * cos_t) / (c + eta_c * cos_t)
    r_p = (eta_c * c - cos_t) / (eta_c * c + cos_t)
    return np.abs(r_s) ** 2, np.abs(r_p) ** 2


def specular_dop(cos_i: np.ndarray, eta: complex | float) -> np.ndarray:
    """Degree of polarization of mirror reflection, ``(R_s - R_p) / (R_s + R_p)``, float64."""
    r_s, r_p = fresnel_reflectance(cos_i, eta)
    return (r_s - r_p) / np.maximum(r_s + r_p, 1e-12)


def diffuse_dop(cos_e: np.ndarray, ior: float) -> np.ndarray:
    """Degree of polarization of diffuse light leaving a dielectric, ``(T_p - T_s) / (T_p + T_s)``.

    By reciprocity the transmittance from inside toward the emission angle
    ``theta_e`` equals that from outside at ``theta_e``, so ``T = 1 - R(theta_e)``.
    This equals Atkinson & Hancock's closed form (2006, eq. 6).

    Args:
        cos_e: cosine of the emission (zenith) angle, any shape, in [0, 1].
        ior: real refractive index of the dielectric (> 1).

    Returns:
        DoP in [0, 1), shaped like ``cos_e``, float64.
    """
    r_s, r_p = fresnel_reflectance(cos_e, ior)
    t_s, t_p = 1.0 - r_s, 1.0 - r_p
    return (t_p - t_s) / np.maximum(t_p + t_s, 1e-12)


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
