"""Dense reconstruction of the registered views: depth maps, consistency filter, fusion.

:func:`dense_stereo` chooses the backend (``geometry.mvs.backend``):

* ``cpu``: :mod:`pmvir.geometry.mvs.sweep` plane sweep per registered view on a
  grid scaled by ``mvs_scale``, then :mod:`pmvir.geometry.mvs.fusion`
  (geometric consistency across the neighbours, point averaging, voxel
  thinning, PCA normals facing the cameras);
* ``colmap-cuda``: :mod:`pmvir.geometry.mvs.colmap` (COLMAP PatchMatch with
  geometric consistency and COLMAP's stereo fusion), on full-resolution images;
* ``auto``: ``colmap-cuda`` when ``pycolmap.has_cuda``, else ``cpu``.

Both use pmvir's view selection (:func:`~pmvir.geometry.mvs.select_neighbours`)
and per-view depth ranges (:func:`depth_range`): the known cameras' visual hull
(:mod:`pmvir.geometry.silhouette.hull`; without masks their common frustum) bounds each
view's depth search, and sparse points, where a view sees enough of them, only
tighten it; with few or no sparse points the hull's surface cells choose the
neighbours, so known poses never need sparse points. Fewer fused points than
``mvs.min_points`` raise :class:`~pmvir.errors.ReconstructionError` naming the
views that gave no consistent depth (a textureless object, or views that do
not overlap), instead of producing an empty mesh.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np

from pmvir.camera import Camera
from pmvir.config import MvsOptions
from pmvir.errors import ConfigError, ReconstructionError, ShapeError
from pmvir.geometry.mvs.fusion import DensePoints, estimate_normals, filter_and_fuse, voxel_thin
from pmvir.geometry.mvs.sweep import (
    DepthMap,
    StereoView,
    prepare_view,
    select_neighbours,
    sweep_depth,
    view_depth_range,
)
from pmvir.geometry.silhouette.hull import Hull, carve_hull
from pmvir.progress import Progress
from pmvir.threads import usable_threads

#: Sparse points choose stereo neighbours and tighten depth ranges when there are at least this many
#: (in all, and in a view); otherwise the known cameras' visual hull does both alone.
_MIN_SUPPORT_POINTS = 20
#: Automatic ZNCC window sides (pixels of the stereo grid): small against the fronto-parallel bias on
#: curved and thin parts; wider on sparse rigs, whose depths one other view confirms.
_WINDOW = 3
_SPARSE_RIG_WINDOW = 7
#: The automatic window on the full-resolution grid of views without masks (``mvs.unmasked_full_grid_px``):
#: about the image area of 3 on the half-resolution grid. Knot and spring on a table, 16 views of
#: 320x256, no masks: vertices beyond 2 % of the diagonal 0.57-1.40 % with the half grid, 0.09-1.06 %
#: with 5 on the full grid, 0.25-1.26 % with 7 (benchmarks page, the stereo grid without masks).
_UNMASKED_FULL_WINDOW = 5
#: The share of the stereo's progress bar a full-resolution grid takes when it is tried first.
_FULL_GRID_SPAN = 0.8


@dataclass(frozen=True)
class DenseResult:
    """What dense stereo produced.

    Attributes:
        points: the fused oriented points.
        backend: 'cpu' or 'colmap-cuda'.
        neighbours: per view the source views used (empty for unregistered views).
        depth_maps: per view the CPU depth map (None for unregistered views and the COLMAP backend).
        valid_depths: per view the number of depths before the consistency filter (-1: not computed).
        consistent_fraction: per view the fraction of its (stereo-grid) mask pixels whose depth
            passed the consistency filter; for a view without a mask, the fraction of its depths
            (-1: not computed: unregistered view or COLMAP backend).
        fused_per_view: per view the number of fused points it contributed (after thinning).
        timings: seconds per step ('depth_maps', 'fusion'; 'full_grid_not_kept': the part of
            'depth_maps' spent on a full-resolution grid that was not kept).
        grid: the CPU stereo grid, 'WxH' of the first depth map (None: COLMAP backend).
        window: the CPU stereo's ZNCC window side (None: COLMAP backend).
        full_grid_consistent: the full-resolution grid's mean consistent fraction when it was tried
            and not kept (``mvs.unmasked_full_min_consistent``), else None.
    """

    points: DensePoints
    backend: str
    neighbours: list[list[int]]
    depth_maps: list[DepthMap | None]
    valid_depths: list[int]
    consistent_fraction: list[float]
    fused_per_view: list[int]
    timings: dict[str, float] = field(default_factory=dict)
    grid: str | None = None
    window: int | None = None
    full_grid_consistent: float | None = None


@dataclass(frozen=True)
class _StereoInputs:
    """What the CPU stereo matches: per view its image, mask, camera, name, source views and depth
    range, and the registered views."""

    images: Sequence[np.ndarray]
    masks: Sequence[np.ndarray | None]
    cameras: Sequence[Camera | None]
    names: Sequence[str]
    neighbours: list[list[int]]
    registered: list[int]
    ranges: list[tuple[float, float] | None]


def resolve_backend(backend: str) -> str:
    """'cpu' or 'colmap-cuda' for a ``geometry.mvs.backend`` value.

    Raises:
        ReconstructionError: 'colmap-cuda' requested but pycolmap has no CUDA.
    """
    import pycolmap

    if backend == "auto":
        return "colmap-cuda" if pycolmap.has_cuda else "cpu"
    if backend == "colmap-cuda" and not pycolmap.has_cuda:
        raise ReconstructionError(
            "geometry.mvs.backend 'colmap-cuda' needs pycolmap built with CUDA (pycolmap.has_cuda is False); "
            "use 'cpu' or 'auto'"
        )
    return backend


def dense_stereo(
    images: Sequence[np.ndarray],
    masks: Sequence[np.ndarray | None],
    cameras: Sequence[Camera | None],
    sparse_points: np.ndarray,
    *,
    names: Sequence[str],
    options: MvsOptions,
    workdir: str | Path | None = None,
    progress: Progress | None = None,
) -> DenseResult:
    """Dense oriented points of the registered views (module docstring).

    Args:
        images: per view (H, W, 3) float32 linear I_int.
        masks: per view a bool (H, W) object mask or None.
        cameras: per view its camera, None where the view is not registered.
        sparse_points: (P, 3) world points from SfM / triangulation (possibly none): they choose the
            neighbours and tighten the hull's depth ranges when there are enough.
        names: per view a name for messages (the frame stem).
        options: the ``geometry.mvs`` options.
        workdir: scratch folder (needed by the COLMAP backend).
        progress: reports per view and is polled for cancellation between views.

    Returns:
        :class:`DenseResult`.

    Raises:
        ReconstructionError: fewer than 2 registered views, masks that share no volume, or fewer
            than ``options.min_points`` fused points (the message names the views).
        CanceledError: the progress object was asked to cancel.
    """
    progress = progress or Progress.none()
    n = len(images)
    if not (len(masks) == len(cameras) == len(names) == n):
        raise ShapeError(
            f"images, masks, cameras and names must have one entry per view, got "
            f"{n}, {len(masks)}, {len(cameras)}, {len(names)}"
        )
    pts = np.asarray(sparse_points, np.float64).reshape(-1, 3)
    registered = [i for i in range(n) if cameras[i] is not None]
    if len(registered) < 2:
        raise ReconstructionError(
            f"dense stereo needs at least 2 registered views, got {len(registered)}"
            + (f" ({', '.join(names[i] for i in registered)})" if registered else "")
        )
    backend = resolve_backend(options.backend)
    reg_cams = [_camera(cameras, i) for i in registered]
    reg_masks = [masks[i] for i in registered]
    hull = carve_hull(reg_cams, reg_masks, names=[names[i] for i in registered])
    support = pts if len(pts) >= _MIN_SUPPORT_POINTS else hull.surface
    nb_local = select_neighbours(
        reg_cams,
        support,
        count=options.neighbours,
        min_angle_deg=options.min_angle_deg,
        max_angle_deg=options.max_angle_deg,
        masks=reg_masks,
    )
    neighbours: list[list[int]] = [[] for _ in range(n)]
    for k, i in enumerate(registered):
        neighbours[i] = [registered[j] for j in nb_local[k]]
    if len(pts) >= _MIN_SUPPORT_POINTS:
        diag = float(np.linalg.norm(np.percentile(pts, 99, 0) - np.percentile(pts, 1, 0)))
    else:
        diag = hull.diagonal
    ranges: list[tuple[float, float] | None] = [None] * n
    for i in registered:
        ranges[i] = depth_range(_camera(cameras, i), hull, pts, masks[i], margin=options.depth_margin)
    if backend == "colmap-cuda":
        return _dense_colmap(
            images,
            masks,
            cameras,
            pts,
            names,
            neighbours,
            registered,
            ranges,
            options,
            workdir,
            diag,
            progress,
        )
    inputs = _StereoInputs(images, masks, cameras, names, neighbours, registered, ranges)
    return _dense_cpu(inputs, options, diag, progress)


def grid_scale(image: np.ndarray, options: MvsOptions) -> float:
    """The CPU stereo grid's scale of one view: ``options.scale``, raised so that the longer side keeps
    ``options.min_grid_px`` pixels (at most 1). Captures without masks may first try the full grid
    (:func:`unmasked_full_grid`)."""
    longer = max(image.shape[:2])
    return float(min(1.0, max(options.scale, options.min_grid_px / max(longer, 1))))


def unmasked_full_grid(images: Sequence[np.ndarray], masks: Sequence[np.ndarray | None], options: MvsOptions) -> bool:
    """Whether no view has a mask and every view is at most ``options.unmasked_full_grid_px`` on its
    longer side: the stereo then runs first on the full-resolution grid, kept when at least
    ``options.unmasked_full_min_consistent`` of its depths are consistent on average."""
    return all(m is None for m in masks) and all(
        max(im.shape[:2]) <= options.unmasked_full_grid_px for im in images
    )


def depth_range(
    camera: Camera, hull: Hull, points: np.ndarray, mask: np.ndarray | None, *, margin: float
) -> tuple[float, float] | None:
    """A view's depth search range: the hull's, tightened by the sparse points it sees when there are enough.

    Args:
        camera: the view (full resolution).
        hull: the known cameras' visual hull (or common frustum).
        points: (P, 3) sparse points (possibly none).
        mask: the view's object mask or None.
        margin: widening of the sparse points' range, a fraction of its far depth.

    Returns:
        (near, far), or None when neither the hull nor the points reach into the view.
    """
    outer = hull.depth_range(camera)
    inner = view_depth_range(camera, points, mask, margin=margin, min_points=_MIN_SUPPORT_POINTS)
    if outer is None or inner is None:
        return outer or inner
    near, far = max(outer[0], inner[0]), min(outer[1], inner[1])
    return (near, far) if near < far else outer


def stereo_window(options: MvsOptions, registered_views: int, *, unmasked_full: bool = False) -> int:
    """The CPU stereo's ZNCC window side: ``options.window``, or when None 3 (5 on the full-resolution
    grid of views without masks, ``unmasked_full``; 7 for captures of at most ``options.sparse_rig_views``
    registered views: one confirming view then fuses a depth, so noise counts)."""
    if options.window is not None:
        return options.window
    if registered_views <= options.sparse_rig_views:
        return _SPARSE_RIG_WINDOW
    return _UNMASKED_FULL_WINDOW if unmasked_full else _WINDOW


def _dense_cpu(inputs: _StereoInputs, options: MvsOptions, diag: float, progress: Progress) -> DenseResult:
    images, masks, cameras, names = inputs.images, inputs.masks, inputs.cameras, inputs.names
    neighbours, registered = inputs.neighbours, inputs.registered
    n = len(images)
    t0 = time.perf_counter()
    full = unmasked_full_grid([images[i] for i in registered], [masks[i] for i in registered], options)
    tried: float | None = None  # the full grid's mean consistent fraction, when it was not kept
    seconds_full = 0.0  # the time of the full grid's depth maps and fusion, when they were not kept
    # the progress bar never goes back: a full grid takes the first 80 % of it (four times the half grid's
    # pixels), and the half grid, when it follows, the rest
    half_from = 0.0
    if full:
        depth_maps, valid, views = _depth_maps(inputs, options, progress, full=True, span=(0.0, _FULL_GRID_SPAN))
        progress.update(_FULL_GRID_SPAN, "fusing the full-resolution depth maps")
        pts_f, views_f, counts_f, fraction = _fused(depth_maps, valid, views, masks, neighbours, options, registered)
        kept = [fraction[i] for i in registered if fraction[i] >= 0]
        if kept and float(np.mean(kept)) < options.unmasked_full_min_consistent:
            tried, full = float(np.mean(kept)), False  # too noisy for the full grid: the half grid averages it
            seconds_full = time.perf_counter() - t0
            half_from = _FULL_GRID_SPAN
    if not full:
        depth_maps, valid, views = _depth_maps(inputs, options, progress, full=False, span=(half_from, 1.0))
        progress.update(1.0, "fusing depth maps")
        pts_f, views_f, counts_f, fraction = _fused(depth_maps, valid, views, masks, neighbours, options, registered)
    t1 = time.perf_counter()
    if options.voxel > 0:
        keep = voxel_thin(pts_f, options.voxel * diag)
        pts_f, views_f, counts_f = pts_f[keep], views_f[keep], counts_f[keep]
    dense = DensePoints(
        points=pts_f, normals=estimate_normals(pts_f, views_f, cameras), views=views_f, consistent=counts_f
    )
    first = next((m for m in depth_maps if m is not None), None)
    result = DenseResult(
        points=dense,
        backend="cpu",
        neighbours=neighbours,
        depth_maps=depth_maps,
        valid_depths=valid,
        consistent_fraction=fraction,
        fused_per_view=np.bincount(views_f, minlength=n).tolist(),
        timings={"depth_maps": t1 - t0, "fusion": time.perf_counter() - t1}
        | ({"full_grid_not_kept": seconds_full} if tried is not None else {}),
        grid=None if first is None else f"{first.depth.shape[1]}x{first.depth.shape[0]}",
        window=stereo_window(options, len(registered), unmasked_full=full),
        full_grid_consistent=tried,
    )
    _check_enough(result, names, registered, options)
    return result


def _depth_maps(
    inputs: _StereoInputs, options: MvsOptions, progress: Progress, *, full: bool, span: tuple[float, float]
) -> tuple[list[DepthMap | None], list[int], list[StereoView | None]]:
    """Per view its depth map, its number of depths (-1: none computed) and its stereo view: on the
    full-resolution grid of views without masks (``full``, :func:`unmasked_full_grid`) or on
    :func:`grid_scale`'s; progress moves across ``span`` (from, to) of the step's bar."""
    images, masks, cameras, names = inputs.images, inputs.masks, inputs.cameras, inputs.names
    neighbours, registered, ranges = inputs.neighbours, inputs.registered, inputs.ranges
    n = len(images)
    views: list[StereoView | None] = [None] * n
    for i in registered:
        if neighbours[i] or any(i in neighbours[j] for j in registered):
            scale = 1.0 if full else grid_scale(images[i], options)
            views[i] = prepare_view(images[i], masks[i], _camera(cameras, i), scale=scale, colour=options.colour)
    depth_maps: list[DepthMap | None] = [None] * n
    valid = [-1] * n
    window = stereo_window(options, len(registered), unmasked_full=full)
    grid = "full-resolution grid, " if full else ""

    def sweep(i: int) -> DepthMap | None:
        ref, rng = views[i], ranges[i]
        if ref is None or not neighbours[i] or rng is None:
            return None
        sources = [v for v in (views[j] for j in neighbours[i]) if v is not None]  # all prepared above
        return sweep_depth(
            ref, sources, *rng, planes=options.planes, window=window, top_k=options.top_k, min_score=options.min_score
        )

    # The views' sweeps are independent and spend their time in OpenCV and NumPy, which release the
    # GIL: one thread per core (the maps, and so the result, are the same as one after the other).
    pool = ThreadPoolExecutor(max_workers=usable_threads())
    try:
        futures = [pool.submit(sweep, i) for i in registered]
        for k, (i, future) in enumerate(zip(registered, futures, strict=True)):
            at = span[0] + (span[1] - span[0]) * k / len(registered)
            progress.update(at, f"depth map {k + 1}/{len(registered)} ({grid}view {names[i]})")
            depth = depth_maps[i] = future.result()
            if depth is not None:
                valid[i] = int(depth.valid.sum())
    finally:  # a cancel (or a failed sweep) drops the sweeps not started
        pool.shutdown(wait=True, cancel_futures=True)
    return depth_maps, valid, views


def _fused(
    depth_maps: list[DepthMap | None],
    valid: list[int],
    views: list[StereoView | None],
    masks: Sequence[np.ndarray | None],
    neighbours: list[list[int]],
    options: MvsOptions,
    registered: list[int],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[float]]:
    """The consistent depths fused (:func:`_fuse`: points, their views and confirming counts) and per
    view the fraction of its object's pixels (without a mask, of its depths) that are consistent."""
    pts_f, views_f, counts_f = _fuse(depth_maps, neighbours, options, len(registered))
    consistent = np.bincount(views_f, minlength=len(views))
    fraction = [-1.0] * len(views)
    for i, view in enumerate(views):
        if view is not None:  # of the object's pixels; without a mask, of the depths found
            base = int(view.mask.sum()) if masks[i] is not None else max(valid[i], 0)
            fraction[i] = float(consistent[i] / max(base, 1))
    return pts_f, views_f, counts_f, fraction


