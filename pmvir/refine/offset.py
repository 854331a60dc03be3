"""A photo-consistent offset of the whole surface along its normals (before the refinement's stages).

The plane sweep's depth maps lie behind the surface wherever a neighbour view sees
it at a grazing angle, so the initial surface of a thin or strongly curved shape
sits inside the truth by a bias every vertex shares (README, "Thin parts"). The
refinement's terms see normals, not absolute position, so they keep such an
offset. This module measures it with parallax: every reference view's pixels on
the mesh are carried into its nearest views through the mesh (the ray through
the pixel meets the plane of the triangle it hits), and the mean zero-normalized
cross-correlation (ZNCC) over small windows is scanned over offsets of the whole
mesh along its vertex normals. Only pairs that see the triangle at a viewing
cosine of at least ``min_cos`` in both views count: grazing pairs are the ones
that pull the minimum inward. The offset is applied only where the scan has an
interior minimum.

Warping through the mesh gives each window the shape of the surface, which a
fronto-parallel stereo window lacks; the scan has one unknown, so the noise of
per-pixel matching averages out (per-vertex offsets estimated the same way were
too noisy to help; README).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np
import open3d as o3d
from scipy.ndimage import uniform_filter

from pmvir.camera import Camera, sample_bilinear
from pmvir.errors import ConfigError
from pmvir.geometry.mesh_ops import face_normals, raycasting_scene, vertex_normals
from pmvir.refine.sampling import Observation


@dataclass(frozen=True)
class OffsetScan:
    """What :func:`photo_consistent_offset` measured.

    Attributes:
        offsets_px: (K,) the scanned offsets, in pixels of the mean ground sampling distance
            (positive: outward, along the vertex normals).
        costs: (K,) mean 1 - ZNCC over the used windows at each offset.
        pixel_size: the mean ground sampling distance (world units per pixel) at the vertices.
        offset: the chosen offset in world units (0 when the scan has no interior minimum).
        pixels: windows that entered the cost (per offset, the same set).
        applied: whether an offset was chosen.
        reason: why not, when not applied.
        blurred_costs: with ``deblur_px``, the costs of the scan on the images blurred by it.
        blurred_offset_px: with ``deblur_px``, that scan's minimum, pixels (None when it has none).
        seconds: wall time of the scan (both scans with ``deblur_px``).
    """

    offsets_px: np.ndarray
    costs: np.ndarray
    pixel_size: float
    offset: float
    pixels: int
    applied: bool
    reason: str = ""
    blurred_costs: np.ndarray | None = None
    blurred_offset_px: float | None = None
    seconds: float = 0.0

    def to_dict(self) -> dict:
        extra = {}
        if self.blurred_costs is not None:
            extra = {
                "blurred_scan_cost": [round(float(x), 6) for x in self.blurred_costs],
                "blurred_offset_px": self.blurred_offset_px,
            }
        return extra | {
            "offset": self.offset,
            "offset_px": self.offset / self.pixel_size if self.pixel_size > 0 else 0.0,
            "pixel_size": self.pixel_size,
            "applied": self.applied,
            "reason": self.reason,
            "pixels": self.pixels,
            "seconds": round(self.seconds, 3),
            "scan_px": [round(float(x), 4) for x in self.offsets_px],
            "scan_cost": [round(float(x), 6) for x in self.costs],
        }


def neighbour_views(cameras: Sequence[Camera], count: int, *, min_angle_deg: float = 5.0) -> list[list[int]]:
    """The ``count`` views whose optical axes are closest in angle to each view's (at least ``min_angle_deg`` apart)."""
    axes = np.array([c.R[2] for c in cameras])
    out = []
    for i in range(len(cameras)):
        ang = np.degrees(np.arccos(np.clip(axes @ axes[i], -1.0, 1.0)))
        ang[i] = np.inf
        ang[ang < min_angle_deg] = np.inf
        order = [int(j) for j in np.argsort(ang) if np.isfinite(ang[j])]
        out.append(order[:count])
    return out


