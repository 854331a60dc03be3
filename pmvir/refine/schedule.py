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
  its exact minimizer given X and L (:mod:`pmvir.refine.albedo`) and L-BFGS runs on
  X and L only; ``"joint"`` makes K L-BFGS unknowns too. Same cost, same minimizers;
  the projected form converged several times faster in our tests.
* Preconditioning: L-BFGS's initial inverse Hessian is a graph smoother on the
  vertex-motion block (:class:`pmvir.refine.mesh_ops.GraphSmoother`); SH and scale
  unknowns of view c are scaled by 1/sqrt(sum of the pair weights 1/|V(i)| of the view).
* Relaxation (``surface.relax_iterations``): after the last stage the vertices are spread evenly
  over the refined surface (:mod:`pmvir.refine.relax`) and the albedo solved there again.
* Stages: :func:`prepare_stage` fixes a stage's data at the current geometry (visibility,
  pairs, E_psm weights, E_pol's DoP mask and DoP weights, n0 and h), :func:`solve_stage`
  minimizes its cost; :func:`refine_surface` is the loop over the two.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

import cv2
import numpy as np
import torch

from pmvir.camera import Camera
from pmvir.config import RefineOptions
from pmvir.errors import ConfigError, ReconstructionError
from pmvir.geometry.silhouette.hull_fit import HullFit, RimFit, fit_inside_hull, fit_to_rims
from pmvir.io.ply import vertex_normals as vertex_normals_np
from pmvir.progress import Progress
from pmvir.refine.albedo import AlbedoSolver
from pmvir.refine.energy import (
    StageProblem,
    azimuth,
    azimuth_distance,
    diffuse_view_factor,
    energy_terms,
    pair_light,
    psm_weights,
    total_energy,
)
from pmvir.refine.lbfgs import LbfgsResult, minimize_lbfgs
from pmvir.refine.mesh_ops import (
    GraphSmoother,
    check_mesh,
    face_adjacency,
    mean_edge_length,
    unique_edges,
    vertex_normals,
)
from pmvir.refine.offset import OffsetScan, photo_consistent_offset
from pmvir.refine.relax import carry_values, relax_tangentially
from pmvir.refine.sampling import (
    Observation,
    PairSamples,
    PairSet,
    ViewStack,
    build_view_stack,
    sample_pairs,
    select_pairs,
)
from pmvir.refine.shadowing import shadow_factors
from pmvir.sh import sh_term_count

#: vertices (N, 3) float64, faces (F, 3) int64 -> (N, V) bool visibility.
VisibilityFn = Callable[[np.ndarray, np.ndarray], np.ndarray]


@dataclass(frozen=True)
class StageLog:
    """What one stage did.

    Attributes:
        index: stage number, 0-based.
        tau_pol, tau_gsm, tau_psm, t, k: the stage's parameters (tau_pol is 0 without E_pol).
        n_pairs: usable (vertex, view) pairs; n_observed: vertices with at least one.
        pol_pairs: the pairs E_pol used (0 without E_pol).
        dop_floor: E_pol's DoP floor (see :func:`dop_floor`; the median of per-pair floors; 0 when
            every pair is kept; None when no pair was evidence and E_pol was off). With measured
            noise (``pol.aop_noise`` 'closure') an 'evidence' floor is on :func:`pol_evidence`'s scale,
            the DoP at the stage's median noise.
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
    pol_pairs: int
    dop_floor: float | None
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
        sh: (V, 9) float32 pmvir-sh9 coefficients per view (L0 = 1, the gauge). With
            ``lighting.sh_order`` > 2 they are the pmvir-sh9 part (the least-squares projection over the
            sphere) of the fitted shading.
        sh_high: (V, T - 9) float32 degree-3 and degree-4 coefficients of :func:`pmvir.sh.sh_basis`
            (T = 16 or 25); (V, 0) with ``lighting.sh_order`` 2.
        rgb_scale: (V, 3) float32 RGB scale per view (view 0 = its initial [1, 1, 1]).
        visibility: (N, V) bool visibility used by the last stage.
        stages: one :class:`StageLog` per stage.
        timings: seconds: ``setup``, ``offset_scan`` (the scans before stage 1 and after the last; those
            between stages count in their stage), ``stage_1`` ... ``stage_S``, ``hull_fit`` (with masks: the fit
            after the last stage; the fits after earlier scans count in their stage), ``rim_fit`` (when run),
            ``lighting`` (the final lighting fit, when run), ``total``.
        intensity_factor: what E_pho and E_psm multiplied intensities and albedos by
            (:func:`intensity_units`).
        offset_scans: the photo-consistent offsets scanned (and applied where the scan found one), in
            order: before stage 1, and with ``offset_scan.mode`` "stages" also before every later stage and
            after the last (:func:`pmvir.refine.offset.photo_consistent_offset`).
        hull_fits: the surface held inside the masks' visual hull (``surface.hull_tolerance_px`` with masks),
            in order: after every applied offset scan but the last, and after the last stage and scan.
        rim_fit: the shoulders moved out to the masks' rims after the last hull fit (``surface.rim_fit_gain`` > 0
            with masks), else None.
        lighting_fit: the final lighting fit's log (``lighting.coupling`` > 0; its time is
            ``timings["lighting"]``), else None.
    """

    vertices: np.ndarray
    normals: np.ndarray
    albedo: np.ndarray
    sh: np.ndarray
    rgb_scale: np.ndarray
    visibility: np.ndarray
    sh_high: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), np.float32))
    stages: list[StageLog] = field(default_factory=list)
    timings: dict[str, float] = field(default_factory=dict)
    intensity_factor: float = 0.0
    offset_scans: list[OffsetScan] = field(default_factory=list)
    hull_fits: list[HullFit] = field(default_factory=list)
    rim_fit: RimFit | None = None
    lighting_fit: StageLog | None = None

    def shading_coefficients(self) -> np.ndarray:
        """(V, T) every fitted coefficient of :func:`pmvir.sh.sh_basis` (``sh`` then ``sh_high``)."""
        return np.concatenate([self.sh, self.sh_high.reshape(len(self.sh), -1)], axis=1)


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
    sh: torch.Tensor  # (V, T): T = 9 (pmvir-sh9), 16 or 25 (refine.lighting.sh_order)
    rgb_scale: torch.Tensor  # (V, 3)


