"""The Fresnel equations and the degrees of polarization they give, one model for the whole project.

The synthesizer renders with these (:mod:`pmvir.synth.materials`) and the refinement's forward
renderer (:mod:`pmvir.refine.forward`) uses the same ones; the refinement's energy has a torch
twin of :func:`fresnel_reflectance` for its gradients (:mod:`pmvir.refine.energy`), tested
against this one.

Light arrives from air; ``eta`` is the medium's relative index (real for a dielectric,
``n + i k`` for a conductor). s is the polarization perpendicular to the plane of incidence,
p the parallel one.
"""

from __future__ import annotations

import numpy as np


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
