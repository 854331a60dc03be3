"""The geometric stage (pipeline stage 2, paper section 4.2): capture and decoded views to an initial mesh.

:func:`run_geometry` runs, timing and counting each step:

1. ``poses``: :func:`pmvir.geometry.sfm.estimate_poses`
   (known-pose triangulation on I_int when the capture has intrinsics and every
   ``cam_from_world``, else incremental SfM, by default on I_min with I_int as the
   fallback: ``sfm.grey``);
2. ``depth_maps`` and ``fusion``: :func:`pmvir.geometry.mvs.dense.dense_stereo`;
   ``isolation`` (a capture without masks, ``geometry.isolate``):
   :func:`pmvir.geometry.silhouette.isolate.isolate_object` finds the object
   (support plane removed, the cluster the views aim at kept), draws its masks
   and its dense points are the depth maps fused again within those masks
   (:func:`object_dense_points`); the steps below use the masks as given ones,
   with 2 px more slack in the surface's silhouette trimming;
3. ``surface``: :func:`pmvir.geometry.surface.initial_surface` (screened
   Poisson, trimmed, simplified, cleaned to one manifold component);
4. ``visibility``: :func:`pmvir.geometry.visibility.vertex_visibility`;
5. ``subdivision``: :func:`pmvir.geometry.subdivision.subdivide_until`
   (sqrt(3) steps until every visible triangle is below
   ``subdivision.max_area_px`` pixels^2);
6. ``silhouettes``: :func:`pmvir.geometry.silhouette.hull_fit.fit_inside_hull` (vertices
   that project outside a mask move inward: ``surface.hull_tolerance_px``); not on the
   masks the isolation drew, which are not exact to the pixel.

:func:`write_geometry` writes a result folder's ``initial.ply`` (the subdivided
initial surface), ``poses/`` (a COLMAP model, binary and text, of the registered
views and the sparse points with their tracks), ``images/`` (the viewable I_int
images the model names), ``sparse.ply`` and ``dense.ply`` (the fused points), ``masks/`` (the
masks the isolation drew, when it ran), and :func:`geometry_report` gives the
JSON-ready counts and timings for ``report.json`` (spec section 3).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from pmvir.camera import Camera
from pmvir.capture import Capture
from pmvir.config import GeometryOptions
from pmvir.errors import ReconstructionError, ShapeError
from pmvir.geometry.export import (
    colmap_reconstruction,
    colours_at,
    viewable_images,
    write_colmap_model,
    write_images,
    write_points_ply,
)
from pmvir.geometry.mesh_ops import edge_topology, vertex_normals
from pmvir.geometry.mvs.dense import DenseResult, dense_stereo, fuse_within_masks
from pmvir.geometry.mvs.fusion import DensePoints
from pmvir.geometry.sfm.poses import SparseModel, estimate_poses
from pmvir.geometry.silhouette.cluster import point_spacing
from pmvir.geometry.silhouette.hull_fit import HullFit, fit_inside_hull
from pmvir.geometry.silhouette.isolate import (
    Isolation,
    isolate_object,
    kept_points,
    on_object,
    wants_isolation,
    write_masks,
)
from pmvir.geometry.subdivision import subdivide_until
from pmvir.geometry.surface.initial import SurfaceResult, initial_surface
from pmvir.geometry.surface.seen_through import MARGIN_SPACINGS, cut_seen_through, lying_on_support
from pmvir.geometry.visibility import vertex_visibility
from pmvir.io.ply import Mesh
from pmvir.polarization.stokes import PolarizationImages
from pmvir.progress import Progress
from pmvir.result import ResultFolder

#: Share of the stage's progress bar given to each step (they sum to 1).
_STEP_WEIGHTS = {"poses": 0.25, "dense": 0.42, "isolation": 0.03, "surface": 0.1, "visibility": 0.1, "subdivision": 0.08, "silhouettes": 0.02}
#: Masks the isolation drew end up to 2 px inside the outline here and there (GrabCut gives the pixels
#: the demosaicing mixes with the background to the background): the silhouette trimming takes this
#: many pixels more than for given masks, and the hull fit, which trusts a mask to half a pixel, does
#: not run on them.
_DRAWN_MASK_SLACK_PX = 2


@dataclass(frozen=True)
class GeometryResult:
    """Everything the geometric stage produced.

    Attributes:
        names: frame stems, in capture order.
        files: frame files as in capture.json, in capture order.
        cameras: per frame the camera used (None where it was not registered).
        sparse: the SfM / triangulation result.
        dense: the dense stereo result.
        surface: the initial surface before subdivision, with per-step counts.
        vertices: (N, 3) float64 the subdivided initial surface.
        faces: (F, 3) int64, counter-clockwise seen from outside.
        visibility: (N, V) bool, V = all frames (False columns for unregistered ones).
        subdivision_rounds: sqrt(3) steps applied.
        subdivision_max_area_px: largest projected visible triangle area at the end, pixels^2.
        subdivision_converged: the area threshold was reached (not a round/vertex limit).
        hull_fit: the subdivided vertices pulled inside the masks' visual hull
            (``surface.hull_tolerance_px``; :func:`pmvir.geometry.silhouette.hull_fit.fit_inside_hull`), or None (off).
        timings: seconds per step: poses, depth_maps, fusion, surface, visibility, subdivision, total.
        previews: per frame (H, W, 3) uint8 sRGB I_int with one exposure for all frames (``images/``).
        masks: per frame the object mask the stage used (given, or drawn by the isolation; None: none).
        isolation: what the isolation found (``geometry.isolate``), or None where it did not run.
        coarse: (vertices, faces, visibility over all frames) of the subdivided surface one sqrt(3) step
            short, before the hull fit (``refine.stages.coarse``); None when no step was applied.
    """

    names: list[str]
    files: list[str]
    cameras: list[Camera | None]
    sparse: SparseModel
    dense: DenseResult
    surface: SurfaceResult
    vertices: np.ndarray
    faces: np.ndarray
    visibility: np.ndarray
    subdivision_rounds: int
    subdivision_max_area_px: float
    subdivision_converged: bool
    hull_fit: HullFit | None = None
    timings: dict[str, float] = field(default_factory=dict)
    previews: list[np.ndarray] = field(default_factory=list)
    masks: list[np.ndarray | None] = field(default_factory=list)
    isolation: Isolation | None = None
    coarse: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    @property
    def registered(self) -> list[bool]:
        return [c is not None for c in self.cameras]


def run_geometry(
    capture: Capture,
    views: Sequence[PolarizationImages],
    *,
    options: GeometryOptions | None = None,
    workdir: str | Path,
    progress: Progress | None = None,
) -> GeometryResult:
    """Poses, dense points, initial surface, visibility and subdivision (module docstring).

    Args:
        capture: the open capture (intrinsics, poses, masks, frame names).
        views: per frame, in capture order, its decoded images (``i_int`` is used).
        options: geometry options (default ``GeometryOptions()``).
        workdir: scratch folder for SfM and (CUDA) dense workspaces; created.
        progress: reports each step (poses, dense, surface, visibility, subdivision), times it and
            is polled for cancellation between steps and views.

    Returns:
        :class:`GeometryResult`.

    Raises:
        ReconstructionError: too few registered views (naming those that failed), too few
            dense points (textureless or non-overlapping views), or no surface.
        CanceledError: the progress object was asked to cancel.
    """
    options = options or GeometryOptions()
    progress = progress or Progress.none()
    n = len(capture.frames)
    if len(views) != n:
        raise ShapeError(f"expected {n} decoded views (one per frame), got {len(views)}")
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    t_start = time.perf_counter()
    names = [f.name for f in capture.frames]
    files = [f.file for f in capture.frames]
    images = [np.asarray(v.i_int, np.float32) for v in views]
    masks = [capture.read_mask(i) for i in range(n)]

    with progress.step("poses", _STEP_WEIGHTS["poses"]) as p:
        known = capture.has_all_poses
        # estimated intrinsics (from EXIF, "estimated": true) are SfM's starting focal length, not held fixed
        intrinsics = [
            None if f.intrinsics is None or (f.intrinsics.estimated and not known) else _k_matrix(f.intrinsics)
            for f in capture.frames
        ]
        priors = [
            0.5 * (f.intrinsics.fx + f.intrinsics.fy) if f.intrinsics is not None and f.intrinsics.estimated else None
            for f in capture.frames
        ]
        sift, fallback = sift_inputs(views, options.sfm.grey, known=known)
        sparse = estimate_poses(
            sift,
            names,
            cameras=[f.camera for f in capture.frames] if known else None,
            intrinsics=intrinsics if any(k is not None for k in intrinsics) else None,
            masks=masks,
            options=options.sfm,
            workdir=workdir / "sfm",
            progress=p.update,
            fallback_images=fallback,
            focal_priors=priors if any(f is not None for f in priors) else None,
        )
    cameras = list(sparse.cameras)
    reg = [i for i in range(n) if cameras[i] is not None]
    reg_cams = [cam for cam in cameras if cam is not None]  # in the order of reg

    with progress.step("dense", _STEP_WEIGHTS["dense"]) as p:
        dense = dense_stereo(
            images,
            masks,
            cameras,
            sparse.points,
            names=names,
            options=options.mvs,
            workdir=workdir,
            progress=p,
        )

    isolation = None
    if wants_isolation(options.isolate.enabled, masks):
        with progress.step("isolation", _STEP_WEIGHTS["isolation"]):
            isolation = isolate_object(
                dense.points.points, cameras, viewable_images(images), settings=options.isolate,
                depth_maps=dense.depth_maps if options.isolate.see_past else None,
            )
            masks = isolation.masks
            dense = replace(dense, points=object_dense_points(dense, isolation, cameras, options))
    else:  # masks given, or isolation off: the step's share of the bar passes at once
        with progress.step("isolation", _STEP_WEIGHTS["isolation"]):
            pass

    with progress.step("surface", _STEP_WEIGHTS["surface"]):
        surface = initial_surface(
            dense.points.points,
            dense.points.normals,
            cameras=reg_cams,
            masks=[masks[i] for i in reg],
            options=options.surface,
            max_area_px=options.surface.split_factor * options.subdivision.max_area_px,
            mask_slack_px=0 if isolation is None else _DRAWN_MASK_SLACK_PX,
            mask_outside_share=0.0 if isolation is None else isolation.outside_share,
        )
        if isolation is not None and (options.isolate.cut_seen_through or options.isolate.cut_support_sheet):
            surface = without_seen_through(surface, dense, options, isolation)

    with progress.step("visibility", _STEP_WEIGHTS["visibility"]):
        vis = vertex_visibility(
            surface.vertices,
            surface.faces,
            reg_cams,
            [masks[i] for i in reg],
            **options.visibility.model_dump(),
        )
        if not vis.any():
            raise ReconstructionError("no vertex of the initial surface is visible in any registered view")

    with progress.step("subdivision", _STEP_WEIGHTS["subdivision"]):
        sub = subdivide_until(
            surface.vertices,
            surface.faces,
            vis,
            reg_cams,
            **options.subdivision.model_dump(),
        )
    vertices, hull = sub.vertices, None
    with progress.step("silhouettes", _STEP_WEIGHTS["silhouettes"]):
        if options.surface.hull_tolerance_px is not None and isolation is None:  # drawn masks: no fit
            hull = fit_inside_hull(
                sub.vertices, sub.faces, reg_cams, [masks[i] for i in reg],
                tolerance_px=options.surface.hull_tolerance_px,
            )
            vertices = hull.vertices
    full_vis = np.zeros((len(sub.vertices), n), bool)
    full_vis[:, reg] = sub.visibility
    coarse = None
    if sub.before_last is not None:
        coarse_vertices, coarse_faces, coarse_reg_vis = sub.before_last
        coarse_vis = np.zeros((len(coarse_vertices), n), bool)
        coarse_vis[:, reg] = coarse_reg_vis
        coarse = (coarse_vertices, coarse_faces, coarse_vis)
    timings = {k: v for k, v in progress.timings.items() if k != "dense"} | dict(dense.timings)
    timings["total"] = time.perf_counter() - t_start
    return GeometryResult(
        names=names,
        files=files,
        cameras=cameras,
        sparse=sparse,
        dense=dense,
        surface=surface,
        vertices=vertices,
        faces=sub.faces,
        visibility=full_vis,
        subdivision_rounds=sub.rounds,
        subdivision_max_area_px=sub.max_area_px,
        subdivision_converged=sub.converged,
        hull_fit=hull,
        timings=timings,
        previews=viewable_images(images, masks),
        masks=masks,
        isolation=isolation,
        coarse=coarse,
    )


def without_seen_through(
    surface: SurfaceResult, dense: DenseResult, options: GeometryOptions, isolation: Isolation | None = None
) -> SurfaceResult:
    """The initial surface without what the views' stereo depths see through (drawn masks' fill across an
    opening) and without the sheet lying on the isolation's support plane (:mod:`pmvir.geometry.surface.seen_through`;
    ``geometry.isolate.cut_seen_through`` and ``cut_support_sheet``), its counts with
    ``seen_through_vertices``, ``support_sheet_vertices`` and the ``cut_*`` sizes. Stereo without depth maps
    (COLMAP's fusion) sees through nothing."""
    points = dense.points.points
    if len(points) < 10:
        return surface
    sheet = None
    if isolation is not None and isolation.plane is not None and options.isolate.cut_support_sheet:
        band = options.isolate.plane_clearance * isolation.clearance
        sheet = lying_on_support(surface.vertices, surface.faces, isolation.plane, band)
    maps = dense.depth_maps if options.isolate.cut_seen_through else [None] * len(dense.depth_maps)
    if sheet is None and not any(dm is not None for dm in maps):
        return surface
    spacing = point_spacing(points)
    v, f, count = cut_seen_through(
        surface.vertices, surface.faces, maps, margin=MARGIN_SPACINGS * spacing,
        support=points, min_angle_deg=options.surface.min_angle_deg, sheet=sheet, spacing=spacing,
    )
    counts = surface.counts | {"seen_through_vertices": count}
    if sheet is not None:
        counts |= {"support_sheet_vertices": int(sheet.sum())}
    if len(v) != len(surface.vertices) or len(f) != len(surface.faces):
        counts |= {"cut_vertices": len(v), "cut_faces": len(f),
                   "boundary_edges": int(edge_topology(f, len(v)).boundary.sum())}
    return replace(surface, vertices=v, faces=f, counts=counts)


def object_dense_points(
    dense: DenseResult, isolation: Isolation, cameras: Sequence[Camera | None], options: GeometryOptions
) -> DensePoints:
    """The isolated object's dense points: the depth maps fused again within its masks, thinned at its
    extent (:func:`~pmvir.geometry.mvs.dense.fuse_within_masks`), those inside every view's mask and
    above the support plane (:func:`~pmvir.geometry.silhouette.isolate.on_object`); the points the
    isolation kept where stereo kept no depth maps (COLMAP's fusion) or the fusion found none."""
    kept = kept_points(dense.points, isolation.keep)
    if len(kept) < 2:
        return kept
    extent = float(np.linalg.norm(np.percentile(kept.points, 99, 0) - np.percentile(kept.points, 1, 0)))
    fused = fuse_within_masks(dense, isolation.masks, cameras, options.mvs, extent=extent)
    if fused is None:
        return kept
    fused = kept_points(fused, on_object(fused.points, cameras, isolation))
    return fused if len(fused) else kept


def _k_matrix(intr: Any) -> np.ndarray:
    return np.array([[intr.fx, 0.0, intr.cx], [0.0, intr.fy, intr.cy], [0.0, 0.0, 1.0]])


def write_poses(directory: str | Path, result: GeometryResult) -> None:
    """``directory``: the COLMAP model (binary and text) of the registered views and the sparse points
    with their tracks (:mod:`pmvir.geometry.export`); images are named as in ``images/``."""
    sparse = result.sparse
    rec = colmap_reconstruction(
        result.cameras, result.names, sparse.points, sparse.point_colors, sparse.point_observations
    )
    write_colmap_model(directory, rec)


def write_geometry(result: ResultFolder, geometry: GeometryResult) -> None:
    """Write ``initial.ply`` (the subdivided initial surface, spec PLY), ``poses/`` (a COLMAP model),
    ``images/`` (the viewable I_int images it names), ``sparse.ply`` and ``dense.ply`` into the result."""
    mesh = Mesh(geometry.vertices, geometry.faces, normals=vertex_normals(geometry.vertices, geometry.faces))
    result.write_mesh("initial.ply", mesh)
    result.write_folder("poses", lambda folder: write_poses(folder, geometry))
    if geometry.previews:
        result.write_folder("images", lambda folder: write_images(folder, geometry.names, geometry.previews))
    sparse, dense = geometry.sparse, geometry.dense.points
    result.write_file("sparse.ply", lambda path: write_points_ply(path, sparse.points, sparse.point_colors))
    colours = (
        colours_at(dense.points, dense.views, geometry.cameras, geometry.previews)
        if geometry.previews
        else None
    )
    result.write_file("dense.ply", lambda path: write_points_ply(path, dense.points, colours, dense.normals))
    if geometry.isolation is not None:
        isolated = geometry.isolation.masks
        result.write_folder("masks", lambda folder: write_masks(folder, geometry.names, isolated))


def sift_inputs(
    views: Sequence[PolarizationImages], grey: str, *, known: bool
) -> tuple[list[np.ndarray], list[np.ndarray] | None]:
    """The images the poses step's SIFT sees, and its fallback images (``sfm.grey``).

    'int' and 'min': I_int or I_min, no fallback; 'auto': I_int with known poses, else I_min
    with I_int as the fallback (:func:`~pmvir.geometry.sfm.estimate_poses`).
    """
    i_int = [np.asarray(v.i_int, np.float32) for v in views]
    if grey == "int" or (grey == "auto" and known):
        return i_int, None
    i_min = [np.asarray(v.i_min, np.float32) for v in views]
    return i_min, (i_int if grey == "auto" else None)


def geometry_report(result: GeometryResult) -> dict[str, Any]:
    """The stage's part of ``report.json``: counts per step and timings (seconds), JSON-ready."""
    sparse, dense = result.sparse, result.dense
    failed = [name for name, ok in zip(result.names, result.registered, strict=True) if not ok]
    return {
        "poses": {
            "mode": "known" if sparse.known_poses else "sfm",
            "views": len(result.names),
            "registered_views": int(sum(result.registered)),
            "unregistered": failed,
            "sparse_points": len(sparse.points),
            "mean_reprojection_error_px": float(sparse.mean_reprojection_error),
            "fallback_images": bool(sparse.fallback),  # sfm.grey 'auto': SfM on I_int after I_min left views out
            "frontier": sparse.frontier,  # sfm.frontier_weight: the poses held to the masks' tangencies
            "silhouette_registered": list(sparse.silhouette_registered),  # sfm.silhouette_register_px
            "silhouette_refused": dict(sparse.silhouette_refused),  # views the silhouette search left out, and why
            "timings": {k: float(v) for k, v in sparse.timings.items()},
            "extras": sparse.extras,  # each refinement after the mapping: its seconds and what it gave
        },
        "dense": {
            "backend": dense.backend,
            "points": len(dense.points),
            "valid_depths_per_view": dict(zip(result.names, dense.valid_depths, strict=True)),
            "fused_points_per_view": dict(zip(result.names, dense.fused_per_view, strict=True)),
            "grid": dense.grid,  # the CPU stereo grid, WxH (mvs.scale, min_grid_px, unmasked_full_grid_px)
            "window": dense.window,  # the CPU stereo's ZNCC window side
            # mvs.unmasked_full_min_consistent: the full grid's mean consistent fraction when it was not kept
            "full_grid_consistent": dense.full_grid_consistent,
        },
        "surface": {k: int(v) for k, v in result.surface.counts.items()}
        | {"components": [dict(c) for c in result.surface.components]},
        "subdivision": {
            "rounds": int(result.subdivision_rounds),
            "max_area_px": float(result.subdivision_max_area_px),
            "converged": bool(result.subdivision_converged),
            "vertices": len(result.vertices),
            "faces": len(result.faces),
            "visible_vertex_fraction": float(result.visibility.any(axis=1).mean())
            if len(result.vertices)
            else 0.0,
        },
        "isolation": None if result.isolation is None else result.isolation.to_dict(),  # geometry.isolate
        "hull_fit": None if result.hull_fit is None else result.hull_fit.to_dict(),  # surface.hull_tolerance_px
        "timings": {k: float(v) for k, v in result.timings.items()},
    }
