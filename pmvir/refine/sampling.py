"""Per-view observations and their sub-pixel sampling at projected vertices.

Conventions (capture spec, sections 1-2):

* A vertex X projects into view c with the pinhole model of
  :class:`pmvir.camera.Camera` to COLMAP pixel coordinates (u, v); the image
  array is sampled at the continuous index (row, col) = (v - 0.5, u - 0.5),
  bilinearly (:class:`_Bilinear`; coordinates clamped to the image).
* AoP is an axial quantity in [0, pi): raw angles are never interpolated. The
  maps (cos 2 phi, sin 2 phi) are interpolated bilinearly and the sampled AoP is
  0.5 * atan2(sin, cos) wrapped to [0, pi).
* DoP and intensities are interpolated bilinearly.
* A (vertex, view) pair is used in a stage when the vertex is visible in the
  view, in front of the camera, its projection's whole bilinear footprint lies
  inside the image, every pixel of the footprint is ``valid`` and, when a minimum
  viewing cosine is given, the vertex normal faces the camera at least that much
  (cos of the angle between the normal and the direction to the camera centre).
  Grazing pairs are left out because their bilinear sample mixes surface points
  far apart along the surface (the footprint stretches by 1 / cos) and their
  colour is the least reliable: kept, they pull the surface away from the truth.
  The pair set
  is fixed for a stage; samples move with the vertices (and are differentiated).
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from pmvir.camera import Camera
from pmvir.errors import ConfigError


@dataclass(frozen=True)
class Observation:
    """One view's decoded measurements (capture spec, section 2).

    Attributes:
        intensity: (H, W, 3) float32 linear RGB, normalized units; I_min or I_int
            as the refinement is told to use (see :func:`observation_from_decoded`).
        aop: (H, W) float32 angle of polarization, radians in [0, pi), ccw sense.
        dop: (H, W) float32 degree of polarization in [0, 1].
        valid: (H, W) bool; False where AoP/DoP are undefined or the pixel is saturated
            or outside the object.
        aop_noise: optional (H, W) float32 noise of the normalized Stokes vector
            (:func:`pmvir.polarization.noise.closure_noise`; NaN where unmeasured), so that
            DoP / noise is each pixel's AoP signal-to-noise ratio; None: the same everywhere.
    """

    intensity: np.ndarray
    aop: np.ndarray
    dop: np.ndarray
    valid: np.ndarray
    aop_noise: np.ndarray | None = None

    def __post_init__(self) -> None:
        i = np.asarray(self.intensity, dtype=np.float32)
        if i.ndim != 3 or i.shape[2] != 3:
            raise ConfigError(f"expected (H, W, 3) intensity, got shape {i.shape}")
        h, w = i.shape[:2]
        fields = {"aop": self.aop, "dop": self.dop, "valid": self.valid}
        if self.aop_noise is not None:
            fields["aop_noise"] = self.aop_noise
        for name, a in fields.items():
            if np.shape(a) != (h, w):
                raise ConfigError(f"expected ({h}, {w}) {name} to match the intensity, got {np.shape(a)}")
        object.__setattr__(self, "intensity", i)
        object.__setattr__(self, "aop", np.asarray(self.aop, dtype=np.float32))
        object.__setattr__(self, "dop", np.asarray(self.dop, dtype=np.float32))
        object.__setattr__(self, "valid", np.asarray(self.valid, dtype=bool))
        if self.aop_noise is not None:
            object.__setattr__(self, "aop_noise", np.asarray(self.aop_noise, dtype=np.float32))

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W)."""
        return self.intensity.shape[0], self.intensity.shape[1]


def observation_from_decoded(
    frame: Mapping[str, np.ndarray], *, intensity: Literal["min", "int"] = "min"
) -> Observation:
    """Build an :class:`Observation` from a decoded frame (the ``pmvir decode`` npz keys).

    Args:
        frame: mapping with ``i_min`` and/or ``i_int`` (H, W, 3), ``aop``, ``dop`` (H, W), ``valid``.
        intensity: ``"min"`` uses I_min (the paper's choice), ``"int"`` uses I_int.

    Raises:
        ConfigError: unknown ``intensity`` or a missing key.
    """
    if intensity not in ("min", "int"):
        raise ConfigError(f"intensity must be 'min' or 'int', got {intensity!r}")
    key = "i_min" if intensity == "min" else "i_int"
    missing = [k for k in (key, "aop", "dop", "valid") if k not in frame]
    if missing:
        raise ConfigError(f"decoded frame lacks {missing}")
    return Observation(intensity=frame[key], aop=frame["aop"], dop=frame["dop"], valid=frame["valid"])


