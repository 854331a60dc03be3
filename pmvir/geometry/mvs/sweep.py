"""Dense multi-view stereo on the CPU: per-view depth maps by plane sweeping (paper section 4.2).

pycolmap's PatchMatch stereo needs CUDA; this module is the CPU path. For each
reference view:

1. **Neighbours** (:func:`select_neighbours`): the views that share the most
   sparse points with it at a triangulation angle near 15 degrees (within
   ``[min_angle, max_angle]``).
2. **Depth range** (:func:`view_depth_range`): the 1st to 99th percentile of the
   depths of the sparse points that project into the view (and its mask),
   widened by a relative margin.
3. **Plane sweep** (:func:`sweep_depth`): fronto-parallel planes evenly spaced in
   inverse depth. Each neighbour is warped onto the reference grid through the
   plane's homography (OpenCV) and compared by zero-mean normalized cross
   correlation (ZNCC, covariances and variances summed over the colour
   channels) over a square window. The cost of a neighbour is ``1 - ZNCC``
   (0 best, 2 worst); a hypothesis that lands inside a neighbour's image but
   outside its (one-pixel dilated) object mask costs 2 (the silhouette
   constraint); one that leaves the neighbour's image costs 1 (no
   information). The aggregated cost is the mean of the ``top_k`` smallest
   neighbour costs, which tolerates occlusion and specular highlights in the
   other neighbours. The winning plane is refined to sub-plane precision with a
   parabola through its neighbours' costs.

Pixels whose reference window has (almost) no texture, that lie outside the
reference mask, whose best plane is the first or last, or whose best
aggregated ZNCC is below ``min_score`` get depth 0 (unknown). Cross-view
consistency filtering and fusion live in :mod:`pmvir.geometry.mvs.fusion`, the
orchestration in :mod:`pmvir.geometry.mvs.dense`.

Images are ``I_int ** (1 / 2.2)`` (:func:`matching_image`; a display-like tone
curve that evens out noise between dark and bright regions). ZNCC is invariant
to gain and offset, so per-view exposure and lighting strength do not matter;
summing over colours keeps hue-only texture, at the price of some sensitivity
to per-view lighting colour.

Pixel convention: COLMAP's (pixel [row, col] centre at (col + 0.5, row + 0.5));
homographies are converted to OpenCV's integer-centre convention internally.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from pmvir.camera import Camera
from pmvir.errors import ConfigError, InputError, ShapeError
from pmvir.geometry.projection import project_points

#: Variance floor of a ZNCC window (grey levels^2 of the tone-mapped [0, 1] image): below it a
#: window is textureless and gives no depth.
MIN_WINDOW_VARIANCE = 1e-5
_EPS = 1e-12
# View selection: preferred triangulation angle and the Gaussian widths below and above it (radians).
_PREFERRED_ANGLE = np.radians(15.0)
_SIGMA_BELOW = np.radians(5.0)
_SIGMA_ABOVE = np.radians(15.0)
# COLMAP pixel coordinates = OpenCV pixel coordinates + 0.5
_CV_TO_COLMAP = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, 0.5], [0.0, 0.0, 1.0]])
_COLMAP_TO_CV = np.linalg.inv(_CV_TO_COLMAP)


@dataclass(frozen=True)
class DepthMap:
    """A view's dense depth on its (possibly downscaled) pixel grid.

    Attributes:
        camera: the camera of this grid (intrinsics scaled to ``depth.shape``).
        depth: (h, w) float32 camera-frame z, world units; 0 where unknown.
        score: (h, w) float32 aggregated ZNCC of the kept depth in [-1, 1]; 0 where unknown.
    """

    camera: Camera
    depth: np.ndarray
    score: np.ndarray

    @property
    def valid(self) -> np.ndarray:
        """(h, w) bool, depth known."""
        return self.depth > 0


@dataclass(frozen=True)
class StereoView:
    """A view prepared for stereo: grey image, mask and camera on the stereo grid.

    Attributes:
        image: (h, w, C) float32 tone-mapped colours (:func:`matching_image`), about [0, 1].
        mask: (h, w) bool object mask (all True when the capture has none).
        camera: the camera scaled to (h, w).
    """

    image: np.ndarray
    mask: np.ndarray
    camera: Camera




def scale_camera(camera: Camera, width: int, height: int) -> Camera:
    """The same camera on a resampled ``width`` x ``height`` grid (COLMAP convention: exact for any scale)."""
    sx, sy = width / camera.width, height / camera.height
    S = np.diag([sx, sy, 1.0])
    return Camera(K=S @ camera.K, R=camera.R, t=camera.t, width=int(width), height=int(height))


def matching_image(rgb: np.ndarray, *, colour: bool = True) -> np.ndarray:
    """Tone-mapped image for matching.

    Args:
        rgb: (H, W, C) or (H, W) float linear intensities (negative noise is clipped to 0).
        colour: keep the C channels; False: their mean (grey).

    Returns:
        (H, W, C) float32 ``rgb ** (1 / 2.2)``, or (H, W, 1) for grey.
    """
    a: np.ndarray = np.asarray(rgb, dtype=np.float32)
    if a.ndim == 2:
        a = a[..., None]
    if a.ndim != 3:
        raise ShapeError(f"expected an (H, W) or (H, W, C) image, got shape {np.shape(rgb)}")
    if not colour and a.shape[2] > 1:
        a = cv2.transform(a, np.full((1, a.shape[2]), 1.0 / a.shape[2], np.float32))[..., None]
    return np.power(np.maximum(a, 0.0), np.float32(1.0 / 2.2))


def prepare_view(
    image: np.ndarray, mask: np.ndarray | None, camera: Camera, *, scale: float, colour: bool = True
) -> StereoView:
    """Downscale one view for stereo.

    Args:
        image: (H, W, 3) float32 linear I_int (or (H, W) grey).
        mask: (H, W) bool object mask, or None (every pixel may hold the object).
        camera: the view's camera at (H, W).
        scale: grid scale in (0, 1]; the grid is ``round(W * scale) x round(H * scale)`` (at least 8).
        colour: match the colour channels (True) or their mean (False).

    Returns:
        The :class:`StereoView` (area-averaged image; the mask keeps pixels at least half covered).
    """
    H, W = image.shape[:2]
    if (camera.height, camera.width) != (H, W):
        raise ShapeError(f"image is {W}x{H} but its camera is {camera.width}x{camera.height}")
    if not 0.0 < scale <= 1.0:
        raise ConfigError(f"scale must lie in (0, 1], got {scale}")
    w, h = max(8, round(W * scale)), max(8, round(H * scale))
    img = matching_image(image, colour=colour)
    m = np.ones((H, W), dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    if m.shape != (H, W):
        raise ShapeError(f"mask is {m.shape[1]}x{m.shape[0]} but the image is {W}x{H}")
    if (w, h) != (W, H):
        img = cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA).reshape(h, w, img.shape[2])
        m = cv2.resize(m.astype(np.float32), (w, h), interpolation=cv2.INTER_AREA) >= 0.5
    return StereoView(image=np.ascontiguousarray(img), mask=m, camera=scale_camera(camera, w, h))


def select_neighbours(
    cameras: Sequence[Camera],
    points: np.ndarray,
    *,
    count: int,
    min_angle_deg: float = 5.0,
    max_angle_deg: float = 60.0,
    masks: Sequence[np.ndarray | None] | None = None,
) -> list[list[int]]:
    """The best source views of every reference view.

    A pair's score sums, over the sparse points that project in front of both
    cameras, inside both images (and masks), with a triangulation angle in
    ``[min_angle_deg, max_angle_deg]``, a Gaussian weight of the angle around 15
    degrees (sigma 5 degrees below, 15 above; the view selection of MVSNet,
    Yao et al. 2018): the nearest views with a useful baseline rank first, as
    they look most alike.

    Args:
        cameras: V cameras.
        points: (P, 3) sparse world points (at least one).
        count: most neighbours per view.
        min_angle_deg, max_angle_deg: triangulation angle range, degrees.
        masks: optional per-view bool masks on each camera's grid.

    Returns:
        For each view, up to ``count`` other view indices, best first (views sharing no
        point with it are left out).
    """
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    n = len(cameras)
    seen = np.zeros((n, len(pts)), dtype=bool)
    for j, cam in enumerate(cameras):
        uv, z = project_points(cam, pts)
        ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < cam.width) & (uv[:, 1] >= 0) & (uv[:, 1] < cam.height)
        m = None if masks is None else masks[j]
        if m is not None:
            rows = np.clip(uv[:, 1].astype(np.int64), 0, cam.height - 1)
            cols = np.clip(uv[:, 0].astype(np.int64), 0, cam.width - 1)
            ok &= np.asarray(m, dtype=bool)[rows, cols]
        seen[j] = ok
    centres = np.stack([c.center for c in cameras])
    rays = pts[None, :, :] - centres[:, None, :]  # (V, P, 3)
    rays /= np.maximum(np.linalg.norm(rays, axis=2, keepdims=True), _EPS)
    lo, hi = np.radians(min_angle_deg), np.radians(max_angle_deg)
    out: list[list[int]] = []
    for r in range(n):
        scores = np.zeros(n)
        for s in range(n):
            if s == r:
                continue
            both = seen[r] & seen[s]
            if not both.any():
                continue
            ang = np.arccos(np.clip((rays[r, both] * rays[s, both]).sum(1), -1.0, 1.0))
            ang = ang[(ang >= lo) & (ang <= hi)]
            sigma = np.where(ang < _PREFERRED_ANGLE, _SIGMA_BELOW, _SIGMA_ABOVE)
            scores[s] = np.exp(-0.5 * ((ang - _PREFERRED_ANGLE) / sigma) ** 2).sum()
        order = [int(s) for s in np.argsort(-scores, kind="stable") if scores[s] > 0]
        out.append(order[:count])
    return out


def view_depth_range(
    camera: Camera,
    points: np.ndarray,
    mask: np.ndarray | None = None,
    *,
    margin: float = 0.1,
    min_points: int = 3,
) -> tuple[float, float] | None:
    """Depth range of a view from sparse points.

    Args:
        camera: the view (on any grid; only the projection is used).
        points: (P, 3) world points.
        mask: optional bool mask on the camera's grid; points outside it are ignored.
        margin: the 1st..99th percentile range is widened by this fraction of its far
            depth on both sides.
        min_points: fewer points in the view than this give None.

    Returns:
        (near, far) world units with 0 < near < far, or None when fewer than ``min_points``
        (at least 3) points project into the view.
    """
    if len(points) < max(min_points, 3):
        return None
    uv, z = project_points(camera, points)
    ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    if mask is not None:
        r = np.clip(uv[:, 1].astype(np.int64), 0, camera.height - 1)
        c = np.clip(uv[:, 0].astype(np.int64), 0, camera.width - 1)
        ok &= np.asarray(mask, dtype=bool)[r, c]
    if ok.sum() < max(min_points, 3):
        return None
    lo, hi = np.percentile(z[ok], [1.0, 99.0])
    pad = margin * hi
    near = max(lo - pad, 1e-3 * hi)
    return float(near), float(hi + pad)


def _channel_sum(a: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """(h, w, K) -> (h, w) weighted channel sum (cv2.transform: far faster than numpy on a short axis)."""
    return cv2.transform(a, weights[None, :])


def _box(a: np.ndarray, window: int) -> np.ndarray:
    return cv2.boxFilter(a, cv2.CV_32F, (window, window), borderType=cv2.BORDER_REFLECT).reshape(a.shape)


def _ref_stats(img: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The reference's padded colours, window means, variance and the colour weights.

    Returns:
        ref (h, w, C + 1) with a zero last channel, its window means (same shape),
        the window variance summed over colours (h, w), and the (C + 1,) weights
        that sum colours and skip the last (mask) channel.
    """
    c = img.shape[2]
    ref = np.ascontiguousarray(np.dstack([img, np.zeros(img.shape[:2], np.float32)]))
    weights = np.array([1.0] * c + [0.0], np.float32)
    mean = _box(ref, window)
    var = np.maximum(_channel_sum(_box(ref * ref, window) - mean * mean, weights), 0.0)
    return ref, mean, var, weights