@dataclass(frozen=True)
class _Blocks:
    """Where each named block of unknowns lives in the flat vector z of a stage.

    Attributes:
        motion: vertex motion, N values ("normal") or 3N ("free", row-major (N, 3)).
        albedo: RGB albedo (3N, row-major (N, 3)); empty unless the albedo is a joint unknown.
        sh: SH coefficients L1..L(T-1) of every view ((T-1)V, row-major (V, T-1)); L0 is the gauge.
        scale: RGB scales of views 1..V-1 (3(V-1)); view 0's is the gauge.
        size: length of z.
    """

    motion: slice
    albedo: slice
    sh: slice
    scale: slice
    size: int

    @classmethod
    def layout(cls, *, n_vertices: int, n_views: int, n_sh: int, motion: str, joint_albedo: bool) -> _Blocks:
        sizes = {
            "motion": n_vertices if motion == "normal" else 3 * n_vertices,
            "albedo": 3 * n_vertices if joint_albedo else 0,
            "sh": (n_sh - 1) * n_views,
            "scale": 3 * (n_views - 1),
        }
        slices, start = {}, 0
        for name, size in sizes.items():
            slices[name] = slice(start, start + size)
            start += size
        return cls(**slices, size=start)


class _Parametrization:
    """Flat, preconditioned unknowns z of one stage <-> (X, K, L_basis, L_scale) (blocks: :class:`_Blocks`).

    Vertex motion is in units of the mean edge length h; SH and scale unknowns of view c are
    scaled by 1/sqrt(sum of the pair weights of view c) (see the module docstring).
    """

    def __init__(
        self,
        start: _Unknowns,
        *,
        pairs: PairSet,
        faces: torch.Tensor,
        h: float,
        motion: str,
        joint_albedo: bool,
    ):
        n, v = start.vertices.shape[0], start.sh.shape[0]
        self.start, self.h, self.motion, self.n, self.v = start, h, motion, n, v
        self.joint_albedo = joint_albedo
        self.normal0 = vertex_normals(start.vertices, faces).detach()
        per_view = torch.zeros(v, dtype=start.sh.dtype, device=start.sh.device)
        per_view.index_add_(0, pairs.view, pairs.weight)
        self.precond = per_view.clamp_min(1.0).rsqrt()
        self.blocks = _Blocks.layout(
            n_vertices=n, n_views=v, n_sh=start.sh.shape[1], motion=motion, joint_albedo=joint_albedo
        )

    def initial(self) -> torch.Tensor:
        z = torch.zeros(self.blocks.size, dtype=self.start.albedo.dtype, device=self.start.albedo.device)
        if self.joint_albedo:
            z[self.blocks.albedo] = self.start.albedo.reshape(-1)
        return z

    def preconditioner(self, smoother: GraphSmoother) -> Callable[[torch.Tensor], torch.Tensor]:
        """The L-BFGS preconditioner: ``smoother`` on the vertex-motion block, identity elsewhere."""
        motion, n = self.blocks.motion, self.n

        def apply(z: torch.Tensor) -> torch.Tensor:
            geo = z[motion]
            geo = smoother(geo if self.motion == "normal" else geo.view(n, 3)).reshape(-1)
            return torch.cat([geo, z[motion.stop :]])

        return apply

    def unpack(self, z: torch.Tensor) -> _Unknowns:
        """Unknowns at z; without ``joint_albedo`` the albedo is the stage's start value (a placeholder)."""
        blocks, s = self.blocks, self.start
        motion = z[blocks.motion]
        if self.motion == "normal":
            vertices = s.vertices + self.h * motion[:, None] * self.normal0
        else:
            vertices = s.vertices + self.h * motion.view(self.n, 3)
        albedo = z[blocks.albedo].view(self.n, 3) if self.joint_albedo else s.albedo
        sh_rest = s.sh[:, 1:] + z[blocks.sh].view(self.v, -1) * self.precond[:, None]
        sh = torch.cat([torch.ones_like(s.sh[:, :1]), sh_rest], dim=1)
        scale_rest = s.rgb_scale[1:] + z[blocks.scale].view(self.v - 1, 3) * self.precond[1:, None]
        rgb_scale = torch.cat([s.rgb_scale[:1], scale_rest], dim=0)
        return _Unknowns(vertices, albedo, sh, rgb_scale)


def _stage_observations(
    vertices: torch.Tensor, faces: torch.Tensor, views: ViewStack, pairs: PairSet
) -> tuple[np.ndarray, np.ndarray, PairSamples]:
    """At the stage's start: (N, 3) mean observed RGB of each vertex over its pairs, (N,) bool
    'has a pair', and the samples of every pair there (their DoP fixes E_pol's masks and weights)."""
    with torch.no_grad():
        normals = vertex_normals(vertices, faces)
        smp = sample_pairs(vertices, normals, views, pairs, with_noise=True)
        total = torch.zeros_like(vertices).index_add_(0, pairs.vertex, smp.intensity)
    count = pairs.count
    mean = total.cpu().numpy().astype(np.float64) / np.maximum(count, 1)[:, None]
    return mean, count > 0, smp


class _IterationLog:
    """Collects the per-iteration energies of a stage and reports them through the stage's progress."""

    def __init__(self, *, max_iterations: int, progress: Progress):
        self.max_iterations, self.progress = max_iterations, progress
        self.energies: list[dict[str, float]] = []
        self.grad_max: list[float] = []

    def __call__(self, it: int, value: float, gmax: float, named: dict[str, float]) -> None:
        self.energies.append(named)
        self.grad_max.append(gmax)
        self.progress.check_cancel(f"at iteration {it}")
        self.progress.update(min(it / self.max_iterations, 1.0), f"iteration {it}: E = {value:.6g}")


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


@dataclass(frozen=True)
class _Setup:
    """What every stage shares: the inputs as tensors, the mesh's connectivity and the options."""

    faces_np: np.ndarray
    topo: _Topology
    cameras: Sequence[Camera]
    observations: Sequence[Observation]
    views: ViewStack
    smoother: GraphSmoother
    visibility_fn: VisibilityFn | None
    opts: RefineOptions
    device: torch.device
    dtype: torch.dtype
    units: float