@dataclass(frozen=True)
class ViewStack:
    """Cameras and images as tensors on the refinement's device.

    Attributes:
        table: (sum_c H_c W_c, C) every view's pixels, row-major, one view after the other:
            channels 0-2 the RGB intensity; with polarization also 3 = cos 2 phi,
            4 = sin 2 phi, 5 = DoP.
        base: (V,) int64 row of each view's first pixel in ``table``.
        width, height: (V,) int64 image sizes.
        rotation: (V, 3, 3) cam_from_world rotations.
        translation: (V, 3) cam_from_world translations.
        intrinsics: (V, 5) fx, fy, cx, cy, skew.
        noise: (sum_c H_c W_c, 1) every view's ``aop_noise`` in the rows of ``table`` (NaN where
            unmeasured or the view has none), or None when no view has one. Sampled only at a
            stage's start (``sample_pairs(..., with_noise=True)``), not in the energy.
    """

    table: torch.Tensor
    base: torch.Tensor
    width: torch.Tensor
    height: torch.Tensor
    rotation: torch.Tensor
    translation: torch.Tensor
    intrinsics: torch.Tensor
    noise: torch.Tensor | None = None

    @property
    def polarimetric(self) -> bool:
        return self.table.shape[1] == 6

    @property
    def n_views(self) -> int:
        return int(self.base.shape[0])


def build_view_stack(
    cameras: Sequence[Camera],
    observations: Sequence[Observation],
    *,
    polarimetric: bool,
    device: torch.device,
    dtype: torch.dtype,
) -> ViewStack:
    """Pack cameras and observations as tensors (see :class:`ViewStack`).

    Raises:
        ConfigError: counts differ, or an image's size differs from its camera's (or is below 2 x 2).
    """
    if len(cameras) != len(observations):
        raise ConfigError(f"{len(cameras)} cameras but {len(observations)} observations")
    if len(cameras) == 0:
        raise ConfigError("need at least one view")
    n_chan = 6 if polarimetric else 3
    sizes = []
    for c, (cam, obs) in enumerate(zip(cameras, observations, strict=True)):
        if obs.shape != (cam.height, cam.width):
            raise ConfigError(
                f"view {c}: image is {obs.shape} (H, W) but the camera is ({cam.height}, {cam.width})"
            )
        if min(obs.shape) < 2:
            raise ConfigError(f"view {c}: images must be at least 2 x 2 pixels, got {obs.shape}")
        sizes.append(obs.shape)
    counts = [h * w for h, w in sizes]
    base = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.int64)
    table = np.empty((int(sum(counts)), n_chan), dtype=np.float32)
    for c, obs in enumerate(observations):
        rows = table[base[c] : base[c] + counts[c]]
        rows[:, :3] = obs.intensity.reshape(-1, 3)
        if polarimetric:
            phi = obs.aop.reshape(-1).astype(np.float64)
            rows[:, 3] = np.cos(2.0 * phi)
            rows[:, 4] = np.sin(2.0 * phi)
            rows[:, 5] = obs.dop.reshape(-1)
    noise = None
    if polarimetric and any(obs.aop_noise is not None for obs in observations):
        noise = np.full((int(sum(counts)), 1), np.nan, dtype=np.float32)
        for c, obs in enumerate(observations):
            if obs.aop_noise is not None:
                noise[base[c] : base[c] + counts[c], 0] = obs.aop_noise.reshape(-1)

    def tensor(a: np.ndarray, dt: torch.dtype = dtype) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a)).to(device=device, dtype=dt)

    intr = np.array([[c.K[0, 0], c.K[1, 1], c.K[0, 2], c.K[1, 2], c.K[0, 1]] for c in cameras])
    return ViewStack(
        table=tensor(table),
        base=tensor(base, torch.int64),
        width=tensor(np.array([w for _, w in sizes]), torch.int64),
        height=tensor(np.array([h for h, _ in sizes]), torch.int64),
        rotation=tensor(np.stack([c.R for c in cameras])),
        translation=tensor(np.stack([c.t for c in cameras])),
        intrinsics=tensor(intr),
        noise=None if noise is None else tensor(noise),
    )


