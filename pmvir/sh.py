"""Second-order spherical-harmonics shading in pmvir's basis (spec section 3, "pmvir-sh9").

``S(N) = L0 + L1*Ny + L2*Nz + L3*Nx + L4*Nx*Ny + L5*Ny*Nz + L6*(Nz^2 - 1/3)
+ L7*Nx*Nz + L8*(Nx^2 - Ny^2)`` for a unit world-frame normal N. The functions
work on NumPy arrays and on PyTorch tensors alike (the refinement differentiates
through them).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from pmvir.errors import ConfigError, ShapeError

SH_BASIS_NAME = "pmvir-sh9"


def sh9_basis(normals: Any) -> Any:
    """The nine basis functions at unit normals.

    Args:
        normals: (..., 3) unit normals, NumPy array or torch tensor.

    Returns:
        (..., 9) basis values, same type and dtype as ``normals``.

    Example:
        >>> sh9_basis(np.array([0.0, 0.0, 1.0])).round(4)
        array([1.    , 0.    , 1.    , 0.    , 0.    , 0.    , 0.6667, 0.    , 0.    ])
    """
    if normals.shape[-1] != 3:
        raise ShapeError(f"expected (..., 3) normals, got {tuple(normals.shape)}")
    x, y, z = normals[..., 0], normals[..., 1], normals[..., 2]
    one = x * 0 + 1
    terms = [one, y, z, x, x * y, y * z, z * z - 1.0 / 3.0, x * z, x * x - y * y]
    if isinstance(normals, np.ndarray):
        return np.stack(terms, axis=-1)
    import torch

    return torch.stack(terms, dim=-1)


#: Orders the refinement's lighting may use: 2 is pmvir-sh9; 3 and 4 add the real spherical
#: harmonics of degree 3 (7 terms) and 4 (9 terms), which are orthogonal over the sphere to
#: every pmvir-sh9 term, so the pmvir-sh9 part of a richer shading is its first 9 coefficients.
SH_ORDERS = (2, 3, 4)


def sh_term_count(order: int) -> int:
    """Number of basis terms of a shading of SH order ``order``: (order + 1)^2."""
    if order not in SH_ORDERS:
        raise ConfigError(f"SH order must be one of {SH_ORDERS}, got {order}")
    return (order + 1) ** 2


def sh_order_of(n_terms: int) -> int:
    """The SH order whose basis has ``n_terms`` terms (9, 16 or 25)."""
    for order in SH_ORDERS:
        if (order + 1) ** 2 == n_terms:
            return order
    raise ShapeError(f"expected 9, 16 or 25 SH coefficients, got {n_terms}")


def sh_basis(normals: Any, order: int = 2) -> Any:
    """The (order + 1)^2 basis functions at unit normals: pmvir-sh9 first, then degree 3 and 4.

    On the unit sphere the degree-3 and degree-4 terms equal the real spherical harmonics of
    those degrees (without their normalization constants, scaled to a largest value of about 1),
    so they are orthogonal to the pmvir-sh9 terms over the sphere.

    Args:
        normals: (..., 3) unit normals, NumPy array or torch tensor.
        order: 2, 3 or 4.

    Returns:
        (..., (order + 1)^2) basis values, same type and dtype as ``normals``.

    Example:
        >>> sh_basis(np.array([0.0, 0.0, 1.0]), 3)[9:].round(4)
        array([0., 0., 0., 1., 0., 0., 0.])
    """
    sh_term_count(order)
    low = sh9_basis(normals)
    if order == 2:
        return low
    x, y, z = normals[..., 0], normals[..., 1], normals[..., 2]
    x2, y2, z2 = x * x, y * y, z * z
    terms = [
        y * (3 * x2 - y2),
        x * y * z * 5.2,
        y * (5 * z2 - 1) * 0.726,
        z * (5 * z2 - 3) / 2.0,
        x * (5 * z2 - 1) * 0.726,
        z * (x2 - y2) * 2.6,
        x * (x2 - 3 * y2),
    ]
    if order == 4:
        terms += [
            x * y * (x2 - y2) * 4.0,
            y * z * (3 * x2 - y2) * 3.08,
            x * y * (7 * z2 - 1) * 1.56,
            y * z * (7 * z2 - 3) * 0.947,
            (35 * z2 * z2 - 30 * z2 + 3) / 8.0,
            x * z * (7 * z2 - 3) * 0.947,
            (x2 - y2) * (7 * z2 - 1) * 0.78,
            x * z * (x2 - 3 * y2) * 3.08,
            x2 * x2 - 6 * x2 * y2 + y2 * y2,
        ]
    if isinstance(normals, np.ndarray):
        return np.concatenate([low, np.stack(terms, axis=-1)], axis=-1)
    import torch

    return torch.cat([low, torch.stack(terms, dim=-1)], dim=-1)


def sh9_shading(normals: Any, coeffs: Any) -> Any:
    """Shading S(N) for normals (..., 3) and coefficients (..., 9) (broadcast), shape (...).

    Example:
        Constant plus a light from +z (L2 = 0.5): brightest facing up, darkest facing down.

        >>> up_down = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]])
        >>> sh9_shading(up_down, np.array([1.0, 0, 0.5, 0, 0, 0, 0, 0, 0]))
        array([1.5, 0.5])
    """
    return (sh9_basis(normals) * coeffs).sum(-1)


def fibonacci_sphere(n: int) -> np.ndarray:
    """``n`` unit directions spread evenly on the sphere (Fibonacci lattice), (n, 3) float64."""
    if n < 1:
        raise ConfigError(f"need at least one direction, got {n}")
    i = np.arange(n, dtype=np.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], axis=1)


def project_to_sh9(directions: np.ndarray, values: np.ndarray) -> np.ndarray:
    """Least-squares pmvir-sh9 coefficients of a shading function sampled at unit directions.

    Args:
        directions: (M, 3) unit directions, M >= 9, spread over the sphere.
        values: (M,) or (M, C) shading values.

    Returns:
        (9,) or (9, C) coefficients.
    """
    basis = sh9_basis(np.asarray(directions, dtype=np.float64))
    coeffs, *_ = np.linalg.lstsq(basis, np.asarray(values, dtype=np.float64), rcond=None)
    return coeffs


#: Per-band factor from a Lambertian shading's coefficients to the coefficients of
#: the distant radiance that produces it: shading S = E / pi with irradiance
#: E_l = A_l * L_l (A_0 = pi, A_1 = 2 pi / 3, A_2 = pi / 4), so L_l = pi / A_l * S_l.
_RADIANCE_FROM_SHADING = np.array([1.0, 1.5, 1.5, 1.5, 4.0, 4.0, 4.0, 4.0, 4.0])


def radiance_from_shading(coeffs: np.ndarray) -> np.ndarray:
    """pmvir-sh9 coefficients of the environment radiance whose Lambertian shading is ``coeffs``.

    With albedo K, a Lambertian surface lit by radiance L(w) shows K * S(N) where
    S = (1/pi) * integral of L(w) max(0, N.w) dw; this inverts that per SH band
    (renderers that need the environment itself, e.g. for specular reflection).

    Args:
        coeffs: (..., 9) shading coefficients.

    Returns:
        (..., 9) radiance coefficients in the same polynomial basis.
    """
    return np.asarray(coeffs, dtype=np.float64) * _RADIANCE_FROM_SHADING