@dataclass(frozen=True)
class StageWeights:
    """One stage's weights of the cost ``E_pho + tau_pol E_pol + tau_gsm E_gsm + tau_psm E_psm
    + tau_light E_light``.

    Attributes:
        tau_pol: tau1 (0 without E_pol); tau_gsm: tau2; tau_psm: tau3; t: E_gsm's exponent;
        tau_light: E_light's weight (0 in the stages; ``lighting.coupling`` in the final lighting fit).
    """

    tau_pol: float
    tau_gsm: float
    tau_psm: float
    t: float
    tau_light: float = 0.0

    @classmethod
    def of_stage(cls, opts: RefineOptions, s: int) -> StageWeights:
        return cls(
            tau_pol=opts.stages.tau_pol[s] if opts.pol.enabled else 0.0,
            tau_gsm=opts.stages.tau_gsm[s],
            tau_psm=opts.stages.tau_psm[s],
            t=opts.stages.gsm_exponent[s],
        )


@dataclass(frozen=True)
class _Stage:
    """A stage's fixed data, chosen at its start (see :func:`prepare_stage`)."""

    index: int
    weights: StageWeights
    visibility: np.ndarray
    pairs: PairSet
    problem: StageProblem
    psm_weight: np.ndarray
    n_observed: int
    h: float
    dop_floor: torch.Tensor | float | None
    pol_pairs: int
    pho_signal: float  # E_pho's value with nothing rendered, at the stage's start (E_light's scale)


def prepare_stage(
    setup: _Setup, state: _Unknowns, visibility: np.ndarray, s: int
) -> tuple[_Stage, _Unknowns]:
    """Fix stage ``s``'s data at the current geometry: visibility, pairs, E_pol's DoP mask and
    weights, E_psm's weights, the motion scale h; on the first stage also the initial albedo.

    Returns:
        the stage and the unknowns to start it from.

    Raises:
        ConfigError: ``visibility_fn`` returned the wrong shape.
        ReconstructionError: no usable pair.
    """
    opts, faces_np = setup.opts, setup.faces_np
    cur_np = state.vertices.detach().cpu().numpy().astype(np.float64)
    n, n_views = len(cur_np), len(setup.cameras)
    if s > 0 and opts.views.refresh_visibility and setup.visibility_fn is not None:
        visibility = np.asarray(setup.visibility_fn(cur_np, faces_np))
        if visibility.shape != (n, n_views):
            raise ConfigError(f"visibility_fn returned shape {visibility.shape}, expected ({n}, {n_views})")
    with torch.no_grad():
        normals_np = vertex_normals(state.vertices, setup.topo.faces).cpu().numpy().astype(np.float64)
    pairs = select_pairs(
        cur_np,
        visibility,
        setup.cameras,
        setup.observations,
        device=setup.device,
        dtype=setup.dtype,
        normals=normals_np,
        min_cos=opts.views.min_cos,
        keep_best=opts.views.min_pairs,
    )
    if pairs.size == 0:
        raise ReconstructionError(
            f"stage {s + 1}: no vertex projects onto valid pixels of a view that sees it"
        )
    colour, observed, samples = _stage_observations(state.vertices, setup.topo.faces, setup.views, pairs)
    if s == 0:
        fill = colour[observed].mean(axis=0)
        init = np.where(observed[:, None], colour, fill[None, :])
        state = replace(state, albedo=torch.from_numpy(init).to(device=setup.device, dtype=setup.dtype))
    weights = StageWeights.of_stage(opts, s)
    psm_weight = psm_weights(
        colour,
        observed,
        setup.topo.edges_np,
        sigma_chroma=opts.pho.psm_sigma_chroma,
        sigma_log_intensity=opts.pho.psm_sigma_log_intensity,
    )
    light_factor = _shadow_factor(setup, state, pairs, normals_np)
    robust = opts.pho.robust != "none" and s > 0  # stage 1 starts from uniform lighting: no residuals yet
    pho_weight = _robust_pho_weights(setup, state, pairs, samples, light_factor) if robust else None
    floor = _stage_dop_floor(samples, opts)
    problem = _stage_problem(
        setup,
        pairs,
        samples,
        psm_weight,
        t=weights.t,
        pho_weight=pho_weight,
        floor=floor,
        light_factor=light_factor,
    )
    stage = _Stage(
        index=s,
        weights=weights,
        visibility=visibility,
        pairs=pairs,
        problem=problem,
        psm_weight=psm_weight,
        n_observed=int(observed.sum()),
        h=mean_edge_length(cur_np, setup.topo.edges_np),
        dop_floor=floor,
        pol_pairs=_pol_pair_count(samples, problem) if opts.pol.enabled else 0,
        pho_signal=_pho_signal(samples, problem),
    )
    return stage, state


def _pho_signal(samples: PairSamples, problem: StageProblem) -> float:
    """E_pho with nothing rendered: every pair's observed intensity squared, weighted as E_pho weights it."""
    w = problem.pairs.weight if problem.pho_weight is None else problem.pairs.weight * problem.pho_weight
    with torch.no_grad():
        return float((((samples.intensity * problem.units) ** 2).sum(-1) * w).sum())


def _stage_dop_floor(samples: PairSamples, opts: RefineOptions) -> torch.Tensor | float | None:
    """E_pol's DoP floor for a stage (:func:`dop_floor`), None where every pair is kept (no
    polarization, or ``pol.dop_min`` 0 with a fixed floor)."""
    if not opts.pol.enabled or samples.dop is None:
        return None
    floor = dop_floor(samples, opts)
    return None if isinstance(floor, float) and floor <= 0.0 else floor


def _pol_pair_count(samples: PairSamples, problem: StageProblem) -> int:
    """The pairs E_pol uses at the stage's start (defined AoP, DoP at or above the floor)."""
    if samples.aop_defined is None:
        return 0
    used = samples.aop_defined if problem.pol_mask is None else samples.aop_defined & problem.pol_mask
    return int(used.sum())


