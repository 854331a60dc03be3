"""Edge-aware residual interpolation (EARI) of the polarization mosaic.

The polarization step of Morimatsu, Monno, Tanaka and Okutomi, "Monochrome and
color polarization demosaicking using edge-aware residual interpolation"
(ICIP 2020; the colour version in IEEE Access 2021), written here from the
paper's description and the authors' public MATLAB code
(github.com/ymonno/EARI-Polarization-Demosaicking, ``EARI.m``,
``residual_interpolation.m``, ``guidedfilter_MLRI_wei.m``) as vectorized
OpenCV float32 operations.

Input: for each colour c a *colour-complete polarization mosaic* ``m`` (H, W):
every pixel holds its own polarizer angle's value of colour c. For a
monochrome sensor that is the raw mosaic; for a colour sensor the Bayer image
of each angle is first colour-interpolated at half resolution (in the paper
with residual-interpolation Bayer demosaicking; here with pmvir's bilinear
colour step, :func:`pmvir.polarization.demosaic.demosaic`), and the four
angles' colour images are interleaved back onto the mosaic grid.

Per colour:

1. **Edge-aware guide** (the densest "channel": all four angles). Four
   directional estimates of the four-angle mean intensity, each the mean of a
   2x3 (or 3x2) window holding every angle once, half a pixel north, south,
   west and east of the pixel (``[1, 2, 1] / 4`` across, mean of two rows or
   columns along). Each is weighted by ``1 / (d + eps)``, where ``d`` is the
   mean, over a 5x3 window on that side, of the *polarization-invariant*
   directional difference ``|detail(row r - 1) - detail(row r)|`` with
   ``detail = centre - mean of the two row neighbours`` (for any physical
   polarization, ``I0 + I90 = I45 + I135``, this vanishes on flat fields and
   responds to intensity edges only). So the guide interpolates along edges,
   not across them. The weights are computed once, from the sum of the
   colours' mosaics, and shared by the colours (the authors compute them per
   colour; edges are mostly common to the colours, and this saves two thirds
   of the guide's cost).
2. **Tentative estimate** of each angle (minimized-Laplacian residual
   interpolation, Kiku et al. 2016): on the angle's own lattice (every second
   pixel in both directions) the samples ``R`` are fitted as ``a G + b`` per
   (2r + 1)^2 lattice window, with the slope from the lattice Laplacians
   ``a = sum(lap(G) lap(R)) / (sum(lap(G)^2) + eps_a)`` (robust to the
   offsets between angles) and ``b = mean(R) - a mean(G)``; ``a`` and ``b`` are
   averaged over the windows containing each lattice point (the authors'
   weighted average, by the inverse squared fitting error floored at 0.01 on
   [0, 1] data, is this plain mean wherever a window's RMS fitting error is
   below 0.1 of full scale, i.e. almost everywhere).
3. **Residuals** ``R - (a G + b)`` at the samples are interpolated bilinearly
   (as in the authors' code) and added to the full-resolution tentative image
   ``a G + b``, with ``a`` and ``b`` themselves upsampled bilinearly from
   the lattice (the fast guided filter's shortcut; the authors compute them at
   every pixel). Every sample stays at its own pixel.

Exactness: constant fields come back exactly (every Laplacian is 0, so the
tentative image is the window mean and the residual 0). On linear fields
the residual is 0 to within second-order terms of the slope's variation.

Reach (Chebyshev, full-resolution pixels, monochrome): guide 3, lattice
Laplacian 2, two box passes of 2r each, bilinear upsampling 1:
``4r + 6`` (:data:`EARI_REACH`); the bilinear colour step adds 2 (a bound:
the extremes of the chain do not line up, 14-15 px measured of 16).
"""

from __future__ import annotations

import cv2
import numpy as np

from pmvir.polarization.lattice import column_phases, interleave2, pair_means, upsample2_phases

