"""The staged refinement: initialization, gauge, parametrization, and the three-stage schedule.

Unknowns (paper section 4.3): vertex positions X, per-vertex RGB albedo K,
per-view SH coefficients L_basis (9) and RGB scales L_scale (3).

* Initialization (paper section 5.1): K = mean of the observed colours of the
  vertex over its usable views, L_basis = [1, 0, ..., 0], L_scale = [1, 1, 1].
* Gauge: K * L_scale (per channel) and L_basis * L_scale (per view) are only
  determined up to scale, and E_psm would shrink K along that direction. We fix
  L0 = 1 in every view and L_scale of view 0 at [1, 1, 1]; everything else is free.
  (The metrics remove a per-channel scale anyway.)
* Vertex motion (``vertex_motion``): ``"free"`` (default) X = X0 + h D, three
  unknowns per vertex; ``"normal"`` X = X0 + h d n0 along the unit normal at the
  start of the stage. h is the mean edge length, so unknowns are O(1). On the
  synthetic bumpy-sphere tests free motion reached about 0.8x the accuracy error of
  normal-only motion in the same number of iterations: a vertex on a slope of a
  missing bump must also move sideways to reach the true surface point it samples.
* Albedo (``albedo_solve``): ``"projected"`` (default) sets K at every evaluation to
  its exact minimizer given X and L (:mod:`pmvir.refine.albedo`) and L-BFGS runs on
  X and L only; ``"joint"`` makes K L-BFGS unknowns too. Same cost, same minimizers;
  the projected form converged several times faster in our tests.
* Preconditioning: L-BFGS's initial inverse Hessian is a graph smoother on the
  vertex-motion block (:class:`pmvir.refine.mesh_ops.GraphSmoother`); SH and scale
  unknowns of view c are scaled by 1/sqrt(sum of the pair weights 1/|V(i)| of the view).
* Between stages the pairs (visibility), E_psm weights, E_pol's DoP mask, n0 and h
  are recomputed at the refined geometry.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from pmvir.camera import Camera
from pmvir.config import RefineOptions
from pmvir.errors import ConfigError, ReconstructionError
from pmvir.progress import Progress
from pmvir.refine.albedo import AlbedoSolver
from pmvir.refine.energy import StageProblem, energy_terms, psm_weights, total_energy
from pmvir.refine.lbfgs import minimize_lbfgs
from pmvir.refine.mesh_ops import (
    GraphSmoother,
    check_mesh,
    face_adjacency,
    mean_edge_length,
    unique_edges,
    vertex_normals,
)
from pmvir.refine.sampling import (
    Observation,
    PairSet,
    ViewStack,
    build_view_stack,
    sample_pairs,
    select_pairs,
)

#: vertices (N, 3) float64, faces (F, 3) int64 -> (N, V) bool visibility.
VisibilityFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class StageLog:
    """What one stage did.

    Attributes:
        index: stage number, 0-based.
        tau_pol, tau_gsm, tau_psm, t, k: the stage's parameters (tau_pol is 0 without E_pol).
        n_pairs: usable (vertex, view) pairs; n_observed: vertices with at least one.
        energies: per iteration (0 = the stage's start), the unweighted terms
            ``pho``, ``pol`` (only with E_pol), ``gsm``, ``psm`` and the weighted ``total``.
        grad_max: per iteration, the largest gradient component (preconditioned unknowns).
        evaluations: cost evaluations including line-search trials.
        stop_reason: see :class:`pmvir.refine.lbfgs.LbfgsResult`.
        seconds: wall time of the stage.
    """

    index: int
    tau_pol: float
    tau_gsm: float
    tau_psm: float
    t: float
    k: float
    n_pairs: int
    n_observed: int
    energies: list[dict[str, float]]
    grad_max: list[float]
    evaluations: int
    stop_reason: str
    seconds: float


@dataclass(frozen=True)
class RefineResult:
    """The refined surface, reflectance and lighting.

    Attributes:
        vertices: (N, 3) float64 refined positions (faces are unchanged).
        normals: (N, 3) float32 area-weighted unit vertex normals of the result.
        albedo: (N, 3) float32 linear RGB albedo K.
        sh: (V, 9) float32 pmvir-sh9 coefficients per view (L0 = 1, the gauge).
        rgb_scale: (V, 3) float32 RGB scale per view (view 0 = its initial [1, 1, 1]).
        visibility: (N, V) bool visibility used by the last stage.
        stages: one :class:`StageLog` per stage.
        timings: seconds: ``setup``, ``stage_1`` ... ``stage_S``, ``total``.
    """

    vertices: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    sh: np.ndarray
    rgb_scale: np.ndarray
    visibility: np.ndarray
    stages: list[StageLog] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)


def resolve_device(name: str) -> torch.device:
    """'auto' -> CUDA when available, else CPU; 'cuda...' must be available.

    Raises:
        ConfigError: CUDA asked for but not available.
    """
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if name.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError(f"device {name!r} requested but CUDA is not available")
    return torch.device(name)


def make_visibility_fn(
    cameras: Sequence[Camera], masks: Sequence[np.ndarray | None] | None = None, **kwargs
) -> VisibilityFn:
    """Bind :func:`pmvir.geometry.visibility.vertex_visibility` to cameras and masks (a :data:`VisibilityFn`)."""
    from pmvir.geometry.visibility import vertex_visibility

    def fn(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
        return vertex_visibility(vertices, faces, cameras, masks, **kwargs)

    return fn


@dataclass
class _Unknowns:
    """Current values between stages (torch, on the device)."""

    vertices: torch.Tensor  # (N, 3)
    albedo: torch.Tensor  # (N, 3)
    sh: torch.Tensor  # (V, 9)
    rgb_scale: torch.Tensor  # (V, 3)


class _Parametrization:
    """Flat, preconditioned unknowns z of one stage <-> (X, K, L_basis, L_scale).

    Blocks of z: vertex motion (N for "normal", 3N for "free"), albedo (3N, only when
    ``joint_albedo``),
    SH L1..L8 per view (8V), RGB scale of views 1..V-1 (3(V-1)).
    """

    def __init__(
        self, start: _Unknowns, pairs: PairSet, faces: torch.Tensor, h: float, motion: str, joint_albedo: bool
    ):
        n, v = start.vertices.shape[0], start.sh.shape[0]
        self.start, self.h, self.motion, self.n, self.v = start, h, motion, n, v
        self.joint_albedo = joint_albedo
        self.normal0 = vertex_normals(start.vertices, faces).detach()
        per_view = torch.zeros(v, dtype=start.sh.dtype, device=start.sh.device)
        per_view.index_add_(0, pairs.view, pairs.weight)
        self.precond = per_view.clamp_min(1.0).rsqrt()
        n_geo = n if motion == "normal" else 3 * n
        sizes = [n_geo, 3 * n if joint_albedo else 0, 8 * v, 3 * (v - 1)]
        self.bounds = np.cumsum([0] + sizes).tolist()

    def initial(self) -> torch.Tensor:
        z = torch.zeros(self.bounds[-1], dtype=self.start.albedo.dtype, device=self.start.albedo.device)
        b = self.bounds
        if self.joint_albedo:
            z[b[1] : b[2]] = self.start.albedo.reshape(-1)
        return z

    def preconditioner(self, smoother: GraphSmoother) -> Callable[[torch.Tensor], torch.Tensor]:
        """The L-BFGS preconditioner: ``smoother`` on the vertex-motion block, identity elsewhere."""
        b, n = self.bounds, self.n

        def apply(z: torch.Tensor) -> torch.Tensor:
            geo = z[b[0] : b[1]]
            geo = smoother(geo if self.motion == "normal" else geo.view(n, 3)).reshape(-1)
            return torch.cat([geo, z[b[1] :]])

        return apply

    def unpack(self, z: torch.Tensor) -> _Unknowns:
        """Unknowns at z; without ``joint_albedo`` the albedo is the stage's start value (a placeholder)."""
        b, n, v, s = self.bounds, self.n, self.v, self.start
        geo = z[b[0] : b[1]]
        if self.motion == "normal":
            vertices = s.vertices + self.h * geo[:, None] * self.normal0
        else:
            vertices = s.vertices + self.h * geo.view(n, 3)
        albedo = z[b[1] : b[2]].view(n, 3) if self.joint_albedo else s.albedo
        sh_rest = s.sh[:, 1:] + z[b[2] : b[3]].view(v, 8) * self.precond[:, None]
        sh = torch.cat([torch.ones_like(s.sh[:, :1]), sh_rest], dim=1)
        scale_rest = s.rgb_scale[1:] + z[b[3] : b[4]].view(v - 1, 3) * self.precond[1:, None]
        rgb_scale = torch.cat([s.rgb_scale[:1], scale_rest], dim=0)
        return _Unknowns(vertices, albedo, sh, rgb_scale)


def _stage_observations(
    vertices: torch.Tensor, faces: torch.Tensor, views, pairs: PairSet
) -> tuple[np.ndarray, np.ndarray, torch.Tensor | None]:
    """At the stage's start: (N, 3) mean observed RGB of each vertex over its pairs, (N,) bool
    'has a pair', and the (P,) DoP of every pair (None without polarization)."""
    with torch.no_grad():
        normals = vertex_normals(vertices, faces)
        smp = sample_pairs(vertices, normals, views, pairs)
        total = torch.zeros_like(vertices).index_add_(0, pairs.vertex, smp.intensity)
    count = pairs.count
    mean = total.cpu().numpy().astype(np.float64) / np.maximum(count, 1)[:, None]
    return mean, count > 0, smp.dop


class _IterationLog:
    """Collects the per-iteration energies of a stage and reports progress / polls cancellation."""

    def __init__(self, max_iterations: int, stage: int, n_stages: int, report, check_cancel):
        self.max_iterations, self.stage, self.n_stages = max_iterations, stage, n_stages
        self.report, self.check_cancel = report, check_cancel
        self.energies: list[dict[str, float]] = []
        self.grad_max: list[float] = []

    def __call__(self, it: int, value: float, gmax: float, named: dict[str, float]) -> None:
        self.energies.append(named)
        self.grad_max.append(gmax)
        s, n = self.stage, self.n_stages
        frac = min(it / self.max_iterations, 1.0)
        self.report((s + frac) / n, f"refine stage {s + 1}/{n} iteration {it}: E = {value:.6g}")
        self.check_cancel(f"at stage {s + 1} iteration {it}")


def _minimize(
    param: _Parametrization,
    problem: StageProblem,
    solver: AlbedoSolver | None,
    tau: tuple[float, float, float],
    smoother: GraphSmoother,
    opts: RefineOptions,
    log: _IterationLog,
    max_iterations: int,
):
    """L-BFGS on one parametrization of a stage's cost."""

    def fun(z: torch.Tensor):
        z = z.detach().requires_grad_(True)
        u = param.unpack(z)
        albedo = u.albedo if solver is None else solver
        terms = energy_terms(u.vertices, albedo, u.sh, u.rgb_scale, problem)
        total = total_energy(terms, tau_pol=tau[0], tau_gsm=tau[1], tau_psm=tau[2])
        (grad,) = torch.autograd.grad(total, z)
        named = {k: float(v.detach()) for k, v in terms.items()}
        named["total"] = float(total.detach())
        return named["total"], grad, named

    return minimize_lbfgs(
        fun,
        param.initial(),
        precondition=param.preconditioner(smoother),
        first_step=0.1,
        max_iterations=max_iterations,
        history_size=opts.history_size,
        rel_tolerance=opts.rel_tolerance,
        grad_tolerance=opts.grad_tolerance,
        on_iteration=log,
    )


def _accepted(
    param: _Parametrization, problem: StageProblem, solver: AlbedoSolver | None, z: torch.Tensor
) -> _Unknowns:
    """The unknowns at the accepted point z (with the projected albedo solved there)."""
    with torch.no_grad():
        u = param.unpack(z)
        if solver is not None:
            energy_terms(u.vertices, solver, u.sh, u.rgb_scale, problem)
            u.albedo = solver.current
    return _Unknowns(u.vertices.detach(), u.albedo.detach(), u.sh.detach(), u.rgb_scale.detach())


@dataclass(frozen=True)
class _Topology:
    """The mesh's fixed connectivity, on the device (and the edges in NumPy too)."""

    faces: torch.Tensor
    face_pairs: torch.Tensor
    has_neighbour: torch.Tensor
    edges: torch.Tensor
    edges_np: np.ndarray

    @classmethod
    def of(cls, faces_np: np.ndarray, device: torch.device) -> _Topology:
        edges_np = unique_edges(faces_np)
        fpairs_np = face_adjacency(faces_np)
        has_nb = np.bincount(fpairs_np[:, 0], minlength=len(faces_np)) > 0
        return cls(
            faces=torch.from_numpy(faces_np).to(device),
            face_pairs=torch.from_numpy(fpairs_np).to(device),
            has_neighbour=torch.from_numpy(has_nb).to(device),
            edges=torch.from_numpy(edges_np).to(device),
            edges_np=edges_np,
        )


def _stage_problem(
    topo: _Topology,
    views: ViewStack,
    pairs: PairSet,
    colour: np.ndarray,
    observed: np.ndarray,
    opts: RefineOptions,
    *,
    polarimetric: bool,
    pol_mask: torch.Tensor | None,
    t: float,
) -> tuple[StageProblem, np.ndarray]:
    """A stage's constants and its E_psm weights (from the observed colours at its start)."""
    w = psm_weights(
        colour,
        observed,
        topo.edges_np,
        sigma_chroma=opts.psm_sigma_chroma,
        sigma_log_intensity=opts.psm_sigma_log_intensity,
    )
    device, dtype = views.table.device, views.table.dtype
    problem = StageProblem(
        faces=topo.faces,
        face_pairs=topo.face_pairs,
        has_neighbour=topo.has_neighbour,
        edges=topo.edges,
        psm_weight=torch.from_numpy(w).to(device=device, dtype=dtype),
        views=views,
        pairs=pairs,
        polarimetric=polarimetric,
        pol_mask=pol_mask,
        k=opts.pol_k,
        dop_weight=opts.dop_weight,
        t=t,
        units=opts.intensity_units,
    )
    return problem, w


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
) -> RefineResult:
    """Polarimetric MVIR: refine a mesh, its albedo and per-view lighting (paper sections 4.3, 5.1).

    Args:
        vertices: (N, 3) initial positions (world units).
        faces: (F, 3) int triangles, counter-clockwise seen from outside.
        cameras: V cameras (cam_from_world, COLMAP pixels).
        observations: V decoded views, same sizes as the cameras; their ``intensity`` is
            I_min or I_int as ``options.intensity`` says (see :func:`observation_from_decoded`).
        visibility: (N, V) bool initial visibility.
        options: the stage's options (default :class:`pmvir.config.RefineOptions`).
        visibility_fn: recomputes visibility from (vertices, faces) between stages (e.g.
            :func:`make_visibility_fn`); without it the initial visibility is kept.
        progress: reports stage and iteration boundaries and is polled there for cancellation.

    Returns:
        :class:`RefineResult`.

    Raises:
        MeshError: malformed mesh. ConfigError: inconsistent inputs or options.
        ReconstructionError: no vertex has a usable view. CanceledError: the progress object was
        asked to cancel.
    """
    t_start = time.perf_counter()
    opts = options if options is not None else RefineOptions()
    verts_np, faces_np = check_mesh(vertices, faces)
    n, n_views = len(verts_np), len(cameras)
    device = resolve_device(opts.device)
    dtype = torch.float32 if opts.dtype == "float32" else torch.float64
    views = build_view_stack(
        cameras, observations, polarimetric=opts.polarimetric, device=device, dtype=dtype
    )
    vis = np.asarray(visibility)
    if vis.shape != (n, n_views):
        raise ConfigError(f"expected ({n}, {n_views}) visibility, got {vis.shape}")

    progress = progress or Progress.none()
    report, check_cancel = progress.update, progress.check_cancel

    topo = _Topology.of(faces_np, device)
    faces_t, edges_np = topo.faces, topo.edges_np
    smoother = GraphSmoother(
        edges_np,
        n,
        lam=opts.precondition_lambda,
        iterations=opts.precondition_iterations,
        device=device,
        dtype=dtype,
    )
    state = _Unknowns(
        vertices=torch.from_numpy(verts_np).to(device=device, dtype=dtype),
        albedo=torch.zeros((n, 3), dtype=dtype, device=device),
        sh=torch.zeros((n_views, 9), dtype=dtype, device=device),
        rgb_scale=torch.ones((n_views, 3), dtype=dtype, device=device),
    )
    state.sh[:, 0] = 1.0
    timings = {"setup": time.perf_counter() - t_start}
    logs: list[StageLog] = []
    n_stages = opts.n_stages

    for s in range(n_stages):
        check_cancel(f"before stage {s + 1}")
        t_stage = time.perf_counter()
        report(s / n_stages, f"refine stage {s + 1}/{n_stages}: visibility and pairs")
        cur_np = state.vertices.detach().cpu().numpy().astype(np.float64)
        if s > 0 and opts.refresh_visibility and visibility_fn is not None:
            vis = np.asarray(visibility_fn(cur_np, faces_np))
            if vis.shape != (n, n_views):
                raise ConfigError(f"visibility_fn returned shape {vis.shape}, expected ({n}, {n_views})")
        with torch.no_grad():
            normals_np = vertex_normals(state.vertices, faces_t).cpu().numpy().astype(np.float64)
        pairs = select_pairs(
            cur_np,
            vis,
            cameras,
            observations,
            device=device,
            dtype=dtype,
            normals=normals_np,
            min_cos=opts.min_view_cos,
            keep_best=opts.min_view_pairs,
        )
        if pairs.size == 0:
            raise ReconstructionError(
                f"stage {s + 1}: no vertex projects onto valid pixels of a view that sees it"
            )
        colour, observed, dop = _stage_observations(state.vertices, faces_t, views, pairs)
        if s == 0:
            fill = colour[observed].mean(axis=0)
            init = np.where(observed[:, None], colour, fill[None, :])
            state.albedo = torch.from_numpy(init).to(device=device, dtype=dtype)
        tau_pol = opts.tau_pol[s] if opts.polarimetric else 0.0
        tau_gsm, tau_psm, t_exp = opts.tau_gsm[s], opts.tau_psm[s], opts.gsm_exponent[s]
        problem, w = _stage_problem(
            topo,
            views,
            pairs,
            colour,
            observed,
            opts,
            polarimetric=opts.polarimetric,
            pol_mask=None if dop is None or opts.dop_min <= 0.0 else dop >= opts.dop_min,
            t=t_exp,
        )
        h = mean_edge_length(cur_np, edges_np)
        joint = opts.albedo_solve == "joint"
        tau = (tau_pol, tau_gsm, tau_psm)
        log = _IterationLog(opts.max_iterations, s, n_stages, report, check_cancel)
        param = _Parametrization(state, pairs, faces_t, h, opts.vertex_motion, joint)
        solver = None if joint else AlbedoSolver(pairs, edges_np, w, tau_psm, state.albedo)
        res = _minimize(param, problem, solver, tau, smoother, opts, log, opts.max_iterations)
        state = _accepted(param, problem, solver, res.x)
        seconds = time.perf_counter() - t_stage
        timings[f"stage_{s + 1}"] = seconds
        logs.append(
            StageLog(
                index=s,
                tau_pol=tau_pol,
                tau_gsm=tau_gsm,
                tau_psm=tau_psm,
                t=t_exp,
                k=opts.pol_k,
                n_pairs=pairs.size,
                n_observed=int(observed.sum()),
                energies=log.energies,
                grad_max=log.grad_max,
                evaluations=res.evaluations,
                stop_reason=res.reason,
                seconds=seconds,
            )
        )

    out_vertices = state.vertices.cpu().numpy().astype(np.float64)
    with torch.no_grad():
        normals = vertex_normals(state.vertices, faces_t).cpu().numpy().astype(np.float32)
    timings["total"] = time.perf_counter() - t_start
    report(1.0, "refine done")
    return RefineResult(
        vertices=out_vertices,
        normals=normals,
        albedo=state.albedo.cpu().numpy().astype(np.float32),
        sh=state.sh.cpu().numpy().astype(np.float32),
        rgb_scale=state.rgb_scale.cpu().numpy().astype(np.float32),
        visibility=vis.astype(bool),
        stages=logs,
        timings=timings,
    )