def _floor_summary(floor: torch.Tensor | float | None) -> float | None:
    """The stage's DoP floor as one number for the log: 0 (every pair kept), the floor, its median
    (per-pair floors), or None (no pair is evidence: E_pol off)."""
    if floor is None:
        return 0.0
    if isinstance(floor, torch.Tensor):
        return float(floor.median())
    return None if math.isinf(floor) else floor


def prefit_lighting(
    setup: _Setup, stage: _Stage, state: _Unknowns, *, progress: Progress
) -> tuple[_Stage, _Unknowns]:
    """Before the first stage: fit the lighting (and the projected albedo) to the initial surface
    with the geometry held (``lighting.prefit_iterations``), so that the first stage starts from
    lighting that explains the images; with ``pho.robust`` the first stage's Cauchy weights are then
    taken from the residuals of that fit (otherwise it would have none: it starts from uniform
    lighting), and specular residue loses its pull from the first stage on.

    With ``pho.shadowing`` the first stage's shadow factors are taken again under the fitted lighting.

    Returns:
        the first stage (with its robust weights) and the unknowns after the fit.
    """
    opts = setup.opts
    state, _ = solve_stage(
        setup,
        stage,
        state,
        progress=progress,
        max_iterations=opts.lighting.prefit_iterations,
        freeze_motion=True,
    )
    robust = opts.pho.robust != "none" and opts.pho.robust_first_stage
    if not robust and opts.pho.shadowing == "none":
        return stage, state
    _, _, samples = _stage_observations(state.vertices, setup.topo.faces, setup.views, stage.pairs)
    light_factor = _shadow_factor(setup, state, stage.pairs, None)
    pho_weight = _robust_pho_weights(setup, state, stage.pairs, samples, light_factor) if robust else None
    problem = _stage_problem(
        setup,
        stage.pairs,
        samples,
        stage.psm_weight,
        t=stage.weights.t,
        pho_weight=pho_weight,
        floor=stage.dop_floor,
        light_factor=light_factor,
    )
    return replace(stage, problem=problem), state


def final_lighting_fit(
    setup: _Setup, state: _Unknowns, visibility: np.ndarray, *, progress: Progress
) -> tuple[_Unknowns, StageLog]:
    """After the last stage: the lighting and albedo fitted again with the geometry held and E_light
    added (``lighting.coupling``, ``lighting.final_iterations``), starting from the stage's result.

    The last stage's weights, pairs and robust weights are taken again at the final surface; E_light's
    scale is E_pho's value with nothing rendered over the squared norm of the views' mean lighting
    at the start (:func:`pmvir.refine.energy.lighting_coupling_term`).
    """
    opts = setup.opts
    stage, state = prepare_stage(setup, state, visibility, opts.n_stages - 1)
    mean = (state.rgb_scale[:, :, None] * state.sh[:, None, :9]).mean(dim=0)
    scale = stage.pho_signal / max(float((mean * mean).sum()), 1e-12)
    stage = replace(
        stage,
        index=opts.n_stages,
        problem=replace(stage.problem, light_scale=scale),
        weights=replace(stage.weights, tau_light=opts.lighting.coupling),
    )
    return solve_stage(
        setup, stage, state, progress=progress, max_iterations=opts.lighting.final_iterations, freeze_motion=True
    )


def _shadow_factor(
    setup: _Setup, state: _Unknowns, pairs: PairSet, normals_np: np.ndarray | None
) -> torch.Tensor | None:
    """(P,) each pair's unblocked share of its irradiance at the current geometry and lighting
    (:func:`pmvir.refine.shadowing.shadow_factors`), None without ``pho.shadowing``."""
    opts = setup.opts
    if opts.pho.shadowing == "none":
        return None
    cur = state.vertices.detach().cpu().numpy().astype(np.float64)
    if normals_np is None:
        with torch.no_grad():
            normals_np = vertex_normals(state.vertices, setup.topo.faces).cpu().numpy().astype(np.float64)
    f = shadow_factors(
        cur,
        setup.faces_np,
        normals_np,
        state.sh.detach().cpu().numpy(),
        n_directions=opts.pho.shadow_directions,
        bounce=opts.pho.shadow_bounce,
        offset=mean_edge_length(cur, setup.topo.edges_np),
    )
    flat = torch.from_numpy(f.reshape(-1)).to(device=setup.device, dtype=setup.dtype)
    return flat.index_select(0, pairs.flat)


def _stage_problem(
    setup: _Setup,
    pairs: PairSet,
    samples: PairSamples,
    psm_weight: np.ndarray,
    *,
    t: float,
    pho_weight: torch.Tensor | None,
    floor: torch.Tensor | float | None,
    light_factor: torch.Tensor | None = None,
) -> StageProblem:
    """A stage's constants; E_pol's pair mask (DoP at or above ``floor``, see :func:`dop_floor`;
    None keeps every pair) and DoP weights are taken from the samples at the stage's start and
    stay fixed, like the pairs."""
    opts, topo = setup.opts, setup.topo
    evidence = pol_evidence(samples)
    pol_mask = None
    if samples.dop is not None and evidence is not None and floor is not None:
        pol_mask = _above_floor(samples.dop, evidence, floor, opts)
    pol_weight = evidence if opts.pol.dop_weight else None
    if pol_weight is not None and opts.pol.dop_weight_power != 1.0:
        pol_weight = pol_weight.clamp_min(0.0) ** opts.pol.dop_weight_power
    if pol_weight is not None and opts.pol.dop_weight_normalized:
        used = pol_weight if pol_mask is None else pol_weight[pol_mask]
        pol_weight = pol_weight / (used.mean() if used.numel() else pol_weight.new_tensor(1.0)).clamp_min(
            1e-6
        )
    return StageProblem(
        faces=topo.faces,
        face_pairs=topo.face_pairs,
        has_neighbour=topo.has_neighbour,
        edges=topo.edges,
        psm_weight=torch.from_numpy(psm_weight).to(device=setup.device, dtype=setup.dtype),
        views=setup.views,
        pairs=pairs,
        polarimetric=opts.pol.enabled,
        pol_mask=pol_mask,
        pol_weight=pol_weight,
        k=opts.pol.k,
        t=t,
        units=setup.units,
        pho_weight=pho_weight,
        diffuse_fresnel_ior=opts.pho.diffuse_fresnel_ior,
        diffuse_dop_ior=opts.pho.diffuse_dop_ior,
        light_factor=light_factor,
    )