#: Window half-width r of the residual fit, in lattice steps (2 full-resolution pixels):
#: (2r + 1)^2 lattice samples, about the authors' 11x11 full-resolution window for r = 2.
EARI_RADIUS = 2
#: Floor added to the directional differences before weighting (normalized intensity units).
EARI_EPS = 1e-4
#: Ridge on the Laplacian fit's slope (squared Laplacian units): keeps the slope at 0, not
#: a ratio of rounding errors, where neither the guide nor the samples curve.
EARI_EPS_SLOPE = 1e-8
#: Chebyshev reach of the monochrome method (guide 3, Laplacian 2, two boxes 2r each, upsampling 1).
EARI_REACH = 4 * EARI_RADIUS + 6

_REPLICATE = cv2.BORDER_REPLICATE
_SMOOTH = np.array([[0.25, 0.5, 0.25]], dtype=np.float32)
_DETAIL = np.array([[-0.5, 1.0, -0.5]], dtype=np.float32)
_LAPLACIAN = np.array([[0, -1, 0], [-1, 4, -1], [0, -1, 0]], dtype=np.float32)


def directional_weights(m: np.ndarray, *, eps: float = EARI_EPS) -> list[np.ndarray]:
    """EARI's normalized weights of the north, south, west and east intensity estimates.

    Args:
        m: colour-complete polarization mosaic (H, W) float32 (every pixel its
            own angle's value; for a colour sensor the sum over colours),
            normalized intensity units.
        eps: floor added to each direction's mean difference before taking
            its reciprocal as the weight.

    Returns:
        Four (H, W) float32 weights (north, south, west, east) summing to 1.
    """
    h, w = m.shape
    weights = []
    for axis in (0, 1):
        detail = cv2.filter2D(m, -1, _DETAIL if axis == 0 else _DETAIL.T, borderType=_REPLICATE)
        # |detail[k - 1] - detail[k]| between neighbouring rows (axis 0) or columns (axis 1), at
        # offset 3 in a buffer with zero padding (the replicated border's difference) on both sides
        if axis == 0:
            d = np.zeros((h + 5, w), np.float32)
            cv2.absdiff(detail[:-1], detail[1:], dst=d[3 : h + 2])
            ksize = (5, 3)  # (width, height): 5 across the direction, 3 along it
        else:
            d = np.zeros((h, w + 5), np.float32)
            cv2.absdiff(detail[:, :-1], detail[:, 1:], dst=d[:, 3 : w + 2])
            ksize = (3, 5)
        s = np.add(cv2.boxFilter(d, -1, ksize, borderType=cv2.BORDER_CONSTANT), np.float32(eps))
        # mean difference over the 3 rows (columns) on the near and on the far side of the pixel
        near, far = (s[1 : h + 1], s[4 : h + 4]) if axis == 0 else (s[:, 1 : w + 1], s[:, 4 : w + 4])
        weights += [cv2.divide(1.0, near), cv2.divide(1.0, far)]
    inv_total = cv2.divide(1.0, cv2.add(cv2.add(weights[0], weights[1]), cv2.add(weights[2], weights[3])))
    return [cv2.multiply(wt, inv_total) for wt in weights]


def edge_aware_guide(m: np.ndarray, weights: list[np.ndarray]) -> np.ndarray:
    """EARI's guide: the four-angle mean intensity, interpolated along edges.

    Args:
        m: colour-complete polarization mosaic of one colour, (H, W) float32.
        weights: :func:`directional_weights` (north, south, west, east).

    Returns:
        (H, W) float32, the estimated mean of the four angles at every pixel.
    """
    h, w = m.shape
    across = cv2.filter2D(m, -1, _SMOOTH, borderType=_REPLICATE)  # [1 2 1]/4 along rows
    down = cv2.filter2D(m, -1, _SMOOTH.T, borderType=_REPLICATE)
    # 2x3 means centred half a pixel up/down (rows) and 3x2 means left/right (columns)
    rows = pair_means(across, 0)  # (h + 1, w): rows[k] = mean of across[k - 1], across[k]
    cols = pair_means(down, 1)
    estimates = (rows[:h], rows[1:], cols[:, :w], cols[:, 1:])  # north, south, west, east
    guide = cv2.multiply(weights[0], estimates[0])
    for wt, est in zip(weights[1:], estimates[1:], strict=True):
        cv2.add(guide, cv2.multiply(wt, est), dst=guide)
    return guide


