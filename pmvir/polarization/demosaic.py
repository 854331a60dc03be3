"""Demosaicing a polarization mosaic to 4 angles x C colours at full resolution.

The method follows the paper (section 4.1): the samples of each polarizer angle
(one pixel of every 2x2 polarizer block) form a half-resolution image; for a
colour sensor that image is itself a Bayer mosaic with the layout's pattern,
because each 2x2 polarizer block sits under one colour filter. Each of those
four Bayer images is colour-interpolated, and each of the resulting
half-resolution planes is then interpolated back to full resolution
(polarization interpolation). A monochrome sensor needs only the second step.

Pixel registration: the samples of the angle at row ``dy``, column ``dx`` of
the 2x2 block sit at full-resolution pixels ``(2 i + dy, 2 j + dx)``. Every
upsampling here (:func:`pmvir.polarization.lattice.upsample2`) keeps each
lattice sample at its own pixel and fills the pixels between with the mean of the two (edge) or four (diagonal)
nearest samples, i.e. exact bilinear interpolation at the true sub-pixel
offsets; so a constant and a linear ramp come back exactly away from the image
border (within 2 pixels of the border, samples beyond it are taken to repeat
the outermost ones). The work is done with OpenCV's threaded per-pixel
operations (``addWeighted`` for the means, ``merge`` to interleave the four
phases) straight into the output planes.

Methods:

* ``"bilinear"``: bilinear colour interpolation of each angle's half-resolution
  Bayer image (red and blue: bilinear 2x upsampling of their quarter-resolution
  lattice; green: mean of the four edge neighbours), then bilinear polarization
  interpolation, all in float32.
* ``"edge-aware"``: OpenCV's edge-aware Bayer demosaicing
  (``COLOR_Bayer*2RGB_EA``) of each angle's image, on 16-bit data (the frame
  is mapped affinely onto 0..65535, so the quantization step is 1/65535 of the
  frame's range, 16 times finer than 12-bit data), then the same bilinear
  polarization interpolation in float32. Frames under 8 pixels high or wide
  (a 2x2 Bayer image per angle, which OpenCV mishandles) use bilinear.
* ``"guided"``: ``"bilinear"``, then the polarization (not the intensity)
  replaced by a guided-filter estimate with the intensity as guide
  (:mod:`pmvir.polarization.guided`): far less false polarization from
  texture and noise, one colour-mean polarization shared by the colours.
* ``"eari"``: Morimatsu et al.'s edge-aware residual interpolation
  (:mod:`pmvir.polarization.eari`): the bilinear colour step of each angle's
  Bayer image at half resolution, the four angles' colour images put back on
  the mosaic grid, then every angle of every colour from an edge-aware guide
  (all four angles) and a Laplacian-fitted tentative image plus the
  interpolated residuals. Keeps every sample (and its noise).
* ``"eari-guided"``: ``"eari"``, then the polarization replaced as in
  ``"guided"``.
* A monochrome layout has no colour step: ``"bilinear"`` and ``"edge-aware"``
  are the bilinear polarization interpolation.

OpenCV names a Bayer code after the second row's second and third pixels, so
its code for a pattern is "off by one" from the pattern's usual name: an
RGGB sensor is ``COLOR_BayerBG2RGB``. :data:`_CV_BAYER` holds the mapping
(checked by tests/polarization/test_demosaic.py).

Relation to polanalyser: ``polanalyser.demosaicing(raw, COLOR_PolarRGB)`` does
the same two bilinear steps on 8/16-bit integers (float input is rescaled to
uint16 first) and returns a list ``[I0, I45, I90, I135]`` of (H, W, 3) BGR
images. Its polarizer block is fixed to the IMX250MYR labels
``[[90, 45], [135, 0]]`` and its Bayer pattern to RGGB; its Stokes/AoLP
formulas (``calcLinearStokes``, ``cvtStokesToAoLP``) are the spec's. So for a
ccw-labelled IMX250MYR frame its ``I_k`` is our ``intensities[:, :, k, ::-1]``
(same angle order, colour axis reversed) and its AoLP is our AoP; for any
other block, Bayer pattern or a "cw" capture it would mislabel the angles,
which :class:`MosaicLayout` handles here.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Literal

import cv2
import numpy as np

from pmvir.errors import ConfigError, DTypeError, ShapeError
from pmvir.polarization.eari import EARI_REACH, eari_polarization
from pmvir.polarization.guided import GUIDED_REACH, guided_polarization
from pmvir.polarization.lattice import (
    STRIP_ROWS,
    column_phases,
    interleave2,
    pair_means,
    quad_means,
    upsample2,
)
from pmvir.polarization.layout import MosaicLayout

DemosaicMethod = Literal["bilinear", "edge-aware", "guided", "eari", "eari-guided"]
_METHODS: tuple[str, ...] = ("bilinear", "edge-aware", "guided", "eari", "eari-guided")

#: OpenCV Bayer conversion name for each pattern (pattern letters are the
#: colours at (0,0), (0,1), (1,0), (1,1)).
_CV_BAYER = {"RGGB": "BayerBG", "GRBG": "BayerGB", "BGGR": "BayerRG", "GBRG": "BayerGR"}

#: Chebyshev radius (full-resolution pixels) of the set of mosaic samples that
#: can influence one output pixel, per (colour, method). Used to dilate
#: saturation masks; tests check it against the measured impulse response.
#: Bilinear: 1 for the polarization step, plus 2 for the colour step. OpenCV's
#: edge-aware step measures 3 too; 4 is declared as a margin, since its code
#: paths depend on the image content.
_SUPPORT_RADIUS = {
    (False, "bilinear"): 1,
    (False, "edge-aware"): 1,
    (True, "bilinear"): 3,
    (True, "edge-aware"): 4,
    (False, "guided"): GUIDED_REACH,
    (True, "guided"): GUIDED_REACH + 1,
    (False, "eari"): EARI_REACH,
    (True, "eari"): EARI_REACH + 2,  # the bilinear colour step's 2 (a bound: 14-15 measured)
    # the guided step widens its input's reach by GUIDED_REACH - 1 (its own, without bilinear's 1)
    (False, "eari-guided"): EARI_REACH + GUIDED_REACH - 1,
    (True, "eari-guided"): EARI_REACH + GUIDED_REACH + 1,
}


#: OpenCV's Bayer demosaicing is wrong on 2x2 images: smaller frames fall back to bilinear.
_EA_MIN_SIZE = 8


def support_radius(layout: MosaicLayout, method: DemosaicMethod = "bilinear") -> int:
    """Chebyshev radius, in full-resolution pixels, of one output pixel's footprint.

    A mosaic sample farther than this (in rows or columns) from an output pixel
    does not change any of that pixel's 4 x C values.
    """
    _check_method(method)
    return _SUPPORT_RADIUS[(layout.is_colour, method)]


def saturation_footprint(
    saturated: np.ndarray, layout: MosaicLayout, *, method: DemosaicMethod = "bilinear"
) -> np.ndarray:
    """Output pixels whose demosaiced values used at least one saturated sample.

    Args:
        saturated: (H, W) bool, True where the raw sample is at or above the white level.
        layout, method: as given to :func:`demosaic`.

    Returns:
        (H, W) bool: ``saturated`` dilated by a (2r + 1) x (2r + 1) square,
        r = :func:`support_radius`.
    """
    if saturated.ndim != 2:
        raise ShapeError(f"expected an (H, W) saturation mask, got shape {saturated.shape}")
    r = support_radius(layout, method)
    kernel = np.ones((2 * r + 1, 2 * r + 1), dtype=np.uint8)
    grown = cv2.dilate(saturated.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return grown.astype(bool)


def demosaic(
    mosaic: np.ndarray,
    layout: MosaicLayout,
    *,
    method: DemosaicMethod = "bilinear",
    out: np.ndarray | None = None,
    on_strip: Callable[[slice], None] | None = None,
) -> np.ndarray:
    """Full-resolution intensities for every polarizer angle and colour.

    Args:
        mosaic: raw samples, shape (H, W), float32 in normalized units
            ((sample - black) / (white - black), exposure-divided); H and W whole
            multiples of ``layout.period``.
        layout: where each angle and colour filter sits.
        method: ``"bilinear"``, ``"edge-aware"``, ``"guided"``, ``"eari"`` or
            ``"eari-guided"`` (see the module docstring).
        out: optional array to write into and return, typically an earlier
            result of this function for a frame of the same size (saves
            allocating, and page-faulting, ~240 MB per 5-Mpixel colour frame).
            Must be (H, W, 4, C) float32 with planar storage, i.e.
            ``out.transpose(2, 3, 0, 1)`` C-contiguous.
        on_strip: optional, called with consecutive row ranges (slices, step 1)
            that cover the frame, each once those rows of the result are final;
            ``"guided"`` calls it during its last pass, while the rows are still
            in the CPU cache (:func:`pmvir.decode.decode_frame` computes the
            Stokes quantities there), the other methods at the end.

    Returns:
        Intensities, shape (H, W, 4, C), float32, angle axis in ``ANGLES_DEG``
        order (0, 45, 90, 135 degrees, ccw), colour axis R, G, B (C = 3) or a
        single channel (C = 1). The array is a transposed view of planar
        (4, C, H, W) storage: per-plane work is fast; ``np.ascontiguousarray``
        gives an (H, W, 4, C)-ordered copy if one is needed.

    Example:
        A uniform field, mosaicked then demosaicked, comes back unchanged:

        >>> from pmvir.polarization.layout import IMX250MYR, mosaic
        >>> field = np.broadcast_to(np.array([1.0, 0.5, 0.0, 0.5], np.float32)[:, None], (8, 8, 4, 3))
        >>> planes = demosaic(mosaic(field, IMX250MYR), IMX250MYR)
        >>> planes.shape, planes.dtype
        ((8, 8, 4, 3), dtype('float32'))
        >>> bool(np.allclose(planes, field))
        True
    """
    _check_method(method)
    if mosaic.ndim != 2:
        raise ShapeError(f"expected an (H, W) mosaic, got shape {mosaic.shape}")
    if mosaic.dtype != np.float32:
        raise DTypeError(f"expected a float32 mosaic, got {mosaic.dtype}")
    h, w = mosaic.shape
    layout.check_size(h, w)
    mosaic = np.ascontiguousarray(mosaic)
    planes = _planes_for(out, (4, layout.channels, h, w))
    quads = _first_step(mosaic, layout, method, planes)
    if method in ("guided", "eari-guided"):
        guided_polarization(planes, quads=quads, on_strip=on_strip)
    elif on_strip is not None:
        for r0 in range(0, h, STRIP_ROWS):
            on_strip(slice(r0, min(r0 + STRIP_ROWS, h)))
    return planes.transpose(2, 3, 0, 1)


def _first_step(mosaic: np.ndarray, layout: MosaicLayout, method: str, planes: np.ndarray) -> list[np.ndarray] | None:
    """Everything but the guided step, into planes (4, C, H, W).

    Returns, for ``"guided"``, each angle's colour sum of the planes' 2x2 means
    (H/2, W/2), taken from the half-resolution lattices; else None.
    """
    h, w = mosaic.shape
    block = layout.angle_index_block()
    quads: list[np.ndarray] | None = [np.empty(0)] * 4 if method == "guided" else None
    if method in ("eari", "eari-guided"):
        eari_polarization(_colour_complete_mosaic(mosaic, layout), block, planes)
    elif not layout.is_colour:
        columns = column_phases(mosaic, 2)
        for dy in range(2):
            for dx in range(2):
                upsample2(columns[dx][dy::2], dy, dx, planes[block[dy, dx], 0])
                if quads is not None:
                    quads[block[dy, dx]] = quad_means(columns[dx][dy::2], dy, dx)
    elif method != "edge-aware" or min(h, w) < _EA_MIN_SIZE:
        columns = column_phases(mosaic, 4)
        for dy in range(2):
            for dx in range(2):
                half = _bilinear_colour(columns, layout, dy, dx, planes[block[dy, dx]])
                if quads is not None:
                    quads[block[dy, dx]] = quad_means(cv2.add(cv2.add(half[0], half[1]), half[2]), dy, dx)
    else:
        _edge_aware_colour(mosaic, layout, planes)
    return quads


def _planes_for(out: np.ndarray | None, shape: tuple[int, int, int, int]) -> np.ndarray:
    """Planar (4, C, H, W) storage: fresh, or the storage behind ``out``."""
    if out is None:
        return np.empty(shape, dtype=np.float32)
    planes = out.transpose(2, 3, 0, 1)
    if planes.shape != shape or planes.dtype != np.float32 or not planes.flags.c_contiguous:
        raise ShapeError(
            f"out must be an (H, W, 4, C) = {shape[2:] + shape[:2]} float32 array with planar "
            f"storage (a previous demosaic result); got {out.shape} {out.dtype}"
        )
    return planes


def _check_method(method: str) -> None:
    if method not in _METHODS:
        raise ConfigError(f"method must be one of {', '.join(map(repr, _METHODS))}, got {method!r}")


def _bilinear_colour(columns: list[np.ndarray], layout: MosaicLayout, dy: int, dx: int,
                     out: np.ndarray) -> np.ndarray:
    """Bilinear Bayer + polarization interpolation of the angle at (dy, dx); out (3, H, W).

    Returns the half-resolution colour image (3, H/2, W/2) that was upsampled.
    """
    h4, w4 = columns[0].shape[0] // 4, columns[0].shape[1]
    half = np.empty((3, 2 * h4, 2 * w4), dtype=np.float32)
    _bilinear_bayer(columns, layout, dy, dx, half)
    for c in range(3):
        upsample2(half[c], dy, dx, out[c])
    return half


def _bilinear_bayer(columns: list[np.ndarray], layout: MosaicLayout, dy: int, dx: int,
                    half: np.ndarray) -> None:
    """Bilinear Bayer interpolation of the angle at (dy, dx) at half resolution; half (3, H/2, W/2)."""
    h4, w4 = columns[0].shape[0] // 4, columns[0].shape[1]
    colours = layout.colour_index_block()
    # quarter[by][bx]: the angle's samples under the Bayer block (by, bx), (H/4, W/4)
    quarter = [[columns[2 * bx + dx][2 * by + dy :: 4] for bx in range(2)] for by in range(2)]
    for c in (0, 2):
        (by, bx), = np.argwhere(colours == c)
        upsample2(quarter[by][bx], int(by), int(bx), half[c])
    # green: two diagonal lattices; the two other positions get the mean of
    # their four edge neighbours (two from each green lattice).
    filled = [row[:] for row in quarter]  # the green lattices as they are
    for by in range(2):
        for bx in range(2):
            if colours[by, bx] != 1:
                beside = quarter[by][1 - bx]  # green lattice in the same row
                above = quarter[1 - by][bx]  # green lattice in the same column
                horiz = pair_means(beside, 1)[:, bx : bx + w4]
                vert = pair_means(above, 0)[by : by + h4]
                filled[by][bx] = cv2.addWeighted(horiz, 0.5, vert, 0.5, 0.0)
    interleave2(filled[0][0], filled[0][1], filled[1][0], filled[1][1], half[1])


def _colour_complete_mosaic(mosaic: np.ndarray, layout: MosaicLayout) -> np.ndarray:
    """(C, H, W): at every pixel its own polarizer angle's value of each colour.

    Monochrome: the mosaic itself. Colour: each angle's half-resolution Bayer
    image, bilinearly colour-interpolated, put back at the angle's pixels.
    """
    h, w = mosaic.shape
    if not layout.is_colour:
        return mosaic[None]
    columns = column_phases(mosaic, 4)
    halves = np.empty((2, 2, 3, h // 2, w // 2), dtype=np.float32)
    for dy in range(2):
        for dx in range(2):
            _bilinear_bayer(columns, layout, dy, dx, halves[dy, dx])
    out = np.empty((3, h, w), dtype=np.float32)
    for c in range(3):
        interleave2(halves[0, 0, c], halves[0, 1, c], halves[1, 0, c], halves[1, 1, c], out[c])
    return out


def _edge_aware_colour(mosaic: np.ndarray, layout: MosaicLayout, planes: np.ndarray) -> None:
    """OpenCV edge-aware Bayer demosaicing of each angle's image, then bilinear upsampling."""
    if layout.bayer is None:
        raise ConfigError("edge-aware demosaicing needs a colour (Bayer) layout")
    lo, hi, _, _ = cv2.minMaxLoc(mosaic)
    span = hi - lo
    scale = 65535.0 / span if span > 0 else 1.0
    # lo -> 0, hi -> 65535, rounded (one threaded pass)
    q16 = cv2.normalize(  # type: ignore[call-overload, unused-ignore]  # OpenCV 5.0 stubs refuse dst=None
        mosaic, None, 0, 65535, cv2.NORM_MINMAX, dtype=cv2.CV_16U
    )
    columns = column_phases(q16, 2)
    code = getattr(cv2, f"COLOR_{_CV_BAYER[layout.bayer]}2RGB_EA")
    block = layout.angle_index_block()
    for dy in range(2):
        for dx in range(2):
            # cvtColor on a row-strided view gave different results (OpenCV 5.0): pass a copy
            rgb = cv2.cvtColor(np.ascontiguousarray(columns[dx][dy::2]), code)
            for c, plane in enumerate(cv2.split(rgb)):
                f = cv2.addWeighted(plane, 1.0 / scale, plane, 0.0, lo, dtype=cv2.CV_32F)
                upsample2(f, dy, dx, planes[block[dy, dx], c])