@dataclass(frozen=True)
class PairSet:
    """The (vertex, view) pairs used in a stage, sorted by view (and by pixel within a view).

    Attributes:
        vertex: (P,) int64 vertex index of each pair.
        view: (P,) int64 view index of each pair (non-decreasing).
        offsets: (V + 1,) pair range of each view: pairs of view c are offsets[c]:offsets[c+1].
        weight: (P,) 1 / |V(i)| of the pair's vertex, float tensor.
        count: (N,) int64 |V(i)|, the number of pairs of each vertex.
        flat: (P,) int64 ``vertex * V + view``, the pair's row in per-(vertex, view) (N * V) arrays.
    """

    vertex: torch.Tensor
    view: torch.Tensor
    offsets: list[int]
    weight: torch.Tensor
    count: np.ndarray
    flat: torch.Tensor

    @property
    def size(self) -> int:
        return int(self.vertex.shape[0])


def select_pairs(
    vertices: np.ndarray,
    visibility: np.ndarray,
    cameras: Sequence[Camera],
    observations: Sequence[Observation],
    *,
    device: torch.device,
    dtype: torch.dtype,
    normals: np.ndarray | None = None,
    min_cos: float = -1.0,
    keep_best: int = 0,
) -> PairSet:
    """The usable (vertex, view) pairs at the current geometry (rules in the module docstring).

    Args:
        vertices: (N, 3) world positions.
        visibility: (N, V) bool, True where vertex i is visible in view c.
        normals: (N, 3) unit vertex normals; needed when ``min_cos`` > -1.
        min_cos: pairs whose normal makes a cosine below this with the direction to the
            camera are left out (-1: none is) ...
        keep_best: ... except each vertex's ``keep_best`` most frontal usable pairs, so that
            a vertex seen by few cameras keeps enough views to be placed.

    Raises:
        ConfigError: ``visibility`` has the wrong shape.
    """
    n, n_views = len(vertices), len(cameras)
    vis = np.asarray(visibility)
    if vis.shape != (n, n_views):
        raise ConfigError(f"expected ({n}, {n_views}) visibility, got {vis.shape}")
    if min_cos > -1.0 and (normals is None or np.shape(normals) != (n, 3)):
        raise ConfigError(f"select_pairs with min_cos > -1 needs ({n}, 3) normals")
    vis = vis.astype(bool)
    vert_idx, view_idx, cos_all = [], [], []
    for c, (cam, obs) in enumerate(zip(cameras, observations, strict=True)):
        idx = np.flatnonzero(vis[:, c])
        uv, depth = cam.project(vertices[idx])
        x, y = uv[:, 0] - 0.5, uv[:, 1] - 0.5
        h, w = obs.shape
        ok = (depth > 0) & (x >= 0) & (y >= 0) & (x <= w - 1) & (y <= h - 1)
        idx, x, y = idx[ok], x[ok], y[ok]
        x0 = np.floor(x).astype(np.int64)
        y0 = np.floor(y).astype(np.int64)
        x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
        valid = obs.valid
        ok = valid[y0, x0] & valid[y0, x1] & valid[y1, x0] & valid[y1, x1]
        # Within a view, pairs go in pixel order: the image lookups then walk memory forwards.
        order = np.argsort(y0[ok] * w + x0[ok], kind="stable")
        kept = idx[ok][order]
        vert_idx.append(kept)
        view_idx.append(np.full(len(kept), c, dtype=np.int64))
        if min_cos > -1.0 and normals is not None:  # checked above
            to_cam = cam.center[None, :] - vertices[kept]
            cos_all.append(
                (normals[kept] * to_cam).sum(1) / np.maximum(np.linalg.norm(to_cam, axis=1), 1e-300)
            )
    vertex = np.concatenate(vert_idx)
    view = np.concatenate(view_idx)
    if min_cos > -1.0:
        keep = _frontal_pairs(vertex, np.concatenate(cos_all), min_cos=min_cos, keep_best=keep_best)
        vertex, view = vertex[keep], view[keep]
    offsets = np.searchsorted(view, np.arange(n_views + 1)).tolist()
    count = np.bincount(vertex, minlength=n).astype(np.int64)
    weight = 1.0 / np.maximum(count[vertex], 1)
    return PairSet(
        vertex=torch.from_numpy(vertex).to(device),
        view=torch.from_numpy(view).to(device),
        offsets=offsets,
        weight=torch.from_numpy(weight).to(device=device, dtype=dtype),
        count=count,
        flat=torch.from_numpy(vertex * n_views + view).to(device),
    )