def pol_evidence(samples: PairSamples) -> torch.Tensor | None:
    """(P,) what E_pol weights and floors each pair by: its DoP, in units of its own AoP noise.

    With the views' measured polarization noise sigma (``refine.pol.aop_noise`` 'closure',
    :func:`pmvir.polarization.noise.closure_noise`): ``rho * m / sigma`` with m the median sigma
    over the stage's pairs, i.e. the AoP's signal-to-noise ratio rho / sigma scaled to read as a
    DoP at the median noise. Unmeasured (NaN) noise counts as m; sigma is held above m / 4, so no
    pair outweighs others by noise alone more than 16-fold at ``pol.dop_weight_power`` 2. Without noise
    maps: the DoP itself. None without polarization.
    """
    if samples.dop is None or samples.aop_noise is None:
        return samples.dop
    noise = samples.aop_noise
    measured = torch.isfinite(noise) & (noise > 0)
    if not bool(measured.any()):
        return samples.dop
    ref = noise[measured].median()
    noise = torch.where(measured, noise, ref).clamp_min(0.25 * ref)
    return samples.dop * (ref / noise)


def _above_floor(
    dop: torch.Tensor, evidence: torch.Tensor, floor: torch.Tensor | float, opts: RefineOptions
) -> torch.Tensor:
    """E_pol's pair mask: the 'evidence' floor applies to :func:`pol_evidence` (and the DoP stays at
    or above ``pol.dop_min``); the 'fixed' and 'shot' floors to the DoP."""
    if opts.pol.dop_min_noise == "evidence":
        return (evidence >= floor) & (dop >= opts.pol.dop_min)
    return dop >= floor


def dop_floor(samples: PairSamples, opts: RefineOptions) -> torch.Tensor | float:
    """E_pol's DoP floor per pair (``pol.dop_min``, ``pol.dop_min_noise``).

    'shot': ``pol.dop_min * sqrt(max(1, m / I))`` with I the pair's colour-mean I_int (recovered from
    I_min = (1 - rho) I_int when E_pho uses I_min) and m its median over the stage's pairs: the
    standard deviation of a DoP measured under shot noise grows as 1 / sqrt(I).

    Returns:
        a float (``'fixed'``; ``'evidence'``, see :func:`evidence_dop_floor`, ``inf`` when no pair
        is evidence) or a (P,) tensor (``'shot'``).
    """
    if opts.pol.dop_min_noise == "fixed" or samples.dop is None:
        return opts.pol.dop_min
    if opts.pol.dop_min_noise == "evidence":
        return evidence_dop_floor(samples, opts)
    i = samples.intensity.mean(dim=-1)
    if opts.pho.intensity == "min":
        i = i / (1.0 - samples.dop).clamp_min(0.05)
    i = i.clamp_min(1e-6)
    ratio = (i.median() / i).clamp_min(1.0)
    return opts.pol.dop_min * torch.sqrt(ratio)


#: Mean azimuth distance eta of an AoP unrelated to the surface (eta is uniform on [0, pi/4]).
CHANCE_ETA = math.pi / 8.0


def evidence_dop_floor(samples: PairSamples, opts: RefineOptions) -> float:
    """The DoP from which the observed AoP is evidence about the current surface ('evidence').

    The pairs at or above ``pol.dop_min`` (with a defined AoP and azimuth) are sorted by their
    evidence (:func:`pol_evidence`: the DoP, over its noise where the views measure it), most
    polarized first, and cut into bins of ``max(pol.dop_evidence_bin, 2% of them)`` pairs (a short
    remainder joins the last bin). Walking down, a bin is evidence while its mean azimuth distance
    eta to the samples' normals is at most ``pol.dop_evidence_ratio * pi / 8``: an AoP unrelated to
    the surface (noise, false polarization at albedo edges) has mean pi/8. The floor is the
    lowest evidence of the last such bin; the walk stops at the first bin that is not (when none is
    not, the floor is ``pol.dop_min``).

    Returns:
        the floor (at least ``pol.dop_min``), or ``inf`` when the most polarized bin is no evidence
        (E_pol then has no pairs this stage).
    """
    evidence = pol_evidence(samples)
    if evidence is None or samples.dop is None or samples.aop is None or samples.aop_defined is None:
        return opts.pol.dop_min
    alpha, defined = azimuth(samples.normal_cam, samples.ray_cam)
    usable = defined & samples.aop_defined & (samples.dop >= opts.pol.dop_min)
    ranked = evidence[usable]
    if ranked.numel() == 0:
        return opts.pol.dop_min
    eta = azimuth_distance(alpha[usable], samples.aop[usable])
    order = torch.argsort(ranked, descending=True)
    ranked, eta = ranked[order], eta[order]
    n = ranked.numel()
    size = min(n, max(opts.pol.dop_evidence_bin, math.ceil(0.02 * n)))
    starts = list(range(0, n, size))
    if len(starts) > 1 and n - starts[-1] < size:
        starts.pop()
    ends = [*starts[1:], n]
    bound = opts.pol.dop_evidence_ratio * CHANCE_ETA
    floor = math.inf
    for a, b in zip(starts, ends, strict=True):
        if float(eta[a:b].mean()) > bound:
            break
        floor = float(ranked[b - 1])
    else:
        return opts.pol.dop_min  # every bin is evidence: keep every pair above dop_min
    return max(floor, opts.pol.dop_min)