def residual_interpolation(
    samples: np.ndarray,
    guide_phases: list[np.ndarray],
    dy: int,
    dx: int,
    out: np.ndarray,
    *,
    radius: int = EARI_RADIUS,
    eps_slope: float = EARI_EPS_SLOPE,
) -> None:
    """One angle at full resolution from its lattice samples and the guide (EARI steps 2-3).

    Args:
        samples: the angle's samples (h, w) float32, ``m[dy::2, dx::2]`` of the
            colour-complete mosaic m (rows may be strided).
        guide_phases: the guide's four phases ``guide[r::2, s::2]`` in the order
            (0, 0), (0, 1), (1, 0), (1, 1), (h, w) float32 each (rows may be strided).
        dy, dx: the angle's position in the 2x2 polarizer block.
        out: (2h, 2w) float32 plane, C-contiguous, overwritten with the angle's
            intensity at every pixel (its own samples unchanged).
        radius: window half-width of the fit, in lattice steps.
        eps_slope: ridge on the Laplacian slope.
    """
    size = (2 * radius + 1, 2 * radius + 1)

    def box(x: np.ndarray) -> np.ndarray:
        return cv2.boxFilter(x, -1, size, borderType=_REPLICATE)

    g = guide_phases[2 * dy + dx]
    lap_r = cv2.filter2D(samples, -1, _LAPLACIAN, borderType=_REPLICATE)
    lap_g = cv2.filter2D(g, -1, _LAPLACIAN, borderType=_REPLICATE)
    num = box(cv2.multiply(lap_g, lap_r))
    den = box(cv2.multiply(lap_g, lap_g))
    den += np.float32(eps_slope)
    a = cv2.divide(num, den)
    b = cv2.subtract(box(samples), cv2.multiply(a, box(g)))
    a, b = box(a), box(b)
    # tentative a g + b plus the residual R - (a g + b) at the samples = R - a g + (a g at full resolution),
    # with a and the offset R - a g upsampled bilinearly; evaluated phase by phase, the samples' own as is
    offset = cv2.subtract(samples, cv2.multiply(a, g))
    slopes = upsample2_phases(a, dy, dx)
    offsets = upsample2_phases(offset, dy, dx)
    phases = [
        samples if k == 2 * dy + dx else cv2.add(offsets[k], cv2.multiply(slopes[k], guide_phases[k]))
        for k in range(4)
    ]
    interleave2(phases[0], phases[1], phases[2], phases[3], out)


def eari_polarization(mosaics: np.ndarray, block: np.ndarray, planes: np.ndarray, *,
                      radius: int = EARI_RADIUS, eps: float = EARI_EPS) -> None:
    """Every angle of every colour at full resolution by EARI.

    Args:
        mosaics: (C, H, W) float32 colour-complete polarization mosaics, H, W even.
        block: (2, 2) int, the angle index (0..3, ``ANGLES_DEG`` order) of each
            pixel of the 2x2 polarizer block.
        planes: (4, C, H, W) float32 output, overwritten.
        radius, eps: :func:`residual_interpolation`'s window and
            :func:`edge_aware_guide`'s floor.
    """
    if mosaics.ndim != 3 or mosaics.dtype != np.float32 or mosaics.shape[1] % 2 or mosaics.shape[2] % 2:
        raise ValueError(f"expected (C, H, W) float32 mosaics with H, W even, got {mosaics.shape} {mosaics.dtype}")
    if planes.shape != (4, *mosaics.shape):
        raise ValueError(f"expected (4, C, H, W) = {(4, *mosaics.shape)} planes, got {planes.shape}")
    if radius < 1:
        raise ValueError(f"need radius >= 1, got {radius}")
    luma = mosaics[0] if len(mosaics) == 1 else cv2.add(cv2.add(mosaics[0], mosaics[1]), mosaics[2])
    weights = directional_weights(luma, eps=eps * len(mosaics))
    for c, m in enumerate(mosaics):
        columns = column_phases(m, 2)
        guide_columns = column_phases(edge_aware_guide(m, weights), 2)
        guide_phases = [guide_columns[s][r::2] for r in range(2) for s in range(2)]
        for dy in range(2):
            for dx in range(2):
                residual_interpolation(columns[dx][dy::2], guide_phases, dy, dx, planes[block[dy, dx], c],
                                       radius=radius)