def _frontal_pairs(vertex: np.ndarray, cos: np.ndarray, *, min_cos: float, keep_best: int) -> np.ndarray:
    """(P,) bool: cos >= min_cos, or among the vertex's ``keep_best`` largest cos."""
    keep = cos >= min_cos
    if keep_best > 0 and len(vertex):
        order = np.lexsort((-cos, vertex))
        vs = vertex[order]
        starts = np.flatnonzero(np.r_[True, vs[1:] != vs[:-1]])
        rank = np.arange(len(vs)) - np.repeat(starts, np.diff(np.r_[starts, len(vs)]))
        keep[order[rank < keep_best]] = True
    return keep


@dataclass(frozen=True)
class PairSamples:
    """Quantities of every pair at the current geometry.

    Attributes:
        intensity: (P, 3) observed RGB I_{i,c}(X).
        normal_cam: (P, 3) the vertex normal in camera c's frame (R_c @ N_i).
        ray_cam: (P, 3) unit direction from camera c's centre to the vertex, camera c's frame.
        aop: (P,) observed AoP phi_{i,c}(X) in [0, pi) (None without polarization).
        dop: (P,) observed DoP rho_{i,c}(X) (None without polarization).
        aop_defined: (P,) bool, False where the interpolated (cos, sin) 2phi vector vanished.
        aop_noise: (P,) the view's ``aop_noise`` at the pair (NaN where unmeasured), or None
            (not asked for, or no view has one).
    """

    intensity: torch.Tensor
    normal_cam: torch.Tensor
    ray_cam: torch.Tensor
    aop: torch.Tensor | None
    dop: torch.Tensor | None
    aop_defined: torch.Tensor | None
    aop_noise: torch.Tensor | None = None


class _Bilinear(torch.autograd.Function):
    """Bilinear lookup in the packed view table at continuous array coordinates (x, y) = (u - 0.5, v - 0.5).

    Coordinates are clamped to the image (zero derivative where clamped). The
    backward pass returns gradients for x and y only; it reuses the per-pair
    derivatives saved by the forward pass instead of recording a graph over the
    (P, 4, C) corner values. The (P, C) result comes as the column groups ``groups``
    (e.g. (3, 1, 1, 1): RGB, cos 2 phi, sin 2 phi, DoP): slicing one output instead
    would make every slice's backward fill a zero (P, C) gradient, and autograd add them.
    """

    @staticmethod
    def forward(ctx, x, y, table, base, width, height, groups):
        ctx.groups = groups
        wf, hf = width.to(x.dtype), height.to(x.dtype)
        xc = torch.minimum(x.clamp_min(0.0), wf - 1.0)
        yc = torch.minimum(y.clamp_min(0.0), hf - 1.0)
        x0 = torch.minimum(xc.floor(), wf - 2.0)
        y0 = torch.minimum(yc.floor(), hf - 2.0)
        fx = (xc - x0)[:, None]
        fy = (yc - y0)[:, None]
        i00 = base + y0.long() * width + x0.long()
        c00 = table.index_select(0, i00)
        c01 = table.index_select(0, i00 + 1)
        c10 = table.index_select(0, i00 + width)
        c11 = table.index_select(0, i00 + width + 1)
        top = torch.lerp(c00, c01, fx)
        bottom = torch.lerp(c10, c11, fx)
        out = torch.lerp(top, bottom, fy)
        inside_x = ((x > 0.0) & (x < wf - 1.0)).to(x.dtype)[:, None]
        inside_y = ((y > 0.0) & (y < hf - 1.0)).to(x.dtype)[:, None]
        dx = torch.lerp(c01 - c00, c11 - c10, fy) * inside_x
        dy = (bottom - top) * inside_y
        ctx.save_for_backward(dx, dy)
        ctx.set_materialize_grads(False)
        return out.split(groups, dim=1)

    @staticmethod
    def backward(ctx, *grads):
        dx, dy = ctx.saved_tensors
        if all(g is None for g in grads):
            return (None,) * 7
        parts = [dx.new_zeros(dx.shape[0], size) if g is None else g
                 for g, size in zip(grads, ctx.groups, strict=True)]
        grad = torch.cat(parts, dim=1)
        return (grad * dx).sum(-1), (grad * dy).sum(-1), None, None, None, None, None


