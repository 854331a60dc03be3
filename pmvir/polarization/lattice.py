"""Lattice resampling shared by the demosaicing methods.

A polarization mosaic is four interleaved lattices (every second pixel in
both directions), and a colour one sixteen (every fourth). These helpers split
an image into its column phases, interleave four half-resolution planes back
onto the full grid, and upsample a lattice 2x bilinearly *registered*: each
lattice sample stays at its own pixel and the pixels between get the mean of
the two (edge) or four (diagonal) nearest samples, so constant and linear
fields come back exactly away from the border. All float32, on OpenCV's
threaded per-pixel operations.
"""

from __future__ import annotations

import cv2
import numpy as np

#: Rows per strip of the strip-wise full-resolution passes (the guided demosaic's last pass,
#: :class:`pmvir.polarization.stokes.PolarizationWriter`), even: 12 strips of 32 x 2448 float32
#: and the temporaries fit in the CPU cache, so each full-resolution plane is read from memory once.
STRIP_ROWS = 32


def column_phases(image: np.ndarray, period: int) -> list[np.ndarray]:
    """The ``period`` column phases of an image: ``out[k] == image[:, k::period]``, contiguous."""
    h, w = image.shape
    return list(cv2.split(np.ascontiguousarray(image).reshape(h, w // period, period)))


def interleave2(p00: np.ndarray, p01: np.ndarray, p10: np.ndarray, p11: np.ndarray,
                 out: np.ndarray) -> None:
    """Write ``out[r::2, s::2] = p_rs`` for four (h, w) planes; out is a contiguous (2h, 2w) plane."""
    h, w = p00.shape
    quad = out.reshape(h, 2, w, 2)
    for r, (left, right) in enumerate(((p00, p01), (p10, p11))):
        res = cv2.merge([left, right], dst=quad[:, r])
        if not np.shares_memory(res, out):  # pragma: no cover - OpenCV reallocated
            quad[:, r] = res


def pair_means(q: np.ndarray, axis: int) -> np.ndarray:
    """Means of neighbouring samples along ``axis``, edge samples repeated.

    For q of shape (h, w) and axis 1 returns (h, w + 1) with
    ``out[:, k] = (q[:, k - 1] + q[:, k]) / 2`` for 0 < k < w, ``out[:, 0] = q[:, 0]``
    and ``out[:, w] = q[:, w - 1]``; axis 0 likewise on rows, (h + 1, w).
    """
    h, w = q.shape
    if axis == 1:
        out = np.empty((h, w + 1), dtype=np.float32)
        if w > 1:
            cv2.addWeighted(q[:, :-1], 0.5, q[:, 1:], 0.5, 0.0, dst=out[:, 1:w])
        out[:, 0] = q[:, 0]
        out[:, w] = q[:, w - 1]
    else:
        out = np.empty((h + 1, w), dtype=np.float32)
        if h > 1:
            cv2.addWeighted(q[:-1], 0.5, q[1:], 0.5, 0.0, dst=out[1:h])
        out[0] = q[0]
        out[h] = q[h - 1]
    return out


def upsample2(q: np.ndarray, oy: int, ox: int, out: np.ndarray) -> None:
    """Bilinear 2x upsampling of a lattice, registered: ``q[i, j]`` is ``out[2i + oy, 2j + ox]``.

    Args:
        q: lattice samples (h, w), float32 (rows may be strided).
        oy, ox: the lattice's row / column phase in ``out`` (0 or 1).
        out: contiguous (2h, 2w) float32 plane, overwritten. Pixels beyond the
            outermost lattice rows/columns repeat the edge values.
    """
    interleave2(*upsample2_phases(q, oy, ox), out)


def upsample2_phases(q: np.ndarray, oy: int, ox: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`upsample2`'s result as its four phases ``(p00, p01, p10, p11)``, ``p_rs = out[r::2, s::2]``.

    The phase ``(oy, ox)`` is ``q`` itself; the others are (h, w) float32 views of new arrays.
    """
    h, w = q.shape
    horiz = pair_means(q, 1)[:, 1 - ox : 1 - ox + w]
    vert = pair_means(q, 0)[1 - oy : 1 - oy + h]
    diag = pair_means(vert, 1)[:, 1 - ox : 1 - ox + w]
    rows_on = (q, horiz) if ox == 0 else (horiz, q)
    rows_off = (vert, diag) if ox == 0 else (diag, vert)
    return (*rows_on, *rows_off) if oy == 0 else (*rows_off, *rows_on)


def quad_means(q: np.ndarray, oy: int, ox: int) -> np.ndarray:
    """The 2x2-block means of :func:`upsample2`'s result, from the lattice alone.

    ``out[i, j]`` is the mean of ``upsample2(q, oy, ox)[2i : 2i + 2, 2j : 2j + 2]``: along each
    axis the block holds the sample and the mean of it and its neighbour on the far side of the
    phase, so the block mean is ``3/4 q[i] + 1/4 q[i + 1]`` (phase 0) or ``1/4 q[i - 1] + 3/4 q[i]``
    (phase 1), edge samples repeated. One separable filter on the (h, w) lattice instead of a
    pass over the (2h, 2w) plane.

    Args:
        q: lattice samples (h, w), float32.
        oy, ox: the lattice's row / column phase, as for :func:`upsample2`.

    Returns:
        (h, w) float32.
    """
    kx, ky = (np.array([[0.75, 0.25]] if o == 0 else [[0.25, 0.75]], dtype=np.float32) for o in (ox, oy))
    return cv2.sepFilter2D(q, cv2.CV_32F, kx, ky, anchor=(ox, oy), borderType=cv2.BORDER_REPLICATE)