def _pixel_zncc_cost(
    warped: np.ndarray,
    ref: np.ndarray,
    ref_mean: np.ndarray,
    ref_var: np.ndarray,
    weights: np.ndarray,
    window: int,
) -> np.ndarray:
    """Per-pixel ``1 - ZNCC`` of a warped neighbour against the reference.

    Args:
        warped: (h, w, C + 1) float32 contiguous, the neighbour's colours then its mask
            (-1 off its image).
        ref, ref_mean, ref_var, weights: from :func:`_ref_stats`.
        window: window side.

    Returns:
        (h, w) float32 cost in [0, 2]: colour ZNCC (covariance and variances summed over colours).
    """
    m = cv2.extractChannel(warped, warped.shape[2] - 1)
    mean_s = _box(warped, window)
    var_s = np.maximum(_channel_sum(_box(warped * warped, window) - mean_s * mean_s, weights), 0.0)
    cov = _channel_sum(_box(warped * ref, window) - mean_s * ref_mean, weights)
    zncc = cov / np.sqrt(np.maximum(ref_var * var_s, _EPS))
    cost = 1.0 - np.clip(zncc, -1.0, 1.0)
    cost[var_s <= MIN_WINDOW_VARIANCE] = 1.0  # textureless in the neighbour: no information
    inside = m > -0.25
    cost[~inside] = 1.0  # outside the neighbour's image: no information
    cost[inside & (m < 0.5)] = 2.0  # inside its image but off its silhouette: impossible
    return cost