@dataclass
class _Pair:
    """A reference view's pixels seen by one source view, with their windows' reference statistics."""

    ref: int
    src: int
    faces: np.ndarray  # (n,) the triangle each pixel's ray hits
    rays: np.ndarray  # (n, 3) unit world directions of the pixels' rays
    # in the pixels' bounding box (outside it every map is zero, as the filters' constant padding is):
    rows: np.ndarray  # (n,) row and column in the box
    cols: np.ndarray
    shape: tuple[int, int]
    ref_masked: np.ndarray  # (h, w) the reference grey at the pixels, 0 elsewhere
    cover: np.ndarray  # (n,) fraction of each pixel's window that is the pair's pixels
    ref_mean: np.ndarray  # (n,) window mean and variance of the reference grey
    ref_var: np.ndarray
    window: int
    origin: tuple[int, int] = (0, 0)  # the box's top-left pixel (row, column) in the reference view


def _pair(
    ref: int,
    src: int,
    rows: np.ndarray,
    cols: np.ndarray,
    faces: np.ndarray,
    rays: np.ndarray,
    grey: np.ndarray,
    window: int,
) -> _Pair:
    if len(rows) == 0:
        empty = np.zeros(0)
        return _Pair(ref, src, faces, rays, rows, cols, (0, 0), np.zeros((0, 0)), empty, empty, empty, window)
    r0, c0 = int(rows.min()), int(cols.min())
    r, c = rows - r0, cols - c0
    shape = (int(r.max()) + 1, int(c.max()) + 1)
    m = np.zeros(shape)
    m[r, c] = 1.0
    ref_masked = grey[r0 : r0 + shape[0], c0 : c0 + shape[1]] * m
    cover = uniform_filter(m, window, mode="constant")
    safe = np.maximum(cover, 1e-12)
    mean = uniform_filter(ref_masked, window, mode="constant") / safe
    var = uniform_filter(ref_masked * ref_masked, window, mode="constant") / safe - mean * mean
    return _Pair(
        ref, src, faces, rays, r, c, shape, ref_masked, cover[r, c], mean[r, c], var[r, c], window, (r0, c0)
    )


def _with_grey(p: _Pair, grey: np.ndarray) -> _Pair:
    """The same pixels and rays with another reference image's window statistics (no new ray casting)."""
    return _pair(p.ref, p.src, p.rows + p.origin[0], p.cols + p.origin[1], p.faces, p.rays, grey, p.window)


def _grey(obs: Observation) -> np.ndarray:
    g = obs.intensity.astype(np.float64).mean(axis=2)
    scale = float(np.percentile(g[obs.valid], 99)) if obs.valid.any() else 1.0
    return g / max(scale, 1e-12)


def _pairs(
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    valid: Sequence[np.ndarray],
    neighbours: Sequence[Sequence[int]],
    min_cos: float,
    greys: Sequence[np.ndarray],
    window: int,
) -> list[_Pair]:
    # World coordinates (origin 0): the camera rays below are cast as they are.
    scene = raycasting_scene(vertices, faces, origin=np.zeros(3)).scene
    fn = face_normals(vertices, faces)
    pairs = []
    for i, cam in enumerate(cameras):
        if not neighbours[i]:
            continue
        origins, dirs = cam.pixel_rays()
        hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([origins, dirs], -1).astype(np.float32)))
        t_hit = hit["t_hit"].numpy()
        prim = hit["primitive_ids"].numpy().astype(np.int64)
        ok = np.isfinite(t_hit) & valid[i]
        ok &= -(fn[np.where(ok, prim, 0)] * dirs).sum(-1) >= min_cos
        rows, cols = np.nonzero(ok)
        f = prim[rows, cols]
        x = cam.center + t_hit[rows, cols, None] * dirs[rows, cols]
        for j in neighbours[i]:
            src = cameras[j]
            uv, z = src.project(x)
            to_x = x - src.center
            dist = np.linalg.norm(to_x, axis=1)
            to_x /= dist[:, None]
            back = scene.cast_rays(
                o3d.core.Tensor(
                    np.concatenate([np.broadcast_to(src.center, x.shape), to_x], 1).astype(np.float32)
                )
            )["t_hit"].numpy()
            col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
            inside = (z > 0) & (col >= 0) & (col < src.width) & (row >= 0) & (row < src.height)
            seen = inside & (np.abs(back - dist) <= 2e-3 * dist) & (-(fn[f] * to_x).sum(-1) >= min_cos)
            seen[inside] &= valid[j][row[inside], col[inside]]
            rs, cs = rows[seen], cols[seen]
            pairs.append(_pair(i, j, rs, cs, f[seen], dirs[rs, cs], greys[i], window))
    return pairs


