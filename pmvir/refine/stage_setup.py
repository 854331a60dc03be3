"""A refinement stage's set-up: the inputs made tensors once, the initial unknowns, and each stage's data fixed at its start (pairs, weights, masks)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import replace

import cv2
import numpy as np
import torch

from pmvir.camera import Camera
from pmvir.config import RefineOptions
from pmvir.errors import ConfigError, ReconstructionError
from pmvir.refine.energy import (
    StageProblem,
    diffuse_view_factor,
    pair_light,
    psm_weights,
)
from pmvir.refine.floors import (
    above_floor,
    pol_evidence,
    pol_pair_count,
    pol_pair_weights,
    pol_weight_mean,
    stage_dop_floor,
)
from pmvir.refine.mesh_ops import (
    GraphSmoother,
    mean_edge_length,
    vertex_normals,
)
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
from pmvir.refine.state import (
    RefineSetup,
    StageData,
    StageWeights,
    Topology,
    Unknowns,
    VisibilityFn,
    resolve_device,
)
from pmvir.sh import sh_term_count


def stage_observations(
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



def prepare_stage(
    setup: RefineSetup, state: Unknowns, visibility: np.ndarray, s: int
) -> tuple[StageData, Unknowns]:
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
    colour, observed, samples = stage_observations(state.vertices, setup.topo.faces, setup.views, pairs)
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
    light_factor = shadow_factor(setup, state, pairs, normals_np)
    robust = opts.pho.robust != "none" and s > 0  # stage 1 starts from uniform lighting: no residuals yet
    pho_weight = robust_pho_weights(setup, state, pairs, samples, light_factor) if robust else None
    floor = stage_dop_floor(samples, opts)
    problem = stage_problem(
        setup,
        pairs,
        samples,
        psm_weight,
        t=weights.t,
        pho_weight=pho_weight,
        floor=floor,
        light_factor=light_factor,
    )
    stage = StageData(
        index=s,
        weights=weights,
        visibility=visibility,
        pairs=pairs,
        problem=problem,
        psm_weight=psm_weight,
        n_observed=int(observed.sum()),
        h=mean_edge_length(cur_np, setup.topo.edges_np),
        dop_floor=floor,
        pol_pairs=pol_pair_count(samples, problem) if opts.pol.enabled else 0,
        pol_weight_mean=pol_weight_mean(samples, problem) if opts.pol.enabled else None,
        pho_signal=_pho_signal(samples, problem),
    )
    return stage, state



def _pho_signal(samples: PairSamples, problem: StageProblem) -> float:
    """E_pho with nothing rendered: every pair's observed intensity squared, weighted as E_pho weights it."""
    w = problem.pairs.weight if problem.pho_weight is None else problem.pairs.weight * problem.pho_weight
    with torch.no_grad():
        return float((((samples.intensity * problem.units) ** 2).sum(-1) * w).sum())



def shadow_factor(
    setup: RefineSetup, state: Unknowns, pairs: PairSet, normals_np: np.ndarray | None
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



def stage_problem(
    setup: RefineSetup,
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
        pol_mask = above_floor(samples.dop, evidence, floor, opts)
    pol_weight = pol_pair_weights(samples, evidence, pol_mask, opts)
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



def make_setup(
    faces_np: np.ndarray,
    n_vertices: int,
    cameras: Sequence[Camera],
    observations: Sequence[Observation],
    *,
    opts: RefineOptions,
    visibility_fn: VisibilityFn | None,
) -> RefineSetup:
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
    topo, smoother = _connectivity(faces_np, n_vertices, opts, device, dtype)
    return RefineSetup(
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


def setup_for_mesh(setup: RefineSetup, faces_np: np.ndarray, n_vertices: int) -> RefineSetup:
    """``setup`` for another mesh over the same views (the coarse-to-fine switch): its connectivity and
    preconditioner rebuilt, the views' tensors shared."""
    topo, smoother = _connectivity(faces_np, n_vertices, setup.opts, setup.device, setup.dtype)
    return replace(setup, faces_np=faces_np, topo=topo, smoother=smoother)


def _connectivity(
    faces_np: np.ndarray, n_vertices: int, opts: RefineOptions, device: torch.device, dtype: torch.dtype
) -> tuple[Topology, GraphSmoother]:
    topo = Topology.of(faces_np, device)
    smoother = GraphSmoother(
        topo.edges_np,
        n_vertices,
        lam=opts.solver.precondition_lambda,
        iterations=opts.solver.precondition_iterations,
        device=device,
        dtype=dtype,
    )
    return topo, smoother



def initial_unknowns(
    vertices: np.ndarray, n_views: int, *, sh_order: int, device: torch.device, dtype: torch.dtype
) -> Unknowns:
    """The paper's start (section 5.1): SH = [1, 0, ..., 0], scale = [1, 1, 1]; the albedo is set by stage 1."""
    n = len(vertices)
    sh = torch.zeros((n_views, sh_term_count(sh_order)), dtype=dtype, device=device)
    sh[:, 0] = 1.0
    return Unknowns(
        vertices=torch.from_numpy(vertices).to(device=device, dtype=dtype),
        albedo=torch.zeros((n, 3), dtype=dtype, device=device),
        sh=sh,
        rgb_scale=torch.ones((n_views, 3), dtype=dtype, device=device),
    )


def robust_pho_weights(
    setup: RefineSetup,
    state: Unknowns,
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
