"""Options of the photometric and polarimetric refinement (pipeline stage 3), grouped by what they act on."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pmvir.config.base import DemosaicMethod, _Options, advanced, basic


class StageOptions(_Options):
    """Per-stage weights of the cost E_pho + tau_pol E_pol + tau_gsm E_gsm + tau_psm E_psm.

    Stage s uses the s-th entry of each list; all lists have one entry per stage.
    """

    tau_pol: list[float] = Field(
        default=[15.0, 30.0, 90.0], min_length=1,
        description="Per stage: weight tau1 of E_pol (the number of entries sets the number of stages).",
        json_schema_extra=basic(),
    )
    tau_gsm: list[float] = Field(
        default=[0.1, 0.1, 0.1], min_length=1,
        description="Per stage: weight tau2 of E_gsm.",
        json_schema_extra=advanced(),
    )
    tau_psm: list[float] = Field(
        default=[2.0, 2.0, 2.0], min_length=1,
        description="Per stage: weight tau3 of E_psm.",
        json_schema_extra=advanced(),
    )
    gsm_exponent: list[float] = Field(
        default=[2.2, 2.8, 3.4], min_length=1,
        description="Per stage: exponent t of E_gsm (>= 1).",
        json_schema_extra=advanced(),
    )
    coarse: int = Field(
        default=0, ge=0,
        description="The first this many stages run on the surface one sqrt(3) step coarser than the "
        "subdivided one, then move it (0: all on the subdivided surface), < the stage count.",
        json_schema_extra=advanced(),
    )

    @model_validator(mode="after")
    def _same_stage_count(self) -> StageOptions:
        lengths = {len(self.tau_pol), len(self.tau_gsm), len(self.tau_psm), len(self.gsm_exponent)}
        if len(lengths) != 1:
            raise ValueError(
                "tau_pol, tau_gsm, tau_psm and gsm_exponent must have one entry per stage, got lengths "
                f"{len(self.tau_pol)}, {len(self.tau_gsm)}, {len(self.tau_psm)}, {len(self.gsm_exponent)}"
            )
        if min(self.tau_pol + self.tau_gsm + self.tau_psm) < 0:
            raise ValueError("the tau weights must be >= 0")
        if min(self.gsm_exponent) < 1.0:
            raise ValueError(f"gsm_exponent entries must be >= 1, got {self.gsm_exponent}")
        if self.coarse >= len(self.tau_pol):
            raise ValueError(f"coarse must be below the stage count {len(self.tau_pol)}, got {self.coarse}")
        return self


class PolOptions(_Options):
    """The polarimetric term E_pol: which (vertex, view) pairs it keeps and how it weights them."""

    enabled: bool = Field(
        default=True,
        description="Use the polarimetric term E_pol (False: the MVIR baseline, --no-polarimetric).",
        json_schema_extra=basic(),
    )
    k: float = Field(
        default=0.5, gt=0.0,
        description="Narrowness k of E_pol's concave cost.",
        json_schema_extra=advanced(),
    )
    dop_weight: bool = Field(
        default=True,
        description="Weight each E_pol pair by its observed DoP rho, sampled at the stage's start and fixed "
        "for the stage (data: no gradient flows through it).",
        json_schema_extra=advanced(),
    )
    dop_weight_normalized: bool = Field(
        default=True,
        description="With dop_weight: divide the stage's DoP weights by their mean over E_pol's pairs, so "
        "they rank pairs without scaling E_pol by the capture's typical DoP.",
        json_schema_extra=advanced(),
    )
    dop_weight_power: float = Field(
        default=2.0, ge=0.0, le=4.0,
        description="With dop_weight: the weight is rho ** this, 0..4 (1: the paper's rho; 2: the inverse "
        "variance of the AoP).",
        json_schema_extra=advanced(),
    )
    aop_noise_scale_deg: float = Field(
        default=0.0, ge=0.0, le=90.0,
        description="> 0: E_pol weights each pair by 1 / (1 + (nu / this)^2), nu its AoP noise (deg) from the "
        "closure residual, not normalized per capture; 0: the DoP weights above.",
        json_schema_extra=basic("deg"),
    )
    aop_noise: Literal["closure", "uniform"] = Field(
        default="closure",
        description="AoP noise model: 'closure' measures it per pixel from the raw mosaic (closure residual) "
        "and weights E_pol by DoP / noise; 'uniform': the same noise everywhere.",
        json_schema_extra=advanced(),
    )
    aop_noise_px: float = Field(
        default=3.0, gt=0.0, le=32.0,
        description="With aop_noise 'closure': standard deviation, in pixels, of the Gaussian average of the "
        "closure residual.",
        json_schema_extra=advanced("px"),
    )
    dop_min: float = Field(
        default=0.05, ge=0.0, lt=1.0,
        description="Pairs whose observed DoP at a stage's start is below this are left out of E_pol for the "
        "stage, [0, 1); 0 keeps every pair.",
        json_schema_extra=advanced(),
    )
    dop_min_noise: Literal["fixed", "shot", "evidence"] = Field(
        default="evidence",
        description="E_pol's DoP floor: 'fixed' (dop_min), 'shot' (rises as 1 / sqrt(I_int) in dark pairs) "
        "or 'evidence' (where the AoP stops agreeing with the surface; E_pol off if nowhere).",
        json_schema_extra=advanced(),
    )
    dop_evidence_ratio: float = Field(
        default=0.7, gt=0.0, le=1.0,
        description="With dop_min_noise 'evidence': a bin of pairs is evidence while its mean azimuth "
        "distance to the surface is at most this fraction of chance's (pi/8), (0, 1].",
        json_schema_extra=advanced(),
    )
    dop_evidence_bin: int = Field(
        default=1000, ge=10,
        description="With dop_min_noise 'evidence': least number of pairs per bin (bins are also at least 2% "
        "of the pairs above dop_min).",
        json_schema_extra=advanced(),
    )
    stokes_smoothing_px: float = Field(
        default=0.0, ge=0.0, le=16.0,
        description="Gaussian standard deviation (px) over which each view's normalized linear Stokes is "
        "averaged inside the valid pixels before E_pol samples it, 0..16; 0: off.",
        json_schema_extra=advanced("px"),
    )


class PhoOptions(_Options):
    """The photometric terms E_pho and E_psm: observed intensity, shading model, robust loss."""

    intensity: Literal["min", "int"] = Field(
        default="min",
        description="Observed colour in E_pho: 'min' = I_min = (1 - rho) I_int (the paper's), 'int' = I_int.",
        json_schema_extra=advanced(),
    )
    intensity_scale: Literal["median", "absolute"] = Field(
        default="median",
        description="Unit of E_pho and E_psm intensities: 'median' (multiples of the capture's median "
        "intensity, independent of exposure) or 'absolute' (normalized units times intensity_units).",
        json_schema_extra=advanced(),
    )
    intensity_units: float = Field(
        default=6.4, gt=0.0,
        description="Intensities and albedos are multiplied by this in E_pho and E_psm: the balance between "
        "them and E_pol / E_gsm (about 32 with intensity_scale 'absolute').",
        json_schema_extra=advanced(),
    )
    diffuse_fresnel_ior: float = Field(
        default=0.0, ge=0.0,
        description="E_pho's diffuse model: 0 Lambertian; n > 1 multiplies each pair's rendering by the "
        "Fresnel transmittance toward the camera of a dielectric of index n.",
        json_schema_extra=advanced(),
    )
    diffuse_dop_ior: float = Field(
        default=0.0, ge=0.0,
        description="With intensity 'min' only: n > 1 multiplies each pair's rendering by 1 - rho_d, the "
        "share of a dielectric's diffuse light I_min keeps (index n). 0: off.",
        json_schema_extra=advanced(),
    )
    shadowing: Literal["none", "cast"] = Field(
        default="none",
        description="E_pho's shading: 'none' (every vertex sees its whole hemisphere) or 'cast' (each pair's "
        "irradiance reduced by the part of the hemisphere the surface blocks).",
        json_schema_extra=advanced(),
    )
    shadow_directions: int = Field(
        default=128, ge=8, le=4096,
        description="With shadowing 'cast': directions over the sphere (Fibonacci) tested from each vertex.",
        json_schema_extra=advanced(),
    )
    shadow_bounce: float = Field(
        default=0.0, ge=0.0, le=1.0,
        description="With shadowing 'cast': the share of the blocked light that the blocking surface sends "
        "back (inter-reflection, not otherwise modelled); 0: none.",
        json_schema_extra=advanced(),
    )
    robust: Literal["none", "cauchy", "specular"] = Field(
        default="cauchy",
        description="E_pho's loss: 'none' (least squares), 'cauchy' (Cauchy weights of the residuals at the "
        "stage's start, from stage 2 on) or 'specular' (down-weights only brighter pairs).",
        json_schema_extra=advanced(),
    )
    robust_scale: float = Field(
        default=0.5, gt=0.0,
        description="Scale s of E_pho's robust weights, in multiples of the stage's median E_pho residual "
        "(RGB norm).",
        json_schema_extra=advanced(),
    )
    robust_first_stage: bool = Field(
        default=False,
        description="With a robust E_pho and the lighting pre-fit: stage 1's weights come from the pre-fit's "
        "residuals (False: stage 1 is least squares).",
        json_schema_extra=advanced(),
    )
    psm_sigma_chroma: float = Field(
        default=0.05, gt=0.0,
        description="E_psm weight w_ij = exp(-|c_i - c_j|^2 / s_c^2) exp(-(log I_i - log I_j)^2 / s_I^2): "
        "s_c, on chromaticity c = RGB / (R + G + B) of the observed colours.",
        json_schema_extra=advanced(),
    )
    psm_sigma_log_intensity: float = Field(
        default=0.3, gt=0.0,
        description="s_I of the E_psm weight, on log mean intensity.",
        json_schema_extra=advanced(),
    )


    @model_validator(mode="after")
    def _dop_ior_needs_min(self) -> PhoOptions:
        if self.diffuse_dop_ior > 0.0 and self.intensity != "min":
            raise ValueError(
                f"diffuse_dop_ior {self.diffuse_dop_ior} models I_min (the part of the diffuse light I_min "
                "keeps) but intensity is 'int', which keeps all of it; set diffuse_dop_ior 0 or intensity 'min'"
            )
        return self


class LightingOptions(_Options):
    """The per-view lighting (spherical harmonics) and its fits outside the stages."""

    sh_order: Literal[2, 3, 4] = Field(
        default=4,
        description="Order of each view's spherical-harmonic shading in E_pho: 2 (9 terms, the paper's), 3 "
        "(16) or 4 (25; holds glossy residue). illumination.json keeps the order-2 part in 'sh'.",
        json_schema_extra=basic(),
    )
    coupling: float = Field(
        default=0.0, ge=0.0, le=1e6,
        description="After the last stage, weight of E_light in a final lighting and albedo fit that pulls "
        "each view's order-2 lighting toward the views' mean, 0..1e6; 0: off.",
        json_schema_extra=advanced(),
    )
    final_iterations: int = Field(
        default=40, ge=1, le=100_000,
        description="L-BFGS iterations of the final lighting fit (with coupling > 0).",
        json_schema_extra=advanced(),
    )
    prefit_iterations: int = Field(
        default=0, ge=0, le=100_000,
        description="L-BFGS iterations fitting the per-view lighting and albedo to the initial surface "
        "before stage 1, geometry held; 0: none.",
        json_schema_extra=advanced(),
    )


class ViewOptions(_Options):
    """Which (vertex, view) pairs each stage samples."""

    min_cos: float = Field(
        default=0.35, ge=-1.0, lt=1.0,
        description="A (vertex, view) pair enters a stage only when the cosine between the vertex normal and "
        "the direction to the camera is at least this, [-1, 1); -1 keeps every visible pair.",
        json_schema_extra=advanced(),
    )
    min_pairs: int = Field(
        default=2, ge=0,
        description="Each vertex keeps at least this many of its most frontal visible pairs even below "
        "min_cos, so parts seen only obliquely stay placed.",
        json_schema_extra=advanced(),
    )
    silhouette_margin_px: int = Field(
        default=2, ge=0, le=64,
        description="Pixels within this distance (px) of an observation's invalid region (outside the mask, "
        "saturated) are not sampled, 0..64.",
        json_schema_extra=advanced("px"),
    )
    drawn_mask_margin_px: int = Field(
        default=1, ge=0, le=16,
        description="On masks the isolation drew, which reach past the object's outline: this many px more "
        "than silhouette_margin_px inside them are not sampled, 0..16.",
        json_schema_extra=advanced("px"),
    )
    refresh_visibility: bool = Field(
        default=True,
        description="Recompute visibility from the refined surface between stages.",
        json_schema_extra=advanced(),
    )


class SolverOptions(_Options):
    """The L-BFGS solve of each stage: iterations, stopping, unknowns, preconditioning."""

    max_iterations: int = Field(
        default=80, ge=1, le=100_000,
        description="Most L-BFGS iterations per stage.",
        json_schema_extra=basic(),
    )
    rel_tolerance: float = Field(
        default=1e-5, ge=0.0,
        description="A stage stops when one iteration lowers the cost by less than this fraction of it.",
        json_schema_extra=advanced(),
    )
    grad_tolerance: float = Field(
        default=1e-9, ge=0.0,
        description="A stage stops when the largest gradient component is at most this.",
        json_schema_extra=advanced(),
    )
    history_size: int = Field(
        default=10, ge=1, le=100,
        description="L-BFGS memory (correction pairs).",
        json_schema_extra=advanced(),
    )
    albedo_solve: Literal["projected", "joint"] = Field(
        default="projected",
        description="'projected': the albedo is set to its exact minimizer over albedos >= 0 at every "
        "evaluation; 'joint': it is one more block of L-BFGS unknowns, clamped at 0 after each stage.",
        json_schema_extra=advanced(),
    )
    precondition_lambda: float = Field(
        default=20.0, ge=0.0,
        description="Strength lam of the preconditioner (I + lam L)^-1 on vertex motion, L the mesh graph "
        "Laplacian; larger values speed smooth large-scale motion. 0: none.",
        json_schema_extra=advanced(),
    )
    precondition_iterations: int = Field(
        default=30, ge=0, le=1000,
        description="Terms of the Neumann series approximating the preconditioner.",
        json_schema_extra=advanced(),
    )
    vertex_motion: Literal["normal", "free"] = Field(
        default="free",
        description="'free': full 3D vertex motion (3 unknowns per vertex); 'normal': each vertex moves "
        "along its normal at the stage's start (1 unknown).",
        json_schema_extra=advanced(),
    )


class OffsetScanOptions(_Options):
    """The offset scan: the whole mesh moved along its normals to where the views agree best."""

    mode: Literal["off", "start", "stages"] = Field(
        default="stages",
        description="Move the whole mesh along its normals to where the views agree best (ZNCC): 'off', "
        "'start' (before stage 1) or 'stages' (before every stage and after the last).",
        json_schema_extra=basic(),
    )
    specular: Literal["off", "same"] = Field(
        default="off",
        description="For a specular-dominated capture (median DoP in the masks above 0.2): 'off' refines it "
        "without the offset scan, 'same' keeps mode. Applied by the pipeline.",
        json_schema_extra=advanced(),
    )
    deblur_px: float = Field(
        default=1.6, ge=0.0,
        description="Blur (px) the decoded images are taken to hold; each scan runs again on images blurred "
        "by it and extrapolates to no blur. 0: off (half the time).",
        json_schema_extra=advanced("px"),
    )
    min_cos: float = Field(
        default=0.8, gt=0.0, lt=1.0,
        description="Only pixels whose triangle both views see at least at this viewing cosine count in the "
        "scan, (0, 1).",
        json_schema_extra=advanced(),
    )


class SurfaceMoveOptions(_Options):
    """Moves of the surface outside the stages: hull fit, rim fit, fairing and tangential relaxation."""

    hull_tolerance_px: float | None = Field(
        default=0.5, ge=0.0,
        description="After every offset scan and the last stage, vertices projecting more than this (px) "
        "outside hull_views views' masks move inward (at most 3 px; needs masks). None: off.",
        json_schema_extra=advanced("px"),
    )
    hull_views: int = Field(
        default=1, ge=1, le=8,
        description="The hull fit moves a vertex inward where at least this many views see it outside their "
        "masks by more than hull_tolerance_px, 1..8 (masks the isolation drew: at least 2).",
        json_schema_extra=advanced(),
    )
    hull_min_gain: float | None = Field(
        default=None, ge=0.0, le=1.0,
        description="A hull-fit step stays only where it brings the vertex this share of its length (px) "
        "closer to the masks, 0..1 (0: every step). None: 0.2 on drawn masks, 0 on given ones.",
        json_schema_extra=advanced(),
    )
    drawn_hull_tolerance_px: float | None = Field(
        default=1.0, ge=0.0,
        description="hull_tolerance_px (px, >= 0) on masks the isolation drew, which reach about a pixel "
        "past the outline. None: no hull fit on drawn masks.",
        json_schema_extra=advanced("px"),
    )
    rim_fit_gain: float = Field(
        default=0.5, ge=0.0, le=1.0,
        description="After the last stage, vertices near a rim lying inside the mask move outward by this "
        "share of the excess, spread over their shoulders (needs masks), 0..1; 0: off.",
        json_schema_extra=advanced(),
    )
    rim_fit_mask_margin_px: float | None = Field(
        default=None, ge=0.0, lt=4.0,
        description="How far (px) the masks reach past the true outline, discounted by the rim fit, [0, 4). "
        "None: estimated from the rims where the offset scans run, else 0.",
        json_schema_extra=advanced("px"),
    )
    fair_iterations: int = Field(
        default=16, ge=0, le=1000,
        description="Last move of the surface (after the hull and rim fits): pairs of Taubin steps removing "
        "ripples shorter than about 11 px (five edges at fair_reference_area_px), 0..1000; 0: off.",
        json_schema_extra=advanced(),
    )
    fair_reference_area_px: float = Field(
        default=2.0, ge=0.0,
        description="Median projected face area (px^2) at which fair_iterations apply as given; a finer mesh "
        "gets up to 16x the pairs, removing ripples as long in pixels. 0: never scaled.",
        json_schema_extra=advanced("px^2"),
    )
    relax_iterations: int = Field(
        default=20, ge=0, le=1000,
        description="After the last stage, steps of tangential relaxation: crowded vertices spread along the "
        "surface without moving it (albedo solved again), 0..1000; 0: off.",
        json_schema_extra=advanced(),
    )


class RefineOptions(_Options):
    """Photometric and polarimetric refinement (pipeline stage 3, paper section 4.3 and 5.1).

    The cost E_pho + tau_pol E_pol + tau_gsm E_gsm + tau_psm E_psm is minimized in stages (see
    :class:`StageOptions`); the groups hold the options of each term and step.
    """

    demosaic: Literal["same"] | DemosaicMethod = Field(
        default="eari",
        description="Demosaicing of the frames the refinement fits: 'same' reuses decode.demosaic's images; "
        "a method name decodes the frames again with it for the refinement only.",
        json_schema_extra=basic(),
    )
    device: str = Field(
        default="auto", pattern=r"^(auto|cpu|cuda(:[0-9]+)?)$",
        description="Torch device: 'auto' (CUDA when present, else CPU), 'cpu', 'cuda' or 'cuda:N'.",
        json_schema_extra=basic(),
    )
    dtype: Literal["float32", "float64"] = Field(
        default="float32",
        description="Floating-point precision.",
        json_schema_extra=advanced(),
    )

    stages: StageOptions = Field(default_factory=StageOptions, description="Per-stage weights of the terms.")
    pol: PolOptions = Field(default_factory=PolOptions, description="The polarimetric term E_pol.")
    pho: PhoOptions = Field(default_factory=PhoOptions, description="The photometric terms E_pho and E_psm.")
    lighting: LightingOptions = Field(default_factory=LightingOptions, description="The per-view lighting.")
    views: ViewOptions = Field(default_factory=ViewOptions, description="The (vertex, view) pairs sampled.")
    solver: SolverOptions = Field(default_factory=SolverOptions, description="The L-BFGS solve of each stage.")
    offset_scan: OffsetScanOptions = Field(default_factory=OffsetScanOptions, description="The offset scan.")
    surface: SurfaceMoveOptions = Field(
        default_factory=SurfaceMoveOptions, description="Hull fit, rim fit and relaxation of the surface."
    )

    @property
    def n_stages(self) -> int:
        """Number of stages (entries of each per-stage list)."""
        return len(self.stages.tau_pol)
