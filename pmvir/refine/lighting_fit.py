"""Lighting fits around the stages: the per-view lighting fitted before stage 1, and the final fit coupled to the shading (E_light)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from pmvir.progress import Progress
from pmvir.refine.solve import solve_stage
from pmvir.refine.stage_setup import (
    prepare_stage,
    robust_pho_weights,
    shadow_factor,
    stage_observations,
    stage_problem,
)
from pmvir.refine.state import RefineSetup, StageData, StageLog, Unknowns


def prefit_lighting(
    setup: RefineSetup, stage: StageData, state: Unknowns, *, progress: Progress
) -> tuple[StageData, Unknowns]:
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
    _, _, samples = stage_observations(state.vertices, setup.topo.faces, setup.views, stage.pairs)
    light_factor = shadow_factor(setup, state, stage.pairs, None)
    pho_weight = robust_pho_weights(setup, state, stage.pairs, samples, light_factor) if robust else None
    problem = stage_problem(
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
    setup: RefineSetup, state: Unknowns, visibility: np.ndarray, *, progress: Progress
) -> tuple[Unknowns, StageLog]:
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