def _robust_pho_weights(
    setup: _Setup,
    state: _Unknowns,
    pairs: PairSet,
    samples: PairSamples,
    light_factor: torch.Tensor | None = None,
) -> torch.Tensor:
    """(P,) Cauchy weights 1 / (1 + (r / s)^2) of each pair's E_pho residual r (RGB norm) at the
    current unknowns, s = ``pho.robust_scale`` times the median residual (``pho.robust``).

    ``pho.robust='specular'`` weights only the pairs observed brighter than rendered (colour mean):
    specular residue only adds light, while a misplaced surface errs both ways, so pairs darker
    than their rendering keep full weight and keep pulling the surface into place.
    """
    with torch.no_grad():
        normals = vertex_normals(state.vertices, setup.topo.faces)
        light = pair_light(normals, state.sh, state.rgb_scale, pairs)
        factor = diffuse_view_factor(
            samples.normal_cam,
            samples.ray_cam,
            fresnel_ior=setup.opts.pho.diffuse_fresnel_ior,
            dop_ior=setup.opts.pho.diffuse_dop_ior,
        )
        if factor is not None:
            light = light * factor[:, None]
        if light_factor is not None:
            light = light * light_factor[:, None]
        diff = samples.intensity - state.albedo.index_select(0, pairs.vertex) * light
        r = torch.linalg.vector_norm(diff, dim=1)
        scale = setup.opts.pho.robust_scale * r.median().clamp_min(1e-12)
        weight = 1.0 / (1.0 + (r / scale) ** 2)
        if setup.opts.pho.robust == "specular":
            weight = torch.where(diff.mean(dim=1) > 0, weight, torch.ones_like(weight))
        return weight