def _mean_zncc_cost(
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    greys: Sequence[np.ndarray],
    pairs: Sequence[_Pair],
    *,
    min_coverage: float = 0.7,
) -> tuple[float, int]:
    """Mean 1 - ZNCC over every pair's windows, the pixels carried through ``vertices`` (same faces and rays).

    Returns the mean and the number of windows (pixels whose window is at least
    ``min_coverage`` covered by the pair's pixels and whose reference window has texture).
    """
    total, count = 0.0, 0
    for p in pairs:
        if len(p.rows) == 0:
            continue
        cam, src = cameras[p.ref], cameras[p.src]
        a, b, c = vertices[faces[p.faces, 0]], vertices[faces[p.faces, 1]], vertices[faces[p.faces, 2]]
        n = np.cross(b - a, c - a)
        denom = (p.rays * n).sum(1)
        t = ((a - cam.center) * n).sum(1) / np.where(np.abs(denom) > 1e-300, denom, 1e-300)
        uv, _ = src.project(cam.center + t[:, None] * p.rays)
        sampled = sample_bilinear(greys[p.src], uv[:, 0], uv[:, 1])
        warped = np.zeros(p.shape)
        warped[p.rows, p.cols] = sampled
        safe = np.maximum(p.cover, 1e-12)
        window = p.window
        mb = uniform_filter(warped, window, mode="constant")[p.rows, p.cols] / safe
        vb = uniform_filter(warped * warped, window, mode="constant")[p.rows, p.cols] / safe - mb * mb
        cab = uniform_filter(p.ref_masked * warped, window, mode="constant")[p.rows, p.cols] / safe
        cab -= p.ref_mean * mb
        use = (p.cover >= min_coverage) & (p.ref_var > 1e-6)
        z = cab / np.sqrt(np.maximum(p.ref_var * vb, 0.0) + 1e-8)
        total += float((1.0 - z[use]).sum())
        count += int(use.sum())
    return (total / count if count else float("nan")), count


