"""The refinement's state: the unknowns between stages, the fixed set-up every stage shares, each stage's data, and the logs and result it returns."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np
import torch

from pmvir.camera import Camera
from pmvir.config import RefineOptions
from pmvir.errors import ConfigError
from pmvir.geometry.silhouette.hull_fit import HullFit, RimFit
from pmvir.refine.energy import (
    StageProblem,
)
from pmvir.refine.mesh_ops import (
    GraphSmoother,
    face_adjacency,
    unique_edges,
)
from pmvir.refine.offset import OffsetScan
from pmvir.refine.relax import Fairing
from pmvir.refine.sampling import (
    Observation,
    PairSet,
    ViewStack,
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
        pol_pairs: the pairs E_pol used (0 without E_pol).
        dop_floor: E_pol's DoP floor (see :func:`dop_floor`; the median of per-pair floors; 0 when
            every pair is kept; None when no pair was evidence and E_pol was off). With measured
            noise (``pol.aop_noise`` 'closure') an 'evidence' floor is on :func:`pol_evidence`'s scale,
            the DoP at the stage's median noise.
        pol_weight_mean: E_pol's mean pair weight over the pairs it used (1 with the default
            normalized DoP weights; below 1 with ``pol.aop_noise_scale_deg``); None without weights.
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
    pol_weight_mean: float | None
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
        stage_timings: per stage, seconds of its parts: ``offset_scan`` (the scan before it, with its hull
            fit; ``offset_scan.mode`` "stages", from the second stage on), ``lift`` (the first stage on the
            subdivided surface after coarse ones: the motion carried to it), ``prepare`` (visibility, pairs,
            weights and floors), ``lighting_prefit`` (the first stage, when run) and ``solve`` (L-BFGS).
        intensity_factor: what E_pho and E_psm multiplied intensities and albedos by
            (:func:`intensity_units`).
        offset_scans: the photo-consistent offsets scanned (and applied where the scan found one), in
            order: before stage 1, and with ``offset_scan.mode`` "stages" also before every later stage and
            after the last (:func:`pmvir.refine.offset.photo_consistent_offset`).
        hull_fits: the surface held inside the masks' visual hull (``surface.hull_tolerance_px`` with masks),
            in order: after every applied offset scan but the last, and after the last stage and scan.
        rim_fit: the shoulders moved out to the masks' rims after the last hull fit (``surface.rim_fit_gain`` > 0
            with masks), else None.
        fairing: the fairing as run (``surface.fair_iterations`` > 0), else None.
        lighting_fit: the final lighting fit's log (``lighting.coupling`` > 0; its time is
            ``timings["lighting"]``), else None.
        coarse_vertices: vertices of the surface the first ``stages.coarse`` stages ran on (0: none).
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
    stage_timings: list[dict[str, float]] = field(default_factory=list)
    intensity_factor: float = 0.0
    offset_scans: list[OffsetScan] = field(default_factory=list)
    hull_fits: list[HullFit] = field(default_factory=list)
    rim_fit: RimFit | None = None
    fairing: Fairing | None = None
    lighting_fit: StageLog | None = None
    coarse_vertices: int = 0

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
class Unknowns:
    """Current values between stages (torch, on the device)."""

    vertices: torch.Tensor  # (N, 3)
    albedo: torch.Tensor  # (N, 3)
    sh: torch.Tensor  # (V, T): T = 9 (pmvir-sh9), 16 or 25 (refine.lighting.sh_order)
    rgb_scale: torch.Tensor  # (V, 3)



@dataclass(frozen=True)
class Topology:
    """The mesh's fixed connectivity, on the device (and the edges in NumPy too)."""

    faces: torch.Tensor
    face_pairs: torch.Tensor
    has_neighbour: torch.Tensor
    edges: torch.Tensor
    edges_np: np.ndarray

    @classmethod
    def of(cls, faces_np: np.ndarray, device: torch.device) -> Topology:
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
class RefineSetup:
    """What every stage shares: the inputs as tensors, the mesh's connectivity and the options."""

    faces_np: np.ndarray
    topo: Topology
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
class StageData:
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
    pol_weight_mean: float | None  # E_pol's mean pair weight over the pairs it uses (None: unweighted)
    pho_signal: float  # E_pho's value with nothing rendered, at the stage's start (E_light's scale)
