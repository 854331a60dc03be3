"""Linear Stokes parameters, AoP, DoP, I_int and I_min (spec section 2).

For the four polarizer angles 0, 45, 90, 135 degrees (ccw from image +x toward
image -y, see shared/spec/capture-format.md):

* ``s0 = (I0 + I45 + I90 + I135) / 2``, ``s1 = I0 - I90``, ``s2 = I45 - I135``;
* ``I_int = (I0 + I45 + I90 + I135) / 4`` per colour;
* AoP ``phi = 0.5 * atan2(s2, s1)`` wrapped to [0, pi), radians, and DoP
  ``rho = sqrt(s1^2 + s2^2) / s0`` clipped to [0, 1], both from the
  colour-averaged intensities;
* ``I_min = (1 - rho) * I_int`` per colour.

The model behind them: an ideal linear polarizer at angle theta passes
``I_theta = s0 / 2 * (1 + rho * cos(2 (theta - phi)))``.

All functions are pure and return float32 (bool for masks).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from pmvir.errors import ShapeError
from pmvir.polarization.lattice import STRIP_ROWS
from pmvir.polarization.layout import ANGLES_DEG

#: Smallest s0 divided by when forming the DoP (normalized intensity units).
DOP_EPS = 1e-8


@dataclass(frozen=True)
class PolarizationImages:
    """Per-pixel polarization quantities of one frame.

    Attributes:
        i_int: mean over the four angles, (H, W, C) float32, linear normalized units.
        i_min: unpolarized part ``(1 - dop) * i_int``, (H, W, C) float32.
        aop: angle of polarization, (H, W) float32 radians in [0, pi), ccw.
        dop: degree of polarization, (H, W) float32 in [0, 1].
        valid: (H, W) bool; False where AoP/DoP are not measurements (noise
            floor, saturation in the interpolation footprint, outside the mask).
    """

    i_int: np.ndarray
    i_min: np.ndarray
    aop: np.ndarray
    dop: np.ndarray
    valid: np.ndarray


def intensities_from_polarization(s0: np.ndarray, aop: np.ndarray, dop: np.ndarray) -> np.ndarray:
    """The forward model: what ideal polarizers at 0, 45, 90, 135 degrees pass.

    ``I_theta = s0 / 2 * (1 + dop * cos(2 (theta - aop)))`` per colour.

    Args:
        s0: (H, W, C) total intensity per colour (or (H, W) for C = 1), float.
        aop: (H, W) radians, ccw.
        dop: (H, W) in [0, 1].

    Returns:
        (H, W, 4, C) float32 intensities, angles in ANGLES_DEG order.
    """
    s0 = np.asarray(s0, dtype=np.float32)
    if s0.ndim == 2:
        s0 = s0[..., None]
    if s0.ndim != 3 or aop.shape != s0.shape[:2] or dop.shape != s0.shape[:2]:
        raise ShapeError(
            f"expected s0 (H, W, C), aop and dop (H, W); got {s0.shape}, {aop.shape}, {dop.shape}"
        )
    theta = np.deg2rad(np.asarray(ANGLES_DEG, dtype=np.float64))
    mod = 1.0 + dop[..., None] * np.cos(2.0 * (theta - aop[..., None]))  # (H, W, 4)
    return (0.5 * s0[:, :, None, :] * mod[..., None]).astype(np.float32)


def _check_intensities(intensities: np.ndarray) -> None:
    if intensities.ndim != 4 or intensities.shape[2] != 4:
        raise ShapeError(f"expected (H, W, 4, C) intensities, got shape {intensities.shape}")


def stokes_from_intensities(i: np.ndarray) -> np.ndarray:
    """Linear Stokes vectors from four polarizer angles.

    Args:
        i: intensities at 0, 45, 90, 135 degrees on the last axis, shape (..., 4), float.

    Returns:
        (s0, s1, s2) stacked on the last axis, shape (..., 3), float32.

    Example:
        Light fully polarized along the 0 degree polarizer:

        >>> stokes_from_intensities(np.array([1.0, 0.5, 0.0, 0.5]))
        array([1., 1., 0.], dtype=float32)
    """
    if i.shape[-1] != 4:
        raise ShapeError(f"expected (..., 4) intensities, got {i.shape}")
    i = i.astype(np.float32, copy=False)
    i0, i45, i90, i135 = (i[..., k] for k in range(4))
    s0 = (i0 + i45 + i90 + i135) * np.float32(0.5)
    return np.stack([s0, i0 - i90, i45 - i135], axis=-1)


def colour_mean_stokes(intensities: np.ndarray) -> np.ndarray:
    """Stokes vectors of the colour-averaged intensities.

    Args:
        intensities: (H, W, 4, C) float32, angles in ANGLES_DEG order.

    Returns:
        (H, W, 3) float32: s0, s1, s2 of ``mean over C`` of the intensities.
    """
    _check_intensities(intensities)
    return stokes_from_intensities(intensities.mean(axis=3, dtype=np.float32))


def mean_intensity(intensities: np.ndarray) -> np.ndarray:
    """I_int, the mean over the four polarizer angles.

    Args:
        intensities: (H, W, 4, C) float32.

    Returns:
        (H, W, C) float32, same units as the input.
    """
    _check_intensities(intensities)
    return intensities.mean(axis=2, dtype=np.float32)


def aop_from_stokes(stokes: np.ndarray) -> np.ndarray:
    """Angle of polarization ``0.5 * atan2(s2, s1)`` wrapped to [0, pi).

    Args:
        stokes: (..., 3) float (s0, s1, s2).

    Returns:
        (...) float32 radians in [0, pi), in the sense of the polarizer angles
        (ccw from image +x toward image -y).

    Example:
        >>> np.degrees(aop_from_stokes(np.array([[1.0, 0.0, 1.0], [1.0, -1.0, 0.0]])))
        array([45., 90.], dtype=float32)
    """
    if stokes.shape[-1] != 3:
        raise ShapeError(f"expected (..., 3) Stokes vectors, got {stokes.shape}")
    return _aop(stokes[..., 1].astype(np.float32), stokes[..., 2].astype(np.float32))


def dop_from_stokes(stokes: np.ndarray, *, eps: float = DOP_EPS) -> np.ndarray:
    """Degree of linear polarization ``sqrt(s1^2 + s2^2) / s0`` clipped to [0, 1].

    Args:
        stokes: (..., 3) float (s0, s1, s2).
        eps: s0 is clamped to at least this before dividing (normalized units).

    Returns:
        (...) float32 in [0, 1]; meaningless (but finite) where s0 is at the noise floor.

    Example:
        >>> dop_from_stokes(np.array([[2.0, 1.0, 0.0], [1.0, 0.6, 0.8]]))
        array([0.5, 1. ], dtype=float32)
    """
    if stokes.shape[-1] != 3:
        raise ShapeError(f"expected (..., 3) Stokes vectors, got {stokes.shape}")
    s = stokes.astype(np.float32, copy=False)
    return _dop(s[..., 0], s[..., 1], s[..., 2], eps)


def _aop(s1: np.ndarray, s2: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    phi = np.arctan2(s2, s1, out=out)  # (-pi, pi]
    phi *= np.float32(0.5)
    np.add(phi, np.float32(np.pi), out=phi, where=phi < 0)
    # float32 rounding can land a tiny negative angle exactly on pi
    phi[phi >= np.float32(np.pi)] = 0.0
    return phi


def _dop(s0: np.ndarray, s1: np.ndarray, s2: np.ndarray, eps: float, out: np.ndarray | None = None) -> np.ndarray:
    num = np.multiply(s1, s1, out=out)
    num += s2 * s2
    np.sqrt(num, out=num)
    num /= np.maximum(s0, np.float32(eps))
    return np.clip(num, 0.0, 1.0, out=num)


def unpolarized_intensity(i_int: np.ndarray, dop: np.ndarray) -> np.ndarray:
    """I_min = (1 - rho) * I_int.

    Args:
        i_int: (H, W, C) float32.
        dop: (H, W) float32 in [0, 1].

    Returns:
        (H, W, C) float32.
    """
    if i_int.shape[:2] != dop.shape:
        raise ShapeError(f"i_int {i_int.shape} and dop {dop.shape} disagree in size")
    return (np.float32(1.0) - dop)[..., None] * i_int


def valid_pixels(
    s0: np.ndarray,
    *,
    noise_floor: float,
    invalid: np.ndarray | None = None,
) -> np.ndarray:
    """Pixels whose AoP/DoP are measurements.

    Args:
        s0: (H, W) float32 total intensity (normalized units).
        noise_floor: pixels whose mean intensity ``s0 / 2`` (= the colour mean of
            I_int) is at or below this are invalid.
        invalid: optional (H, W) bool of pixels already known bad (saturated
            footprint, outside the mask).

    Returns:
        (H, W) bool.
    """
    valid = np.isfinite(s0) & (s0 * np.float32(0.5) > np.float32(noise_floor))
    if invalid is not None:
        if invalid.shape != s0.shape:
            raise ShapeError(f"invalid mask {invalid.shape} does not match s0 {s0.shape}")
        valid &= ~invalid
    return valid


def polarization_images(
    intensities: np.ndarray,
    *,
    noise_floor: float,
    invalid: np.ndarray | None = None,
) -> PolarizationImages:
    """All spec section 2 quantities of one demosaiced frame.

    Same results as :func:`colour_mean_stokes`, :func:`mean_intensity`,
    :func:`aop_from_stokes`, :func:`dop_from_stokes`,
    :func:`unpolarized_intensity` and :func:`valid_pixels` applied in turn
    (tested), computed plane by plane (fast on :func:`demosaic`'s planar output)
    in strips of rows (:class:`PolarizationWriter`).

    Args:
        intensities: (H, W, 4, C) float32 (e.g. from :func:`pmvir.polarization.demosaic.demosaic`).
        noise_floor: see :func:`valid_pixels`.
        invalid: optional (H, W) bool of pixels known bad before this step.

    Returns:
        The frame's :class:`PolarizationImages`; i_int and i_min C-contiguous.
    """
    images = PolarizationWriter(intensities, noise_floor=noise_floor, invalid=invalid)
    for r0 in range(0, intensities.shape[0], STRIP_ROWS):
        images.write(slice(r0, min(r0 + STRIP_ROWS, intensities.shape[0])))
    return images.result()


class PolarizationWriter:
    """:func:`polarization_images`, filled in strip by strip (row ranges in any order).

    Holds the output arrays; :meth:`write` computes the rows of a strip from the
    same rows of the intensities, so a demosaicing pass can hand each strip over
    while it is still in the CPU cache (:func:`pmvir.decode.decode_frame`).

    Args:
        intensities: (H, W, 4, C) float32; only read by :meth:`write`, for its rows.
        noise_floor: see :func:`valid_pixels`.
        invalid: optional (H, W) bool of pixels known bad before this step.
    """

    def __init__(self, intensities: np.ndarray, *, noise_floor: float, invalid: np.ndarray | None = None):
        _check_intensities(intensities)
        h, w, _, c = intensities.shape
        if invalid is not None and invalid.shape != (h, w):
            raise ShapeError(f"invalid mask {invalid.shape} does not match s0 {(h, w)}")
        self._planes = intensities.transpose(2, 3, 0, 1)  # (4, C, H, W)
        self._noise_floor = noise_floor
        self._invalid = invalid
        self._images = PolarizationImages(
            i_int=np.empty((h, w, c), dtype=np.float32),
            i_min=np.empty((h, w, c), dtype=np.float32),
            aop=np.empty((h, w), dtype=np.float32),
            dop=np.empty((h, w), dtype=np.float32),
            valid=np.empty((h, w), dtype=bool),
        )

    def write(self, rows: slice) -> None:
        """Compute the outputs' rows ``rows`` (a slice with step 1) from the same rows of the intensities."""
        strip = self._planes[:, :, rows]
        c = strip.shape[1]
        out = self._images
        i_int_c = [_weighted_sum([strip[a, k] for a in range(4)], 0.25) for k in range(c)]
        # the colour-averaged I0..I135 only enter through these sums:
        s0 = _weighted_sum(i_int_c, 2.0 / c)  # (I0 + I45 + I90 + I135) / 2
        s1 = _weighted_sum([strip[0, k] for k in range(c)], 1.0 / c)
        s1 -= _weighted_sum([strip[2, k] for k in range(c)], 1.0 / c)
        s2 = _weighted_sum([strip[1, k] for k in range(c)], 1.0 / c)
        s2 -= _weighted_sum([strip[3, k] for k in range(c)], 1.0 / c)
        _aop(s1, s2, out=out.aop[rows])
        keep = np.subtract(np.float32(1.0), _dop(s0, s1, s2, DOP_EPS, out=out.dop[rows]), out=s1)
        _interleave(i_int_c, out=out.i_int[rows])
        _interleave([p * keep for p in i_int_c], out=out.i_min[rows])
        invalid = None if self._invalid is None else self._invalid[rows]
        out.valid[rows] = valid_pixels(s0, noise_floor=self._noise_floor, invalid=invalid)

    def result(self) -> PolarizationImages:
        """The frame's :class:`PolarizationImages` (complete once every row was written)."""
        return self._images


def _weighted_sum(planes: list[np.ndarray], weight: float) -> np.ndarray:
    """``weight * sum(planes)`` as a new contiguous float32 (H, W) array.

    Uses OpenCV's threaded arithmetic on contiguous planes (demosaic's output),
    numpy otherwise.
    """
    w = np.float32(weight)
    if all(p.flags.c_contiguous and p.dtype == np.float32 for p in planes):
        if len(planes) == 1:
            return planes[0] * w
        out: np.ndarray = cv2.addWeighted(planes[0], float(w), planes[1], float(w), 0.0)
        for p in planes[2:]:
            cv2.scaleAdd(p, float(w), out, dst=out)
        return out
    out = planes[0].astype(np.float32)  # a copy
    for p in planes[1:]:
        out += p
    out *= w
    return out


def _interleave(planes: list[np.ndarray], out: np.ndarray) -> None:
    """C planes (h, w) -> ``out`` (h, w, C), C-contiguous."""
    if len(planes) == 1:
        out[..., 0] = planes[0]
        return
    res = cv2.merge(planes, dst=out)
    if not np.shares_memory(res, out):  # pragma: no cover - OpenCV reallocated
        out[...] = res
