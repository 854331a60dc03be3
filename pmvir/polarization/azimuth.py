"""The perspective-exact azimuth of a surface normal (capture spec, section 2): one function for all.

For a unit viewing ray ``d`` (camera centre to surface point) and a unit normal
``n``, both in OpenCV camera axes, the ray's reference axes are
``r0 = normalize(d x u)`` and ``r1 = r0 x d`` with ``u = (0, -1, 0)`` the camera's
up axis, and the normal's azimuth is ``alpha = atan2(e . r1, e . r0)`` for
``e = n - (n . d) d``. This is the frame Mitsuba 3's ``stokes`` integrator reports
in; on the optical axis it is the orthographic ``atan2(-n_y, n_x)``. Diffuse
(p-polarized) light has AoP ``alpha`` mod pi, specular (s-polarized) light
``alpha + pi/2`` mod pi.

Since r0 and r1 are perpendicular to d, ``e . r0 = n . r0`` and ``e . r1 = n . r1``;
written out with ``s = sqrt(d_x^2 + d_z^2)`` (``r0 = (d_z, 0, -d_x) / s``,
``r1 = (d_x d_y, -s^2, d_y d_z) / s``) and the common factor 1/s dropped::

    alpha = atan2(d_y (n_x d_x + n_z d_z) - n_y s^2,  n_x d_z - n_z d_x)

The same function serves NumPy arrays (the renderers, checks) and torch tensors
(E_pol, differentiable): only elementwise arithmetic and ``atan2``.

>>> import numpy as np
>>> n = np.array([0.48, -0.64, -0.6])
>>> alpha, defined = perspective_azimuth(n, np.array([0.0, 0.0, 1.0]))
>>> round(float(np.degrees(alpha)), 4), round(float(np.degrees(orthographic_azimuth(n))), 4), bool(defined)
(53.1301, 53.1301, True)
>>> d = np.array([0.5, 0.3, 1.0]) / np.linalg.norm([0.5, 0.3, 1.0])
>>> round(float(np.degrees(perspective_azimuth(n, d)[0])), 2)  # off the axis: 16 degrees from it
37.47
"""

from __future__ import annotations

import math
import sys
from typing import TYPE_CHECKING, Any, TypeVar

import numpy as np

if TYPE_CHECKING:  # torch is imported by the refinement that passes tensors; the renderers need not load it
    import torch

__all__ = ["AZIMUTH_EPS", "orthographic_azimuth", "perspective_azimuth"]

#: Squared length (relative) below which the normal's component across the ray is taken as zero:
#: the normal points along the ray and its azimuth is undefined.
AZIMUTH_EPS = 1e-12

Array = TypeVar("Array", np.ndarray, "torch.Tensor")


def _is_tensor(x: Any) -> bool:
    torch = sys.modules.get("torch")  # not imported: x is no tensor
    return torch is not None and isinstance(x, torch.Tensor)


def _atan2(y: Any, x: Any) -> Any:
    if _is_tensor(y):
        return y.atan2(x)
    return np.arctan2(y, x)


def _where(cond: Any, a: Any, b: Any) -> Any:
    if _is_tensor(cond):
        return a.where(cond, b)  # torch.where(cond, a, b)
    return np.where(cond, a, b)


def perspective_azimuth(normal_cam: Array, ray_cam: Array) -> tuple[Array, Array]:
    """Azimuth alpha of normals seen along rays (spec section 2), wrapped to [0, 2 pi).

    Args:
        normal_cam: (..., 3) unit normals in OpenCV camera axes (x right, y down, z forward).
        ray_cam: (..., 3) unit directions from the camera centre to the surface points,
            camera axes (broadcast against ``normal_cam``). Must not be parallel to the
            camera's up axis (no pinhole camera looks that way).

    Returns:
        alpha (...) radians in [0, 2 pi), same array type and float dtype as the inputs,
        and a bool mask (...) of where it is defined (the normal is not along the ray;
        alpha is 0 elsewhere, with a zero gradient).
    """
    nx, ny, nz = normal_cam[..., 0], normal_cam[..., 1], normal_cam[..., 2]
    dx, dy, dz = ray_cam[..., 0], ray_cam[..., 1], ray_cam[..., 2]
    s2 = dx * dx + dz * dz
    x = nx * dz - nz * dx
    y = dy * (nx * dx + nz * dz) - ny * s2
    defined = x * x + y * y > AZIMUTH_EPS * s2
    x_safe = _where(defined, x, x * 0 + 1)
    y_safe = _where(defined, y, y * 0)
    alpha = _atan2(y_safe, x_safe) % (2.0 * math.pi)
    return alpha, defined


def orthographic_azimuth(normal_cam: Array) -> Array:
    """The orthographic rule ``atan2(-n_y, n_x)`` in [0, 2 pi) (exact only on the optical axis).

    Kept for comparisons (how far a model that ignores perspective is off) and for the
    built-in renderer's documented switch ``aop_frame="normal"``.
    """
    return _atan2(-normal_cam[..., 1], normal_cam[..., 0]) % (2.0 * math.pi)