def photo_consistent_offset(
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    observations: Sequence[Observation],
    *,
    neighbours: int = 2,
    min_cos: float = 0.8,
    window: int = 5,
    max_px: float = 1.5,
    step_px: float = 0.25,
    min_pixels: int = 500,
    min_curvature: float = 0.01,
    deblur_px: float = 0.0,
) -> OffsetScan:
    """Scan offsets of the whole mesh along its vertex normals for the most photo-consistent one.

    Args:
        vertices, faces: the mesh (faces counter-clockwise seen from outside).
        cameras, observations: the views (``valid`` marks usable pixels).
        neighbours: source views per reference view (the nearest by optical-axis angle).
        min_cos: least viewing cosine of a used pixel's triangle in both views.
        window: ZNCC window side, pixels (odd).
        max_px, step_px: the scan covers [-max_px, max_px] mean ground sampling distances.
        min_pixels: fewer usable windows than this: no offset is applied.
        min_curvature: least curvature of the scan, relative to its minimum cost, per px^2 (the
            quadratic coefficient of a parabola fitted to the whole scan, divided by the
            minimum); below it the views barely tell the offsets apart (little texture: the
            windows hold noise and smooth shading) and no offset is applied. A curvature, not
            the rise to the scan's ends, so that it does not depend on the scan's range or on
            where in it the minimum lies (the refinement's later scans cover +-0.75 px). 0: no such
            rule.
        deblur_px: 0, or the Gaussian blur (pixels) the images are taken to hold: the scan runs
            again on the images blurred by it and the offset is extrapolated to no blur,
            ``2 o - o_blurred``. Image blur (demosaicing's above all) moves the scan's minimum
            inward in proportion to its variance (README: 1.6 px matches the default
            demosaicing on the synthetic captures).

    Returns:
        :class:`OffsetScan`; move the vertices by ``offset`` along ``vertex_normals``.

    Raises:
        ConfigError: mismatched inputs or options out of range.
    """
    if len(cameras) != len(observations):
        raise ConfigError(f"{len(cameras)} cameras but {len(observations)} observations")
    if window < 3 or window % 2 == 0:
        raise ConfigError(f"the ZNCC window must be odd and at least 3 pixels, got {window}")
    if not 0.0 < step_px <= max_px:
        raise ConfigError(f"expected 0 < step_px <= max_px, got {step_px} and {max_px}")
    if min_curvature < 0.0:
        raise ConfigError(f"min_curvature must be >= 0, got {min_curvature}")
    if deblur_px < 0.0:
        raise ConfigError(f"deblur_px must be >= 0, got {deblur_px}")
    vertices = np.asarray(vertices, dtype=np.float64)
    faces = np.asarray(faces, dtype=np.int64)
    normals = vertex_normals(vertices, faces).astype(np.float64)
    # mean ground sampling distance at the vertices, over the views (depth / focal length)
    depth = np.array([np.median(cam.world_to_cam(vertices)[:, 2]) / cam.K[0, 0] for cam in cameras])
    pixel_size = float(np.mean(depth))
    k = round(max_px / step_px)
    offsets_px = np.arange(-k, k + 1) * step_px
    greys = [_grey(o) for o in observations]
    valid = [o.valid for o in observations]
    nearest = neighbour_views(cameras, neighbours)

    pairs = _pairs(vertices, faces, cameras, valid, nearest, min_cos, greys, window)

    def costs_of(images: list[np.ndarray], pairs: list[_Pair]) -> tuple[np.ndarray, int]:
        costs, counts = [], []
        for d in offsets_px:
            cost, count = _mean_zncc_cost(vertices + d * pixel_size * normals, faces, cameras, images, pairs)
            costs.append(cost)
            counts.append(count)
        return np.asarray(costs), (int(min(counts)) if counts else 0)

    costs_a, pixels = costs_of(greys, pairs)

    def scan(offset: float, applied: bool, reason: str = "") -> OffsetScan:
        return OffsetScan(offsets_px, costs_a, pixel_size, offset, pixels, applied, reason)

    if pixels < min_pixels or not np.all(np.isfinite(costs_a)):
        return scan(0.0, False, f"{pixels} usable windows (at least {min_pixels} needed)")
    best = int(np.argmin(costs_a))
    if best == 0 or best == len(costs_a) - 1:
        return scan(0.0, False, f"the minimum is at the scan's end ({offsets_px[best]:+.2f} px)")
    curvature = float(np.polyfit(offsets_px, costs_a, 2)[0]) / max(float(costs_a[best]), 1e-12)
    if min_curvature > 0.0 and curvature < min_curvature:
        return scan(
            0.0,
            False,
            f"the cost's curvature is only {100 * curvature:.3f}% of its minimum per px^2 (at least "
            f"{100 * min_curvature:.3f}% needed): too little texture to tell the offsets apart",
        )
    found = _minimum_px(offsets_px, costs_a, step_px)
    if deblur_px <= 0.0:
        return scan(found * pixel_size, True)
    blurred = [cv2.GaussianBlur(g, (0, 0), deblur_px) for g in greys]
    blurred_costs, _ = costs_of(blurred, [_with_grey(p, blurred[p.ref]) for p in pairs])
    b = int(np.argmin(blurred_costs))
    at_end = b in (0, len(blurred_costs) - 1) or not np.all(np.isfinite(blurred_costs))
    blurred_px = None if at_end else _minimum_px(offsets_px, blurred_costs, step_px)
    # no interior minimum on the blurred images: keep the plain scan's
    deblurred = found if blurred_px is None else 2.0 * found - blurred_px
    deblurred = float(np.clip(deblurred, offsets_px[0], offsets_px[-1]))
    return OffsetScan(
        offsets_px, costs_a, pixel_size, deblurred * pixel_size, pixels, True, "", blurred_costs, blurred_px
    )


def _minimum_px(offsets_px: np.ndarray, costs: np.ndarray, step_px: float) -> float:
    """The scan's minimum in pixels: a parabola through the lowest sample and up to two on each side."""
    best = int(np.argmin(costs))
    near = slice(max(best - 2, 0), min(best + 3, len(costs)))
    a2, a1, _ = np.polyfit(offsets_px[near] - offsets_px[best], costs[near], 2)
    sub = -a1 / (2.0 * a2) if a2 > 0 else 0.0
    return float(offsets_px[best] + np.clip(sub, -step_px, step_px))