def sample_pairs(
    vertices: torch.Tensor,
    normals: torch.Tensor,
    views: ViewStack,
    pairs: PairSet,
    *,
    with_noise: bool = False,
) -> PairSamples:
    """Project every pair's vertex into its view and sample the images there (differentiably).

    Pairs are transformed to camera frames view by view (pairs are sorted by view);
    the image lookup is :class:`_Bilinear`.

    Args:
        vertices: (N, 3) world positions.
        normals: (N, 3) unit world normals of the vertices.
        views: the packed views.
        pairs: the stage's pairs.
        with_noise: also sample ``views.noise`` (PairSamples.aop_noise), without a gradient.
    """
    sizes = [b - a for a, b in zip(pairs.offsets[:-1], pairs.offsets[1:], strict=True)]
    # torch.split (not slicing): its backward concatenates, slicing's would zero-fill (P, 3) per view.
    xs = torch.split(vertices.index_select(0, pairs.vertex), sizes)
    ns = torch.split(normals.index_select(0, pairs.vertex), sizes)
    rot, trans = views.rotation, views.translation
    pc = torch.cat([x @ rot[c].T + trans[c] for c, x in enumerate(xs)])
    normal_cam = torch.cat([n @ rot[c].T for c, n in enumerate(ns)])
    ray_cam = pc / torch.linalg.vector_norm(pc, dim=1, keepdim=True).clamp_min(1e-12)
    fx, fy, cx, cy, skew = views.intrinsics.index_select(0, pairs.view).unbind(1)
    px, py, pz = pc.unbind(1)  # (indexing columns would zero-fill a (P, 3) gradient per column)
    inv_z = 1.0 / pz.clamp_min(1e-9)
    xn, yn = px * inv_z, py * inv_z
    u = fx * xn + skew * yn + cx
    v = fy * yn + cy
    lookup = (
        views.base.index_select(0, pairs.view),
        views.width.index_select(0, pairs.view),
        views.height.index_select(0, pairs.view),
    )
    if not views.polarimetric:
        (rgb,) = _Bilinear.apply(u - 0.5, v - 0.5, views.table, *lookup, (3,))
        return PairSamples(rgb, normal_cam, ray_cam, None, None, None)
    rgb, cos2, sin2, dop = _Bilinear.apply(u - 0.5, v - 0.5, views.table, *lookup, (3, 1, 1, 1))
    cos2, sin2 = cos2.squeeze(1), sin2.squeeze(1)
    defined = cos2 * cos2 + sin2 * sin2 > 1e-12
    cos_safe = torch.where(defined, cos2, torch.ones_like(cos2))
    phi = torch.remainder(0.5 * torch.atan2(sin2, cos_safe), torch.pi)
    noise = None
    if with_noise and views.noise is not None:
        with torch.no_grad():
            (noise,) = _Bilinear.apply(u.detach() - 0.5, v.detach() - 0.5, views.noise, *lookup, (1,))
            noise = noise[:, 0]
    return PairSamples(rgb, normal_cam, ray_cam, phi, dop.squeeze(1), defined, noise)
