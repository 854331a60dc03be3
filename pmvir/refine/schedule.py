"""The staged refinement: initialization, gauge, parametrization, and the three-stage schedule.

Unknowns (paper section 4.3): vertex positions X, per-vertex RGB albedo K,
per-view SH coefficients L_basis (9) and RGB scales L_scale (3).

* Initialization (paper section 5.1): K = mean of the observed colours of the
  vertex over its usable views, L_basis = [1, 0, ..., 0], L_scale = [1, 1, 1].
* Gauge: K * L_scale (per channel) and L_basis * L_scale (per view) are only
  determined up to scale, and E_psm would shrink K along that direction. We fix
  L0 = 1 in every view and L_scale of view 0 at [1, 1, 1]; everything else is free.
  (The metrics remove a per-channel scale anyway.)
* Vertex motion (``solver.vertex_motion``): ``"free"`` (default) X = X0 + h D, three
  unknowns per vertex; ``"normal"`` X = X0 + h d n0 along the unit normal at the
  start of the stage. h is the mean edge length, so unknowns are O(1). On the
  synthetic bumpy-sphere tests free motion reached about 0.8x the accuracy error of
  normal-only motion in the same number of iterations: a vertex on a slope of a
  missing bump must also move sideways to reach the true surface point it samples.
* Albedo (``solver.albedo_solve``): ``"projected"`` (default) sets K at every evaluation to
  its exact minimizer over K >= 0 given X and L (:mod:`pmvir.refine.albedo`) and L-BFGS
  runs on X and L only; ``"joint"`` makes K L-BFGS unknowns too, clamped at 0 after each
  stage. The projected form converged several times faster in our tests.
* Preconditioning: L-BFGS's initial inverse Hessian is a graph smoother on the
  vertex-motion block (:class:`pmvir.refine.mesh_ops.GraphSmoother`); SH and scale
  unknowns of view c are scaled by 1/sqrt(sum of the pair weights 1/|V(i)| of the view).
* Coarse to fine (``stages.coarse``): the first stages may run on the surface one sqrt(3) step
  coarser, their motion then carried to the subdivided surface (:mod:`pmvir.refine.coarse`).
* Relaxation (``surface.relax_iterations``): after the last stage the vertices are spread evenly
  over the refined surface (:mod:`pmvir.refine.relax`) and the albedo solved there again.
* Fairing (``surface.fair_iterations``): the last move of the surface, after the hull and rim
  fits, removes ripples shorter than about 11 pixels: five edges where the median face projects to
  2 px^2, more edges on a finer mesh (:func:`pmvir.refine.relax.fair_taubin`).
* Stages: :func:`prepare_stage` fixes a stage's data at the current geometry (visibility,
  pairs, E_psm weights, E_pol's DoP mask and DoP weights, n0 and h), :func:`solve_stage`
  minimizes its cost; :func:`refine_surface` is the loop over the two.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import torch

from pmvir.camera import Camera
from pmvir.config import RefineOptions
from pmvir.errors import ConfigError
from pmvir.geometry.silhouette.hull_fit import HullFit, RimFit
from pmvir.progress import Progress
from pmvir.refine.coarse import CoarseMesh, Lift
from pmvir.refine.lighting_fit import final_lighting_fit, prefit_lighting
from pmvir.refine.mesh_ops import (
    check_mesh,
    vertex_normals,
)
from pmvir.refine.offset import OffsetScan
from pmvir.refine.relax import Fairing
from pmvir.refine.sampling import (
    Observation,
)
from pmvir.refine.solve import solve_stage
from pmvir.refine.stage_setup import initial_unknowns, make_setup, prepare_stage, setup_for_mesh
from pmvir.refine.state import RefineResult, RefineSetup, StageLog, Unknowns, VisibilityFn
from pmvir.refine.surface_moves import fair_surface, hold_inside_hull, move_to_rims, scan_offset

#: Share of the refinement's progress taken by the offset scans outside the stages, per ``offset_scan.mode``.
_SCAN_WEIGHT = {"off": 0.0, "start": 0.01, "stages": 0.02}
#: Share of the refinement's progress taken by the final lighting fit (``lighting.coupling`` > 0).
_LIGHTING_WEIGHT = 0.03


def refine_surface(
    vertices: np.ndarray,
    faces: np.ndarray,
    cameras: Sequence[Camera],
    observations: Sequence[Observation],
    visibility: np.ndarray,
    *,
    options: RefineOptions | None = None,
    visibility_fn: VisibilityFn | None = None,
    progress: Progress | None = None,
    masks: Sequence[np.ndarray | None] | None = None,
    coarse: CoarseMesh | None = None,
) -> RefineResult:
    """Polarimetric MVIR: refine a mesh, its albedo and per-view lighting (paper sections 4.3, 5.1).

    Args:
        vertices: (N, 3) initial positions (world units).
        faces: (F, 3) int triangles, counter-clockwise seen from outside.
        cameras: V cameras (cam_from_world, COLMAP pixels).
        observations: V decoded views, same sizes as the cameras; their ``intensity`` is
            I_min or I_int as ``options.pho.intensity`` says (see :func:`observation_from_decoded`).
        visibility: (N, V) bool initial visibility.
        options: the stage's options (default :class:`pmvir.config.RefineOptions`).
        visibility_fn: recomputes visibility from (vertices, faces) between stages (e.g.
            :func:`make_visibility_fn`); without it the initial visibility is kept.
        progress: one step ``stage s`` per stage, reporting its iterations; polled there for cancellation.
        masks: the V views' object masks (None entries: no mask); with ``surface.hull_tolerance_px`` the
            surface is held inside their visual hull after every offset scan and after the last stage
            (:func:`pmvir.geometry.silhouette.hull_fit.fit_inside_hull`), and with ``surface.rim_fit_gain`` the shoulders
            whose rims lie inside them move out after the last stage
            (:func:`pmvir.geometry.silhouette.hull_fit.fit_to_rims`). None: neither.
        coarse: the surface one sqrt(3) step before ``vertices, faces`` (its vertices on the same surface);
            the first ``options.stages.coarse`` stages run on it. None: every stage on ``vertices, faces``.

    Returns:
        :class:`RefineResult`.

    Raises:
        MeshError: malformed mesh. ConfigError: inconsistent inputs or options.
        ReconstructionError: no vertex has a usable view. CanceledError: the progress object was
        asked to cancel.
    """
    t_start = time.perf_counter()
    opts = options if options is not None else RefineOptions()
    progress = progress or Progress.none()
    verts_np, faces_np = check_mesh(vertices, faces)
    n, n_views = len(verts_np), len(cameras)
    fine_vis = np.asarray(visibility)
    if fine_vis.shape != (n, n_views):
        raise ConfigError(f"expected ({n}, {n_views}) visibility, got {fine_vis.shape}")
    n_coarse = opts.stages.coarse if coarse is not None else 0
    start, start_faces, vis, lift = _start_mesh(verts_np, faces_np, fine_vis, coarse if n_coarse > 0 else None)
    setup = make_setup(start_faces, len(start), cameras, observations, opts=opts, visibility_fn=visibility_fn)
    state = initial_unknowns(
        start, n_views, sh_order=opts.lighting.sh_order, device=setup.device, dtype=setup.dtype
    )
    if masks is not None and len(masks) != n_views:
        raise ConfigError(f"expected {n_views} masks (one per view), got {len(masks)}")
    hull_fits: list[HullFit] = []

    def scanned(state: Unknowns, scans: list[OffsetScan], p: Progress) -> tuple[Unknowns, list[OffsetScan]]:
        state, scans = scan_offset(setup, state, opts, scans, p)
        if scans[-1].applied:
            state = hold_inside_hull(setup, state, masks, hull_fits)
        return state, scans

    scans: list[OffsetScan] = []
    t_scan = time.perf_counter()
    if opts.offset_scan.mode != "off":
        with progress.step("offset scan", weight=0.01) as p:
            state, scans = scanned(state, scans, p)
    timings = {"setup": t_scan - t_start, "offset_scan": time.perf_counter() - t_scan}
    logs: list[StageLog] = []
    stage_timings: list[dict[str, float]] = []
    for s in range(opts.n_stages):
        t_stage = time.perf_counter()
        parts: dict[str, float] = {}
        lighting = _LIGHTING_WEIGHT if opts.lighting.coupling > 0.0 else 0.0
        stage_weight = (1.0 - _SCAN_WEIGHT[opts.offset_scan.mode] - lighting) / opts.n_stages
        with progress.step(f"stage {s + 1}", weight=stage_weight) as p:
            p.update(0.0, f"of {opts.n_stages}: visibility and pairs")
            if lift is not None and s == n_coarse:
                t = time.perf_counter()
                setup, state = _to_fine(setup, state, lift, faces_np)
                vis = fine_vis
                parts["lift"] = time.perf_counter() - t
            if s > 0 and opts.offset_scan.mode == "stages":
                t = time.perf_counter()
                state, scans = scanned(state, scans, p)
                parts["offset_scan"] = time.perf_counter() - t  # with the hull fit after an applied scan
            t = time.perf_counter()
            stage, state = prepare_stage(setup, state, vis, s)
            parts["prepare"] = time.perf_counter() - t
            vis = stage.visibility
            if s == 0 and opts.lighting.prefit_iterations > 0:
                t = time.perf_counter()
                with p.step("lighting", weight=0.1) as q:
                    stage, state = prefit_lighting(setup, stage, state, progress=q)
                parts["lighting_prefit"] = time.perf_counter() - t
            t = time.perf_counter()
            state, log = solve_stage(setup, stage, state, progress=p)
            parts["solve"] = time.perf_counter() - t
        logs.append(log)
        timings[f"stage_{s + 1}"] = time.perf_counter() - t_stage
        stage_timings.append(parts)

    state, scans, rim_fit, fairing = _final_moves(setup, state, masks, scans, hull_fits, timings, progress)
    lighting_fit = None
    if opts.lighting.coupling > 0.0:
        t_fit = time.perf_counter()
        with progress.step("lighting", weight=_LIGHTING_WEIGHT) as p:
            state, lighting_fit = final_lighting_fit(setup, state, vis, progress=p)
        timings["lighting"] = time.perf_counter() - t_fit
    with torch.no_grad():
        normals = vertex_normals(state.vertices, setup.topo.faces).cpu().numpy().astype(np.float32)
    timings["total"] = time.perf_counter() - t_start
    return RefineResult(
        vertices=state.vertices.cpu().numpy().astype(np.float64),
        normals=normals,
        albedo=state.albedo.cpu().numpy().astype(np.float32),
        sh=state.sh[:, :9].cpu().numpy().astype(np.float32),
        sh_high=state.sh[:, 9:].cpu().numpy().astype(np.float32),
        rgb_scale=state.rgb_scale.cpu().numpy().astype(np.float32),
        visibility=vis.astype(bool),
        stages=logs,
        timings=timings,
        stage_timings=stage_timings,
        intensity_factor=setup.units,
        offset_scans=scans,
        hull_fits=hull_fits,
        rim_fit=rim_fit,
        fairing=fairing,
        lighting_fit=lighting_fit,
        coarse_vertices=len(start) if lift is not None else 0,
    )


def _final_moves(
    setup: RefineSetup,
    state: Unknowns,
    masks: Sequence[np.ndarray | None] | None,
    scans: list[OffsetScan],
    hull_fits: list[HullFit],
    timings: dict[str, float],
    progress: Progress,
) -> tuple[Unknowns, list[OffsetScan], RimFit | None, Fairing | None]:
    """The moves of the surface after the last stage, in order: the offset scan (``offset_scan.mode``
    "stages"), the hull fit and the rim fit (with masks), the fairing; each one's seconds go into
    ``timings``. Returns the state, the scans so far, the rim fit and the fairing (None when not run)."""
    opts = setup.opts
    if opts.offset_scan.mode == "stages":
        t_scan = time.perf_counter()
        with progress.step("offset scan", weight=0.01) as p:
            state, scans = scan_offset(setup, state, opts, scans, p)
        timings["offset_scan"] += time.perf_counter() - t_scan
    if masks is not None and opts.surface.hull_tolerance_px is not None:
        t_hull = time.perf_counter()
        state = hold_inside_hull(setup, state, masks, hull_fits)
        timings["hull_fit"] = time.perf_counter() - t_hull
    rim_fit = None
    if masks is not None and opts.surface.rim_fit_gain > 0.0:
        t_rim = time.perf_counter()
        state, rim_fit = move_to_rims(setup, state, masks)
        timings["rim_fit"] = time.perf_counter() - t_rim
    fairing = None
    if opts.surface.fair_iterations > 0:
        t_fair = time.perf_counter()
        state, fairing = fair_surface(setup, state)
        timings["fairing"] = time.perf_counter() - t_fair
    return state, scans, rim_fit, fairing


def _start_mesh(
    vertices: np.ndarray, faces: np.ndarray, visibility: np.ndarray, coarse: CoarseMesh | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, Lift | None]:
    """The mesh the first stage runs on (``coarse`` where given), its visibility, and the lift to the
    subdivided mesh (None without ``coarse``)."""
    if coarse is None:
        return vertices, faces, visibility, None
    coarse.check(visibility.shape[1])
    start, start_faces = check_mesh(coarse.vertices, coarse.faces)
    return start, start_faces, np.asarray(coarse.visibility), Lift.between(start, start_faces, vertices)


def _to_fine(setup: RefineSetup, state: Unknowns, lift: Lift, faces_np: np.ndarray) -> tuple[RefineSetup, Unknowns]:
    """The coarse stages' positions and albedo carried to the subdivided surface, and its set-up."""
    with torch.no_grad():
        vertices = lift.apply(state.vertices, offsets=True)
        albedo = lift.apply(state.albedo, offsets=False)
    return setup_for_mesh(setup, faces_np, len(vertices)), replace(state, vertices=vertices, albedo=albedo)