def _minimize(
    param: _Parametrization,
    *,
    problem: StageProblem,
    solver: AlbedoSolver | None,
    weights: StageWeights,
    smoother: GraphSmoother,
    opts: RefineOptions,
    log: _IterationLog,
    max_iterations: int,
    freeze_motion: bool = False,
) -> LbfgsResult:
    """L-BFGS on one parametrization of a stage's cost (``freeze_motion``: the vertex-motion block's
    gradient is zeroed, so the geometry stays put and only lighting and albedo move)."""

    def fun(z: torch.Tensor) -> tuple[float, torch.Tensor, dict[str, float]]:
        z = z.detach().requires_grad_(True)
        u = param.unpack(z)
        albedo = u.albedo if solver is None else solver
        terms = energy_terms(u.vertices, albedo, u.sh, u.rgb_scale, problem)
        total = total_energy(
            terms,
            tau_pol=weights.tau_pol,
            tau_gsm=weights.tau_gsm,
            tau_psm=weights.tau_psm,
            tau_light=weights.tau_light,
        )
        (grad,) = torch.autograd.grad(total, z)
        if freeze_motion:
            grad[param.blocks.motion] = 0.0
        named = {k: float(v.detach()) for k, v in terms.items()}
        named["total"] = float(total.detach())
        return named["total"], grad, named

    return minimize_lbfgs(
        fun,
        param.initial(),
        precondition=param.preconditioner(smoother),
        first_step=0.1,
        max_iterations=max_iterations,
        history_size=opts.solver.history_size,
        rel_tolerance=opts.solver.rel_tolerance,
        grad_tolerance=opts.solver.grad_tolerance,
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


def solve_stage(
    setup: _Setup,
    stage: _Stage,
    state: _Unknowns,
    *,
    progress: Progress,
    max_iterations: int | None = None,
    freeze_motion: bool = False,
) -> tuple[_Unknowns, StageLog]:
    """Minimize one stage's cost from ``state`` (L-BFGS; the albedo projected or joint).

    ``max_iterations`` (default: the options') and ``freeze_motion`` (geometry held, only lighting
    and albedo solved) serve :func:`prefit_lighting`.

    Returns:
        the unknowns at the accepted point and the stage's log.
    """
    t0 = time.perf_counter()
    opts = setup.opts
    joint = opts.solver.albedo_solve == "joint"
    param = _Parametrization(
        state,
        pairs=stage.pairs,
        faces=setup.topo.faces,
        h=stage.h,
        motion=opts.solver.vertex_motion,
        joint_albedo=joint,
    )
    solver = (
        None
        if joint
        else AlbedoSolver(
            stage.pairs, setup.topo.edges_np, stage.psm_weight, stage.weights.tau_psm, state.albedo
        )
    )
    iterations = opts.solver.max_iterations if max_iterations is None else max_iterations
    log = _IterationLog(max_iterations=iterations, progress=progress)
    res = _minimize(
        param,
        problem=stage.problem,
        solver=solver,
        weights=stage.weights,
        smoother=setup.smoother,
        opts=opts,
        log=log,
        max_iterations=iterations,
        freeze_motion=freeze_motion,
    )
    w = stage.weights
    stage_log = StageLog(
        index=stage.index,
        tau_pol=w.tau_pol,
        tau_gsm=w.tau_gsm,
        tau_psm=w.tau_psm,
        t=w.t,
        k=opts.pol.k,
        n_pairs=stage.pairs.size,
        n_observed=stage.n_observed,
        pol_pairs=stage.pol_pairs,
        dop_floor=_floor_summary(stage.dop_floor) if opts.pol.enabled else None,
        energies=log.energies,
        grad_max=log.grad_max,
        evaluations=res.evaluations,
        stop_reason=res.reason,
        seconds=time.perf_counter() - t0,
    )
    accepted = _accepted(param, stage.problem, solver, res.x)
    if not freeze_motion and opts.surface.relax_iterations > 0 and stage.index == opts.n_stages - 1:
        accepted = _relaxed(setup, stage.problem, solver, accepted)
    return accepted, stage_log


def _relaxed(
    setup: _Setup, problem: StageProblem, solver: AlbedoSolver | None, state: _Unknowns
) -> _Unknowns:
    """``state`` with its vertices spread evenly over the last stage's surface (``surface.relax_iterations``,
    :func:`pmvir.refine.relax.relax_tangentially`); the albedo is solved again at the new positions
    (projected) or interpolated there (joint)."""
    verts = state.vertices.cpu().numpy().astype(np.float64)
    relaxed, face_ids, bary = relax_tangentially(verts, setup.faces_np, setup.opts.surface.relax_iterations)
    vertices = torch.from_numpy(relaxed).to(device=setup.device, dtype=setup.dtype)
    if solver is not None:
        with torch.no_grad():
            energy_terms(vertices, solver, state.sh, state.rgb_scale, problem)
        albedo = solver.current.detach()
    else:
        carried = carry_values(state.albedo.cpu().numpy().astype(np.float64), setup.faces_np, face_ids, bary)
        albedo = torch.from_numpy(carried).to(device=setup.device, dtype=setup.dtype)
    return _Unknowns(vertices, albedo, state.sh, state.rgb_scale)


def intensity_units(observations: Sequence[Observation], opts: RefineOptions) -> float:
    """The factor on intensities and albedos in E_pho and E_psm (``pho.intensity_scale``, ``pho.intensity_units``).

    With ``pho.intensity_scale='median'`` it is ``pho.intensity_units / m``, m the median colour-mean observed
    intensity over every view's valid pixels, so that E_pho's weight against E_pol and E_gsm does not
    change with the exposure or the lighting's brightness.

    Raises:
        ReconstructionError: 'median' asked for but no view has a valid pixel with positive intensity.
    """
    if opts.pho.intensity_scale == "absolute":
        return opts.pho.intensity_units
    values = [obs.intensity[obs.valid].mean(axis=-1) for obs in observations]
    flat = np.concatenate(values) if values else np.zeros(0, np.float32)
    flat = flat[np.isfinite(flat) & (flat > 0)]
    if flat.size == 0:
        raise ReconstructionError("no view has a valid pixel with positive intensity to scale E_pho by")
    return opts.pho.intensity_units / float(np.median(flat))


def with_valid_margin(obs: Observation, margin: int) -> Observation:
    """The observation with ``valid`` shrunk by ``margin`` pixels (a square structuring element):
    pixels within ``margin`` (Chebyshev distance) of an invalid one (the mask's outside, a saturated
    footprint) become invalid too.
    The image border is not a boundary: pixels there stay valid."""
    kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
    valid = cv2.erode(obs.valid.astype(np.uint8), kernel, borderType=cv2.BORDER_REPLICATE) > 0
    return replace(obs, valid=valid)


def with_smoothed_stokes(obs: Observation, sigma_px: float) -> Observation:
    """The observation with its AoP and DoP taken from the Gaussian average (standard deviation
    ``sigma_px``) of the normalized Stokes (rho cos 2 phi, rho sin 2 phi) over its valid pixels.

    Normalized convolution: each average is divided by the Gaussian's weight on valid pixels, so
    invalid pixels (the mask's outside, the silhouette margin, saturation) neither leak in nor pull
    the DoP toward 0 at the edges. Invalid pixels keep their values; ``valid`` and the intensity are
    unchanged.
    """
    valid = obs.valid.astype(np.float32)
    phi = obs.aop.astype(np.float64)
    rho = np.where(obs.valid, obs.dop, 0.0)

    def blur(a: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(a.astype(np.float32), (0, 0), sigma_px, borderType=cv2.BORDER_REPLICATE)

    weight = np.maximum(blur(valid), 1e-6)
    s1 = blur(rho * np.cos(2.0 * phi)) / weight
    s2 = blur(rho * np.sin(2.0 * phi)) / weight
    aop = np.mod(0.5 * np.arctan2(s2, s1), np.pi)
    aop = np.minimum(aop, np.nextafter(np.float32(np.pi), np.float32(0.0)))
    return replace(
        obs,
        aop=np.where(obs.valid, aop, obs.aop).astype(np.float32),
        dop=np.where(obs.valid, np.clip(np.hypot(s1, s2), 0.0, 1.0), obs.dop).astype(np.float32),
    )


def _setup(
    faces_np: np.ndarray,
    n_vertices: int,
    cameras: Sequence[Camera],
    observations: Sequence[Observation],
    *,
    opts: RefineOptions,
    visibility_fn: VisibilityFn | None,
) -> _Setup:
    device = resolve_device(opts.device)
    dtype = torch.float32 if opts.dtype == "float32" else torch.float64
    if opts.views.silhouette_margin_px > 0:
        observations = [with_valid_margin(obs, opts.views.silhouette_margin_px) for obs in observations]
    if opts.pol.aop_noise == "uniform":
        observations = [replace(obs, aop_noise=None) for obs in observations]
    if opts.pol.stokes_smoothing_px > 0 and opts.pol.enabled:
        observations = [with_smoothed_stokes(obs, opts.pol.stokes_smoothing_px) for obs in observations]
    views = build_view_stack(
        cameras, observations, polarimetric=opts.pol.enabled, device=device, dtype=dtype
    )
    topo = _Topology.of(faces_np, device)
    smoother = GraphSmoother(
        topo.edges_np,
        n_vertices,
        lam=opts.solver.precondition_lambda,
        iterations=opts.solver.precondition_iterations,
        device=device,
        dtype=dtype,
    )
    return _Setup(
        units=intensity_units(observations, opts),
        faces_np=faces_np,
        topo=topo,
        cameras=cameras,
        observations=observations,
        views=views,
        smoother=smoother,
        visibility_fn=visibility_fn,
        opts=opts,
        device=device,
        dtype=dtype,
    )


def _initial_unknowns(
    vertices: np.ndarray, n_views: int, *, sh_order: int, device: torch.device, dtype: torch.dtype
) -> _Unknowns:
    """The paper's start (section 5.1): SH = [1, 0, ..., 0], scale = [1, 1, 1]; the albedo is set by stage 1."""
    n = len(vertices)
    sh = torch.zeros((n_views, sh_term_count(sh_order)), dtype=dtype, device=device)
    sh[:, 0] = 1.0
    return _Unknowns(
        vertices=torch.from_numpy(vertices).to(device=device, dtype=dtype),
        albedo=torch.zeros((n, 3), dtype=dtype, device=device),
        sh=sh,
        rgb_scale=torch.ones((n_views, 3), dtype=dtype, device=device),
    )


#: Share of the refinement's progress taken by the offset scans outside the stages, per ``offset_scan.mode``.
_SCAN_WEIGHT = {"off": 0.0, "start": 0.01, "stages": 0.02}
#: Share of the refinement's progress taken by the final lighting fit (``lighting.coupling`` > 0).
_LIGHTING_WEIGHT = 0.03


def _offset_scan(
    setup: _Setup, state: _Unknowns, opts: RefineOptions, scans: list[OffsetScan], progress: Progress
) -> tuple[_Unknowns, list[OffsetScan]]:
    """Move the whole surface along its normals to the most photo-consistent offset (:mod:`pmvir.refine.offset`).

    A uniform offset along the normals leaves the normals, so the albedo and lighting stay valid.
    The first scan covers +-1.5 pixels; the later ones (``offset_scan.mode`` "stages"), which found at most
    0.25 pixels on the captures measured (README), +-0.75 pixels at half the cost.
    """
    progress.update(0.0, "photo-consistent offset along the normals")
    v = state.vertices.detach().cpu().numpy().astype(np.float64)
    scan = photo_consistent_offset(
        v,
        setup.faces_np,
        setup.cameras,
        setup.observations,
        min_cos=opts.offset_scan.min_cos,
        max_px=0.75 if scans else 1.5,
        deblur_px=opts.offset_scan.deblur_px,
    )
    if not scan.applied:
        return state, [*scans, scan]
    v = v + scan.offset * vertex_normals_np(v, setup.faces_np)
    moved = torch.from_numpy(v).to(device=setup.device, dtype=setup.dtype)
    return replace(state, vertices=moved), [*scans, scan]


def _inside_hull(
    setup: _Setup, state: _Unknowns, masks: Sequence[np.ndarray | None] | None, fits: list[HullFit]
) -> _Unknowns:
    """``state`` with the vertices outside the masks' visual hull moved inside (``surface.hull_tolerance_px``);
    the fit is appended to ``fits``. Unchanged without masks or with the option off."""
    tolerance = setup.opts.surface.hull_tolerance_px
    if masks is None or tolerance is None:
        return state
    v = state.vertices.detach().cpu().numpy().astype(np.float64)
    fit = fit_inside_hull(v, setup.faces_np, setup.cameras, masks, tolerance_px=tolerance)
    fits.append(fit)
    if fit.moved == 0:
        return state
    moved = torch.from_numpy(fit.vertices).to(device=setup.device, dtype=setup.dtype)
    return replace(state, vertices=moved)


def rim_fit_margin(opts: RefineOptions) -> float | None:
    """The masks' margin the rim fit discounts: ``surface.rim_fit_mask_margin_px`` where set; else estimated from the
    rims (None) where the offset scans run, and 0 where they are off. The estimate takes a surface that lies
    inside all round for a margin of the masks, and the scans are what moves such a surface; without them
    (a specular-dominated capture, whose stereo surface lies inside at the depth of its reflections) the
    rims are the only measure of it."""
    if opts.surface.rim_fit_mask_margin_px is not None:
        return opts.surface.rim_fit_mask_margin_px
    return None if opts.offset_scan.mode != "off" else 0.0


def _to_rims(
    setup: _Setup, state: _Unknowns, masks: Sequence[np.ndarray | None]
) -> tuple[_Unknowns, RimFit]:
    """``state`` with the shoulders whose rims lie inside the masks moved outward (``surface.rim_fit_gain``)."""
    v = state.vertices.detach().cpu().numpy().astype(np.float64)
    fit = fit_to_rims(
        v,
        setup.faces_np,
        setup.cameras,
        masks,
        gain=setup.opts.surface.rim_fit_gain,
        mask_margin_px=rim_fit_margin(setup.opts),
    )
    moved = torch.from_numpy(fit.vertices).to(device=setup.device, dtype=setup.dtype)
    return replace(state, vertices=moved), fit


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
    setup = _setup(faces_np, n, cameras, observations, opts=opts, visibility_fn=visibility_fn)
    vis = np.asarray(visibility)
    if vis.shape != (n, n_views):
        raise ConfigError(f"expected ({n}, {n_views}) visibility, got {vis.shape}")
    state = _initial_unknowns(
        verts_np, n_views, sh_order=opts.lighting.sh_order, device=setup.device, dtype=setup.dtype
    )
    if masks is not None and len(masks) != n_views:
        raise ConfigError(f"expected {n_views} masks (one per view), got {len(masks)}")
    hull_fits: list[HullFit] = []

    def scanned(state: _Unknowns, scans: list[OffsetScan], p: Progress) -> tuple[_Unknowns, list[OffsetScan]]:
        state, scans = _offset_scan(setup, state, opts, scans, p)
        if scans[-1].applied:
            state = _inside_hull(setup, state, masks, hull_fits)
        return state, scans

    scans: list[OffsetScan] = []
    t_scan = time.perf_counter()
    if opts.offset_scan.mode != "off":
        with progress.step("offset scan", weight=0.01) as p:
            state, scans = scanned(state, scans, p)
    timings = {"setup": t_scan - t_start, "offset_scan": time.perf_counter() - t_scan}
    logs: list[StageLog] = []
    for s in range(opts.n_stages):
        t_stage = time.perf_counter()
        lighting = _LIGHTING_WEIGHT if opts.lighting.coupling > 0.0 else 0.0
        stage_weight = (1.0 - _SCAN_WEIGHT[opts.offset_scan.mode] - lighting) / opts.n_stages
        with progress.step(f"stage {s + 1}", weight=stage_weight) as p:
            p.update(0.0, f"of {opts.n_stages}: visibility and pairs")
            if s > 0 and opts.offset_scan.mode == "stages":
                state, scans = scanned(state, scans, p)
            stage, state = prepare_stage(setup, state, vis, s)
            vis = stage.visibility
            if s == 0 and opts.lighting.prefit_iterations > 0:
                with p.step("lighting", weight=0.1) as q:
                    stage, state = prefit_lighting(setup, stage, state, progress=q)
            state, log = solve_stage(setup, stage, state, progress=p)
        logs.append(log)
        timings[f"stage_{s + 1}"] = time.perf_counter() - t_stage

    if opts.offset_scan.mode == "stages":
        t_scan = time.perf_counter()
        with progress.step("offset scan", weight=0.01) as p:
            state, scans = _offset_scan(setup, state, opts, scans, p)
        timings["offset_scan"] += time.perf_counter() - t_scan
    if masks is not None and opts.surface.hull_tolerance_px is not None:
        t_hull = time.perf_counter()
        state = _inside_hull(setup, state, masks, hull_fits)
        timings["hull_fit"] = time.perf_counter() - t_hull
    rim_fit = None
    if masks is not None and opts.surface.rim_fit_gain > 0.0:
        t_rim = time.perf_counter()
        state, rim_fit = _to_rims(setup, state, masks)
        timings["rim_fit"] = time.perf_counter() - t_rim
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
        intensity_factor=setup.units,
        offset_scans=scans,
        hull_fits=hull_fits,
        rim_fit=rim_fit,
        lighting_fit=lighting_fit,
    )