def _source_stack(view: StereoView) -> np.ndarray:
    """(h, w, C + 1) float32: the colours, then the mask dilated by a pixel (-1 off the image once warped)."""
    m = cv2.dilate(view.mask.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(np.float32)
    return np.dstack([view.image, m])


def _crop(mask: np.ndarray, pad: int) -> tuple[int, int, int, int]:
    """Bounding rows/cols [r0, r1) x [c0, c1) of a mask, padded and clipped."""
    rows, cols = np.flatnonzero(mask.any(1)), np.flatnonzero(mask.any(0))
    h, w = mask.shape
    return (
        max(rows[0] - pad, 0),
        min(rows[-1] + 1 + pad, h),
        max(cols[0] - pad, 0),
        min(cols[-1] + 1 + pad, w),
    )


def _aggregate(costs: Sequence[np.ndarray], top_k: int) -> np.ndarray:
    """Per-pixel mean of the ``top_k`` smallest of several (h, w) cost maps (running insertion, no sort)."""
    k = min(top_k, len(costs))
    smallest = [np.full_like(costs[0], np.inf) for _ in range(k)]
    for c in costs:
        for i in range(k):
            lo = np.minimum(smallest[i], c)
            c = np.maximum(smallest[i], c)
            smallest[i] = lo
    total = smallest[0]
    for extra in smallest[1:]:
        total = total + extra
    return total / np.float32(k)


def _parabola_offset(c_prev: np.ndarray, c_best: np.ndarray, c_next: np.ndarray) -> np.ndarray:
    """Sub-sample offset in [-0.5, 0.5] of a parabola's minimum through three equally spaced costs."""
    denom = c_prev - 2.0 * c_best + c_next
    off = 0.5 * (c_prev - c_next) / np.where(denom > _EPS, denom, np.inf)
    return np.clip(off, -0.5, 0.5)


def sweep_depth(
    ref: StereoView,
    sources: Sequence[StereoView],
    near: float,
    far: float,
    *,
    planes: int = 96,
    window: int = 7,
    top_k: int = 2,
    min_score: float = 0.5,
) -> DepthMap:
    """Plane-sweep depth of one reference view (module docstring, step 3).

    Args:
        ref: the reference view.
        sources: its neighbours (at least one), on any grids.
        near, far: depth range, 0 < near < far.
        planes: number of fronto-parallel planes, evenly spaced in inverse depth.
        window: ZNCC window side in pixels (odd).
        top_k: neighbour costs averaged per pixel (the smallest ones).
        min_score: smallest aggregated ZNCC ``1 - cost`` kept.

    Returns:
        The :class:`DepthMap` on the reference grid.
    """
    if not sources:
        raise InputError("sweep_depth needs at least one source view")
    if not 0.0 < near < far:
        raise ConfigError(f"need 0 < near < far, got {near}, {far}")
    if window < 3 or window % 2 == 0:
        raise ConfigError(f"window must be odd and >= 3, got {window}")
    if planes < 3:
        raise ConfigError(f"need at least 3 planes, got {planes}")
    h, w = ref.image.shape[:2]
    depth = np.zeros((h, w), np.float32)
    score = np.zeros((h, w), np.float32)
    if not ref.mask.any():
        return DepthMap(ref.camera, depth, score)
    r0, r1, c0, c1 = _crop(ref.mask, window)
    img = np.ascontiguousarray(ref.image[r0:r1, c0:c1])
    ref4, ref_mean, ref_var, weights = _ref_stats(img, window)
    inv = np.linspace(1.0 / far, 1.0 / near, planes)  # plane i at depth 1 / inv[i]
    # Reference pixel (OpenCV, crop) -> normalized camera ray.
    shift = np.array([[1.0, 0.0, c0], [0.0, 1.0, r0], [0.0, 0.0, 1.0]])
    ray_from_pix = np.linalg.inv(ref.camera.K) @ _CV_TO_COLMAP @ shift
    stacks = [_source_stack(s) for s in sources]
    channels = img.shape[2]
    if any(st.shape[2] != channels + 1 for st in stacks) or channels > 3:
        raise ShapeError("reference and source images must have the same number (1 to 3) of colours")
    border = tuple(-1.0 if k == channels else 0.0 for k in range(4))
    rels = []
    for s in sources:
        R_rel = s.camera.R @ ref.camera.R.T
        t_rel = s.camera.t - R_rel @ ref.camera.t
        rels.append((_COLMAP_TO_CV @ s.camera.K, R_rel, t_rel))
    volume = np.empty((planes, r1 - r0, c1 - c0), np.float32)
    costs: list[np.ndarray] = [np.empty(0)] * len(sources)
    size = (c1 - c0, r1 - r0)
    for i, q in enumerate(inv):
        for j, (Ks, R_rel, t_rel) in enumerate(rels):
            # fronto-parallel plane z = d: X_src = (R_rel + t_rel [0 0 1] / d) X_ref
            Hm = Ks @ (R_rel + np.outer(t_rel, [0.0, 0.0, q])) @ ray_from_pix
            warped = cv2.warpPerspective(
                stacks[j],
                Hm,
                size,
                flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                borderMode=cv2.BORDER_CONSTANT,
                borderValue=border,
            )
            costs[j] = _pixel_zncc_cost(warped, ref4, ref_mean, ref_var, weights, window)
        volume[i] = _aggregate(costs, top_k)
    best = np.argmin(volume, axis=0)
    c_best = np.take_along_axis(volume, best[None], 0)[0]
    c_prev = np.take_along_axis(volume, np.maximum(best - 1, 0)[None], 0)[0]
    c_next = np.take_along_axis(volume, np.minimum(best + 1, planes - 1)[None], 0)[0]
    off = _parabola_offset(c_prev, c_best, c_next)
    interior = (best > 0) & (best < planes - 1)
    step = inv[1] - inv[0]
    q_best = inv[best] + np.where(interior, off, 0.0) * step
    s = 1.0 - c_best
    keep = ref.mask[r0:r1, c0:c1] & (ref_var > MIN_WINDOW_VARIANCE) & (s >= min_score) & interior
    depth[r0:r1, c0:c1] = np.where(keep, 1.0 / q_best, 0.0)
    score[r0:r1, c0:c1] = np.where(keep, s, 0.0)
    return DepthMap(ref.camera, depth, score)