def _fuse(
    depth_maps: Sequence[DepthMap | None], neighbours: Sequence[Sequence[int]], options: MvsOptions, registered: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """:func:`filter_and_fuse` with the stereo options (one confirming view on sparse rigs) and the occlusion test."""
    return filter_and_fuse(
        depth_maps,
        neighbours,
        max_reproj_px=options.consistency_px,
        max_rel_depth=options.consistency_depth,
        min_consistent=1 if registered <= options.sparse_rig_views else options.min_consistent,
        max_occluding=options.max_occluding,
    )


def fuse_within_masks(
    dense: DenseResult,
    masks: Sequence[np.ndarray | None],
    cameras: Sequence[Camera | None],
    options: MvsOptions,
    *,
    extent: float,
) -> DensePoints | None:
    """The CPU stereo's depth maps fused again, each view's depths kept inside its mask.

    A capture without masks is fused over whole images and thinned at the scene's extent (the
    table's as well as the object's). Once the object's masks are drawn, its depths are fused
    again alone, each mask grown by one pixel of the stereo grid (a mask drawn from the images
    may end a pixel inside the outline), and thinned at the object's ``extent``: the object
    keeps the point density a masked capture gives it.

    Args:
        dense: the result of :func:`dense_stereo` (its depth maps and neighbours).
        masks: per view its (H, W) bool object mask, None where none.
        cameras: per view its camera, None where the view is not registered.
        options: the ``geometry.mvs`` options of that run.
        extent: the object's bounding-box diagonal, world units; points are thinned to one per
            cube of ``options.voxel`` times it.

    Returns:
        The fused, oriented points, or None where ``dense`` kept no depth maps (COLMAP's fusion).
    """
    if not any(dm is not None for dm in dense.depth_maps):
        return None
    maps: list[DepthMap | None] = []
    grow = np.ones((3, 3), np.uint8)
    for dm, mask in zip(dense.depth_maps, masks, strict=True):
        if dm is None or mask is None:
            maps.append(dm)
            continue
        h, w = dm.depth.shape
        covered = cv2.resize(np.asarray(mask, np.float32), (w, h), interpolation=cv2.INTER_AREA) > 0
        inside = cv2.dilate(covered.astype(np.uint8), grow).astype(bool)
        maps.append(replace(dm, depth=np.where(inside, dm.depth, 0).astype(dm.depth.dtype)))
    registered = sum(cam is not None for cam in cameras)
    pts, views, counts = _fuse(maps, dense.neighbours, options, registered)
    if options.voxel > 0 and len(pts):
        keep = voxel_thin(pts, options.voxel * extent)
        pts, views, counts = pts[keep], views[keep], counts[keep]
    return DensePoints(points=pts, normals=estimate_normals(pts, views, cameras), views=views, consistent=counts)


def _dense_colmap(
    images: Sequence[np.ndarray],
    masks: Sequence[np.ndarray | None],
    cameras: Sequence[Camera | None],
    pts: np.ndarray,
    names: Sequence[str],
    neighbours: list[list[int]],
    registered: list[int],
    ranges: list[tuple[float, float] | None],
    options: MvsOptions,
    workdir: str | Path | None,
    diag: float,
    progress: Progress,
) -> DenseResult:
    from pmvir.geometry.mvs.colmap import colmap_fusion, colmap_patch_match, write_workspace

    if workdir is None:
        raise ConfigError("the colmap-cuda backend needs a workdir")
    n = len(images)
    t0 = time.perf_counter()
    local = {i: k for k, i in enumerate(registered)}
    root = write_workspace(
        Path(workdir) / "colmap-dense",
        [images[i] for i in registered],
        [masks[i] for i in registered],
        [_camera(cameras, i) for i in registered],
        [names[i] for i in registered],
        [[local[j] for j in neighbours[i]] for i in registered],
        pts,
    )
    known = [r for r in ranges if r is not None]
    if not known:
        raise ReconstructionError("no registered view sees the object's volume: cannot bound the depth range")
    progress.update(0.0, "COLMAP PatchMatch stereo (CUDA)")
    colmap_patch_match(root, depth_range=(min(r[0] for r in known), max(r[1] for r in known)))
    t1 = time.perf_counter()
    progress.update(1.0, "COLMAP stereo fusion")
    points, normals = colmap_fusion(
        root,
        max_reproj_error=2.0 * options.consistency_px / options.scale,
        max_depth_error=options.consistency_depth,
    )
    views = _nearest_view(points, normals, cameras, registered)
    if options.voxel > 0:
        keep = voxel_thin(points, options.voxel * diag)
        points, normals, views = points[keep], normals[keep], views[keep]
    dense = DensePoints(
        points=points, normals=normals, views=views, consistent=np.zeros(len(points), np.int64)
    )
    per_view = np.bincount(views, minlength=n).tolist() if len(views) else [0] * n
    result = DenseResult(
        points=dense,
        backend="colmap-cuda",
        neighbours=neighbours,
        depth_maps=[None] * n,
        valid_depths=[-1] * n,
        consistent_fraction=[-1.0] * n,
        fused_per_view=per_view,
        timings={"depth_maps": t1 - t0, "fusion": time.perf_counter() - t1},
    )
    _check_enough(result, names, registered, options)
    return result


def _camera(cameras: Sequence[Camera | None], i: int) -> Camera:
    """The camera of view ``i``, which the caller knows to be registered."""
    cam = cameras[i]
    if cam is None:
        raise ReconstructionError(f"view {i} has no pose but was taken as registered")
    return cam


def _nearest_view(
    points: np.ndarray, normals: np.ndarray, cameras: Sequence[Camera | None], registered: list[int]
) -> np.ndarray:
    """Per point, the registered view whose viewing direction best faces its normal."""
    if len(points) == 0:
        return np.zeros(0, np.int64)
    centres = np.stack([_camera(cameras, i).center for i in registered])
    best = np.full(len(points), -np.inf)
    view = np.zeros(len(points), np.int64)
    for k, c in enumerate(centres):
        d = c - points
        cos = (d * normals).sum(1) / np.maximum(np.linalg.norm(d, axis=1), 1e-12)
        better = cos > best
        best[better] = cos[better]
        view[better] = registered[k]
    return view


def _check_enough(
    result: DenseResult, names: Sequence[str], registered: list[int], options: MvsOptions
) -> None:
    """ReconstructionError when too few points were fused, or too few depths passed the consistency filter."""
    count = len(result.points)
    fractions = [result.consistent_fraction[i] for i in registered if result.consistent_fraction[i] >= 0]
    overall = float(np.mean(fractions)) if fractions else None
    if count >= options.min_points and (overall is None or overall >= options.min_consistent_fraction):
        return
    weak = [
        names[i]
        for i in registered
        if result.fused_per_view[i] == 0
        or 0 <= result.consistent_fraction[i] < options.min_consistent_fraction
    ]
    no_nb = [names[i] for i in registered if not result.neighbours[i]]
    detail = f"; views without a neighbour sharing sparse points: {', '.join(no_nb)}" if no_nb else ""
    share = (
        ""
        if overall is None
        else (
            f"; on average {100 * overall:.1f}% of a view's object pixels got a consistent depth "
            f"(mvs.min_consistent_fraction: {100 * options.min_consistent_fraction:.1f}%)"
        )
    )
    raise ReconstructionError(
        f"dense stereo fused {count} points from {len(registered)} registered views (mvs.min_points: "
        f"{options.min_points}){share}; views with (almost) no consistent depth: "
        f"{', '.join(weak) if weak else 'none'}{detail}. The object may be textureless, or the views may "
        "not overlap."
    )


__all__ = ["DenseResult", "dense_stereo", "fuse_within_masks", "resolve_backend"]
