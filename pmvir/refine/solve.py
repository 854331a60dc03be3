"""Solving one refinement stage: the flat preconditioned unknowns, L-BFGS on the stage's cost, the albedo solved at the result."""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from pmvir.config import RefineOptions
from pmvir.progress import Progress
from pmvir.refine.albedo import AlbedoSolver
from pmvir.refine.energy import (
    StageProblem,
    energy_terms,
    total_energy,
)
from pmvir.refine.floors import floor_summary
from pmvir.refine.lbfgs import LbfgsResult, minimize_lbfgs
from pmvir.refine.mesh_ops import (
    GraphSmoother,
    vertex_normals,
)
from pmvir.refine.relax import carry_values, relax_tangentially
from pmvir.refine.sampling import (
    PairSet,
)
from pmvir.refine.state import RefineSetup, StageData, StageLog, StageWeights, Unknowns


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
        start: Unknowns,
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

    def unpack(self, z: torch.Tensor) -> Unknowns:
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
        return Unknowns(vertices, albedo, sh, rgb_scale)


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
) -> Unknowns:
    """The unknowns at the accepted point z (with the projected albedo solved there, or the joint one
    clamped at 0)."""
    with torch.no_grad():
        u = param.unpack(z)
        if solver is not None:
            energy_terms(u.vertices, solver, u.sh, u.rgb_scale, problem)
            u.albedo = solver.current
        else:  # joint: L-BFGS's albedo is unbounded; a reflectance is not negative
            u.albedo = u.albedo.clamp_min(0.0)
    return Unknowns(u.vertices.detach(), u.albedo.detach(), u.sh.detach(), u.rgb_scale.detach())


def solve_stage(
    setup: RefineSetup,
    stage: StageData,
    state: Unknowns,
    *,
    progress: Progress,
    max_iterations: int | None = None,
    freeze_motion: bool = False,
) -> tuple[Unknowns, StageLog]:
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
        dop_floor=floor_summary(stage.dop_floor) if opts.pol.enabled else None,
        pol_weight_mean=stage.pol_weight_mean,
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
    setup: RefineSetup, problem: StageProblem, solver: AlbedoSolver | None, state: Unknowns
) -> Unknowns:
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
    return Unknowns(vertices, albedo, state.sh, state.rgb_scale)
