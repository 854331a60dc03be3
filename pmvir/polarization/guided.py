"""Guided polarization demosaicing: sharp intensity, polarization from a guided filter.

Why: in a bilinear demosaic every polarizer angle is interpolated from its own
lattice (every second pixel, and every fourth of one colour), so intensity
texture reaches the four angles at different sub-pixel offsets:
``s1 = I0 - I90`` and ``s2 = I45 - I135`` pick up a difference of two
interpolations of the *intensity* (false polarization), and each sample's noise
goes straight into them. On real surfaces what varies at pixel scale is mostly
the intensity (albedo, shading, and in a path-traced render its Monte Carlo
noise); the normalized Stokes vector ``(s1, s2) / s0`` (DoP and AoP) follows the
surface normal and is smooth. The intensity-correlation idea of the
polarization-demosaicing literature (Zhang et al. 2016, "Image interpolation for
division of focal plane polarimeters with intensity correlation"; the guided,
edge-aware residual interpolation of Morimatsu et al., ICIP 2020 / IEEE Access
2021) uses that: keep the intensity sharp and estimate the polarization relative
to it, with a guided filter (He et al. 2013) whose guide is the intensity.

Per colour c:

1. bilinear demosaic (:func:`pmvir.polarization.demosaic.demosaic`, method
   ``"bilinear"``): ``I_k`` for k = 0, 45, 90, 135 degrees, and from them
   ``g = I0 + I45 + I90 + I135`` (= 2 s0), ``s1 = I0 - I90``, ``s2 = I45 - I135``;
2. ``g``, ``s1``, ``s2`` are averaged over 2x2 pixels (half resolution: the fast
   guided filter of He & Sun 2015);
3. in every (2r + 1)^2 window of the half-resolution image, ``s_i`` is fitted
   as ``a g + b`` (least squares), with ``a`` pulled toward the window's
   intensity-weighted polarization ``q = mean(s_i) / mean(g)`` by a ridge term
   ``eps = (tau mean(g))^2``:
   ``a = (cov(g, s_i) + eps q) / (var(g) + eps)``, ``b = mean(s_i) - a mean(g)``.
   Where the intensity is flat ``a -> q`` and ``b -> 0``: ``s_i = q g``, the
   polarization ratio of the window times the pixel's own intensity (noise and
   false polarization averaged out, texture kept). Where a window straddles
   an edge between two differently polarized regions (an occluding contour, a
   highlight), the fit passes through both, as a guided filter does, instead of
   mixing them;
4. ``a`` and ``b`` are averaged over the windows that contain each pixel,
   each window weighted by the inverse of its mean squared fitting error
   (``s1`` and ``s2`` together), as in the weighted averaging of the
   residual-interpolation code of Monno, Kiku et al. that Morimatsu et al.'s
   EARI uses (``guidedfilter_MLRI_wei.m``). The error is floored at
   ``k`` (3) times the frame's median error per unit intensity (a noise
   estimate, since shot noise grows with intensity) times the window's
   intensity (at least the dark threshold), so windows that fit to within the noise count equally and only
   windows that straddle a change of polarization (a contour, a highlight's
   edge, where a single line cannot fit) lose weight. Then ``a`` and ``b`` are
   brought back to full resolution (bilinear, the registration of
   ``cv2.resize``), and ``s_i' = a g + b`` at full resolution, with the
   full-resolution ``g``;
5. back to intensities, keeping each pair's bilinear mean: ``I0, I90 =
   (I0 + I90) / 2 +- s1' / 2`` and ``I45, I135 = (I45 + I135) / 2 +- s2' / 2``;
   so ``s0`` is the bilinear one, unchanged (and so is the small mismatch
   ``(I0 + I90) - (I45 + I135)``, zero for any physical field).

Exactness: on affine fields (every channel linear in x, y) the window
statistics ``cov``, ``var`` are the same in every window and the box and
2x2-mean/bilinear resampling steps reproduce affine fields, so ``s_i' = s_i``:
constant and linear fields come back exactly away from the border (up to the
ridge term's ``q``, which varies across windows only as the ratio of two
affine fields does: a second-order effect, below 1e-5 in the tests).

Reach: the bilinear step's, widened by the 2x2 mean, two (2r + 1)^2 box passes
at half resolution and the bilinear upsampling: 12 px (mono) and 13 px (colour)
for r = 2 (:data:`GUIDED_REACH`, checked against the measured impulse response).
Saturated samples invalidate that neighbourhood (``saturation_footprint``).
The weights' floor is one number per frame (a median over all windows): one
sample moves it by at most a rank, far below 1e-4 in any output on frames of
128x128 and up (the impulse-response test).

Implementation: the half-resolution statistics, fits and weighted means are
computed in strips of 32 rows (each box sum over the strip plus ``r`` rows of
margin, cropped), and step 5 in strips of 32 full-resolution rows with the
coefficients upsampled per strip, so the temporaries stay in the CPU cache and
each full-resolution plane is read and written once; a caller can take each
finished strip at once (``on_strip``, what decoding does for the Stokes
quantities). The demosaicing hands over the 2x2 means of step 2 from its
half-resolution lattices (:func:`pmvir.polarization.lattice.quad_means`).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from pmvir.polarization.lattice import STRIP_ROWS

#: Window half-width r at half resolution ((2r + 1)^2 half-resolution pixels). On the Mitsuba
#: frames of bench/demosaic.py r = 2 measured clearly better than r = 1 at 1224x1024 and about
#: equal at 612x512; r = 3 blurs the polarization of small objects (README, Decoding).
GUIDED_RADIUS = 2
#: Ridge strength, relative to the window's mean intensity (0.1 measured best of 0.03 .. 3).
GUIDED_TAU = 0.1
#: Chebyshev reach, full-resolution pixels, of the whole method on a monochrome sensor (bilinear,
#: 2x2 mean, two box passes of radius r at half resolution, bilinear upsampling); a colour sensor
#: adds 1. Checked against the measured impulse response (tests/polarization/test_demosaic.py).
GUIDED_REACH = 4 * GUIDED_RADIUS + 4

#: Windows are averaged with weights 1 / max(fitting error, k x the frame's median fitting error
#: per unit intensity x the window's intensity): k = 0.01 .. 4 all measured AoP 0.69x, DoP 0.75x
#: polanalyser's on the Mitsuba knot frames (0.72x / 0.79x unweighted); k <= 1 cost 3% AoP on the
#: noisy synthetic texture of tests/polarization/test_guided.py, k >= 2 nothing (< 0.2%).
GUIDED_WEIGHT_K = 3.0

#: mean(g) at or below this (normalized units) gives zero polarization.
_EPS = 1e-6
#: Smallest weight floor per unit intensity (normalized units), for noise-free frames.
_WEIGHT_FLOOR_MIN = 1e-7


def guided_polarization(planes: np.ndarray, *, radius: int = GUIDED_RADIUS, tau: float = GUIDED_TAU,
                        weight_k: float | None = GUIDED_WEIGHT_K, quads: list[np.ndarray] | None = None,
                        on_strip: Callable[[slice], None] | None = None) -> None:
    """Replace the polarization of bilinear-demosaiced planes by the guided estimate, in place.

    Args:
        planes: planar intensities (4, C, H, W) float32, angle axis 0, 45, 90,
            135 degrees, H and W even (the storage behind :func:`demosaic`'s
            result); overwritten.
        radius: window half-width r at half resolution, >= 1.
        tau: ridge strength (> 0) pulling each window's fit toward its
            intensity-weighted polarization ratio.
        weight_k: average each pixel's windows weighted by their inverse fitting
            error, floored at ``weight_k`` times the frame's typical (median)
            error per unit intensity (step 4 of the module docstring), or None
            for the plain mean of the windows.
        quads: optional, each angle's colour sum of the planes' 2x2 means, four
            (H/2, W/2) float32 arrays (what the demosaicing computes more cheaply
            from its half-resolution lattices, :func:`pmvir.polarization.lattice.quad_means`);
            taken from ``planes`` when None.
        on_strip: optional, called with consecutive row ranges (slices) covering
            the frame, each as soon as those rows of ``planes`` are final (so that
            the caller can use them while they are in the CPU cache).
    """
    if planes.ndim != 4 or planes.shape[0] != 4 or planes.dtype != np.float32:
        raise ValueError(f"expected (4, C, H, W) float32 planes, got {planes.shape} {planes.dtype}")
    n_col, h, w = planes.shape[1:]
    if h % 2 or w % 2:
        raise ValueError(f"expected an even-sized image, got {w}x{h}")
    if radius < 1 or not tau > 0 or (weight_k is not None and not weight_k > 0):
        raise ValueError(f"need radius >= 1, tau > 0 and weight_k > 0 or None, got {radius}, {tau}, {weight_k}")
    if quads is None:
        quads = [_half_colour_sum(planes[k], (w // 2, h // 2)) for k in range(4)]
    elif len(quads) != 4 or any(q.shape != (h // 2, w // 2) or q.dtype != np.float32 for q in quads):
        raise ValueError(f"expected four ({h // 2}, {w // 2}) float32 quads, got {[q.shape for q in quads]}")
    # colour sums at half resolution (2x2 means): g = C * 2 s0, and s1, s2
    gh = cv2.add(cv2.add(quads[0], quads[2]), cv2.add(quads[1], quads[3]))
    sh = (cv2.subtract(quads[0], quads[2]), cv2.subtract(quads[1], quads[3]))
    fit = _WindowFits(gh, sh, radius=radius, tau=tau, n_col=n_col)
    # half resolution; per colour c: s_c' = A g_c + B / C, so that the colour sum is A g + B
    coeffs = [np.empty_like(gh) for _ in range(4)]
    if weight_k is None:
        fit.plain_means(1.0 / n_col, coeffs)
    else:
        per_intensity = np.concatenate(fit.per_intensity)
        typical = float(np.median(per_intensity)) if per_intensity.size else 0.0
        fit.weighted_means(max(weight_k * typical, _WEIGHT_FLOOR_MIN), 1.0 / n_col, coeffs)
    _apply_coefficients(planes, coeffs, on_strip)


#: Half-resolution rows per strip of :class:`_WindowFits` (even, so that strips keep the global
#: row parity); each strip's temporaries are small and stay in the CPU cache.
_HALF_STRIP_ROWS = 32


class _WindowFits:
    """Steps 3 and 4 of the module docstring, in strips of half-resolution rows.

    Box sums need ``radius`` rows beyond a strip: each is taken over the strip's rows plus that
    margin (OpenCV replicates the border at the margin's outer edge, which is the image's own
    edge only where the image ends) and cropped to the strip. Holds, for the whole
    half-resolution frame: the fits ``a``, ``b`` of s1 and s2, ``mean_g``, the fitting error
    ``mse`` (s1 and s2 together) and the error per unit intensity of every 4th lit window
    (``per_intensity``, one array per strip).

    Args:
        gh: colour sum of the four angles' 2x2 means, (h, w) float32.
        sh: the half-resolution ``s1``, ``s2`` (I0 - I90, I45 - I135), (h, w) float32 each.
        radius, tau: as for :func:`guided_polarization`.
        n_col: number of colours C (the dark threshold scales with it).
    """

    def __init__(self, gh: np.ndarray, sh: tuple[np.ndarray, np.ndarray], *, radius: int, tau: float,
                 n_col: int):
        self.size = (2 * radius + 1, 2 * radius + 1)
        self.strips = [
            (slice(y0, min(y0 + _HALF_STRIP_ROWS, gh.shape[0])),
             slice(max(y0 - radius, 0), min(y0 + _HALF_STRIP_ROWS + radius, gh.shape[0])))
            for y0 in range(0, gh.shape[0], _HALF_STRIP_ROWS)
        ]
        self.a = (np.empty_like(gh), np.empty_like(gh))
        self.b = (np.empty_like(gh), np.empty_like(gh))
        self.mean_g = np.empty_like(gh)
        self.mse = np.empty_like(gh)
        self.per_intensity: list[np.ndarray] = []
        self.dark = floor = 2.0 * n_col * _EPS
        for rows, margin in self.strips:
            g_m = gh[margin]
            mean_g = self.mean_g[rows]
            mean_g[...] = self.box(g_m, rows, margin)
            var_g = cv2.subtract(self.box(cv2.multiply(g_m, g_m), rows, margin), cv2.multiply(mean_g, mean_g))
            eps = cv2.multiply(mean_g, mean_g, scale=tau * tau)
            _, lit = cv2.threshold(mean_g, floor, 1.0, cv2.THRESH_BINARY)  # 0 where dark
            inv_mean_g = cv2.divide(lit, np.maximum(mean_g, np.float32(floor)))
            np.maximum(var_g, 0.0, out=var_g)  # rounding can make it slightly negative
            den = cv2.add(var_g, eps)
            inv_den = np.reciprocal(np.maximum(den, np.float32(1e-30), out=den))
            mse = self.mse[rows]
            mse[...] = 0.0
            for k in range(2):
                s_m = sh[k][margin]
                mean_s = self.box(s_m, rows, margin)
                cov = cv2.subtract(self.box(cv2.multiply(g_m, s_m), rows, margin), cv2.multiply(mean_g, mean_s))
                q = cv2.multiply(mean_s, inv_mean_g)
                a = self.a[k][rows]
                a[...] = cv2.multiply(cv2.multiply(cv2.add(cov, cv2.multiply(eps, q)), inv_den), lit)
                self.b[k][rows] = cv2.subtract(cv2.multiply(mean_s, lit), cv2.multiply(a, mean_g))
                # mean((s - a g - b)^2) = var(s) - 2 a cov(g, s) + a^2 var(g)
                var_s = cv2.subtract(self.box(cv2.multiply(s_m, s_m), rows, margin), cv2.multiply(mean_s, mean_s))
                mse += cv2.subtract(var_s, cv2.multiply(a, cov, scale=2.0))
                mse += cv2.multiply(cv2.multiply(a, a), var_g)
            # every 4th window (strips start on even rows, so these are the frame's even rows)
            self.per_intensity.append(cv2.multiply(mse, inv_mean_g)[::2, ::2][lit[::2, ::2] > 0])

    def box(self, x: np.ndarray, rows: slice, margin: slice) -> np.ndarray:
        """Box means (border replicated) of x, given on rows ``margin``, at rows ``rows``."""
        full = cv2.boxFilter(x, -1, self.size, borderType=cv2.BORDER_REPLICATE)
        return full[rows.start - margin.start : rows.stop - margin.start]

    def plain_means(self, b_scale: float, coeffs: list[np.ndarray]) -> None:
        """Step 4 unweighted: ``coeffs`` = A1, B1 b_scale, A2, B2 b_scale, plain window means; overwritten."""
        for rows, margin in self.strips:
            for k in range(2):
                coeffs[2 * k][rows] = self.box(self.a[k][margin], rows, margin)
                np.multiply(self.box(self.b[k][margin], rows, margin), np.float32(b_scale), out=coeffs[2 * k + 1][rows])

    def weighted_means(self, floor_per_intensity: float, b_scale: float, coeffs: list[np.ndarray]) -> None:
        """Step 4: ``coeffs`` = A1, B1 b_scale, A2, B2 b_scale, window means weighted by 1 / max(error, floor).

        Args:
            floor_per_intensity: the error floor per unit of the window's mean intensity.
            b_scale: factor on the B coefficients (1 / C).
            coeffs: four (h, w) float32 arrays, overwritten.
        """
        for rows, margin in self.strips:
            # the floor's intensity is at least the dark threshold: a dark, noise-free window's weight
            # stays ~1e5 x a lit one's, not 1e20 (whose rounding in OpenCV's running box sums, double,
            # spread ~1e4 of error down the columns below a dark area, ~100x the lit windows' weights)
            floor_img = np.maximum(self.mean_g[margin], np.float32(self.dark))
            floor_img *= np.float32(floor_per_intensity)
            weight = cv2.divide(1.0, cv2.max(self.mse[margin], floor_img))
            inv_weight_sum = cv2.divide(1.0, self.box(weight, rows, margin))
            for k in range(2):
                cv2.multiply(self.box(cv2.multiply(self.a[k][margin], weight), rows, margin), inv_weight_sum,
                             dst=coeffs[2 * k][rows])
                cv2.multiply(self.box(cv2.multiply(self.b[k][margin], weight), rows, margin), inv_weight_sum,
                             dst=coeffs[2 * k + 1][rows], scale=b_scale)

def _apply_coefficients(planes: np.ndarray, coeffs: list[np.ndarray],
                        on_strip: Callable[[slice], None] | None) -> None:
    """Step 5 of the module docstring, in place, strip by strip (:data:`STRIP_ROWS`, even).

    Args:
        planes: (4, C, H, W) float32 bilinear intensities; overwritten.
        coeffs: half-resolution (H/2, W/2) float32 ``A1, B1 / C, A2, B2 / C`` of
            ``s1`` (I0 - I90) and ``s2`` (I45 - I135).
        on_strip: called with each strip's rows once they are final.
    """
    n_col, h, w = planes.shape[1:]
    rows = min(STRIP_ROWS, h)
    pair_sum = (np.empty((rows, w), np.float32), np.empty((rows, w), np.float32))
    g = np.empty((rows, w), np.float32)
    s_new = np.empty((rows, w), np.float32)
    for r0 in range(0, h, rows):
        r1 = min(r0 + rows, h)
        n = r1 - r0
        a1, b1, a2, b2 = (_upsample_rows(x, r0, r1, w) for x in coeffs)
        for c in range(n_col):
            i0, i45, i90, i135 = (planes[k, c, r0:r1] for k in range(4))
            total0, total1, g_c, s_c = pair_sum[0][:n], pair_sum[1][:n], g[:n], s_new[:n]
            cv2.add(i0, i90, dst=total0)  # the pair sums are kept
            cv2.add(i45, i135, dst=total1)
            cv2.add(total0, total1, dst=g_c)  # 2 s0 of colour c
            for plus, minus, total, a_full, b_full in ((i0, i90, total0, a1, b1), (i45, i135, total1, a2, b2)):
                cv2.multiply(a_full, g_c, dst=s_c)
                cv2.add(s_c, b_full, dst=s_c)
                cv2.addWeighted(total, 0.5, s_c, 0.5, 0.0, dst=plus)
                cv2.subtract(total, plus, dst=minus)
        if on_strip is not None:
            on_strip(slice(r0, r1))


def _upsample_rows(x: np.ndarray, r0: int, r1: int, w: int) -> np.ndarray:
    """Rows ``r0:r1`` (even bounds) of ``cv2.resize(x, (w, 2 x rows), INTER_LINEAR)``, computing only those.

    A 2x linear upsampling reads the source rows next to each output row's own: with one
    source row of margin on each side (where the image has one) the strip equals the whole
    image's rows.
    """
    lo, hi = max(r0 // 2 - 1, 0), min(r1 // 2 + 1, x.shape[0])
    up = cv2.resize(x[lo:hi], (w, 2 * (hi - lo)), interpolation=cv2.INTER_LINEAR)
    return up[r0 - 2 * lo : r1 - 2 * lo]


def _half_colour_sum(angle_planes: np.ndarray, half: tuple[int, int]) -> np.ndarray:
    """2x2 means of one angle's (C, H, W) planes, summed over colours: (H/2, W/2) float32."""
    total = cv2.resize(angle_planes[0], half, interpolation=cv2.INTER_AREA)
    for plane in angle_planes[1:]:
        cv2.add(total, cv2.resize(plane, half, interpolation=cv2.INTER_AREA), dst=total)
    return total
