"""Options of the photometric and polarimetric refinement (pipeline stage 3), grouped by what they act on."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pmvir.config.base import DemosaicMethod, _Options


class StageOptions(_Options):
    """Per-stage weights of the cost E_pho + tau_pol E_pol + tau_gsm E_gsm + tau_psm E_psm.

    Stage s uses the s-th entry of each list; all lists have one entry per stage.
    """

    tau_pol: list[float] = Field(
        default=[15.0, 30.0, 90.0],
        min_length=1,
        description="Per stage: weight tau1 of E_pol. [15, 30, 90] (a quarter of the [60, 120, 360] chosen when "
        "the refinement fitted guided frames) measured best from eari frames on both renderers' Stanford "
        "captures: accuracy gain of the three-model average +42.4% -> +44.1% (built-in) and +30.6% -> +32.7% "
        "(Mitsuba); halved +43.6% / +32.1%; an eighth no better (README).",
    )
    tau_gsm: list[float] = Field(
        default=[0.1, 0.1, 0.1], min_length=1, description="Per stage: weight tau2 of E_gsm."
    )
    tau_psm: list[float] = Field(
        default=[2.0, 2.0, 2.0], min_length=1, description="Per stage: weight tau3 of E_psm."
    )
    gsm_exponent: list[float] = Field(
        default=[2.2, 2.8, 3.4], min_length=1, description="Per stage: exponent t of E_gsm (>= 1)."
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
        return self


class PolOptions(_Options):
    """The polarimetric term E_pol: which (vertex, view) pairs it keeps and how it weights them."""

    enabled: bool = Field(
        default=True,
        description="Use the polarimetric term E_pol (False: the MVIR baseline, --no-polarimetric).",
    )
    k: float = Field(default=0.5, gt=0.0, description="Narrowness k of E_pol's concave cost.")
    dop_weight: bool = Field(
        default=True,
        description="Weight each E_pol pair by its observed DoP rho, sampled at the stage's start and fixed for "
        "the stage (data: no gradient flows through it).",
    )
    dop_weight_normalized: bool = Field(
        default=True,
        description="With dop_weight: divide the stage's DoP weights by their mean over E_pol's pairs, so the "
        "weight ranks pairs by reliability without also scaling E_pol down by the capture's typical DoP. "
        "Measured in the README.",
    )
    dop_weight_power: float = Field(
        default=2.0,
        ge=0.0,
        le=4.0,
        description="With dop_weight: the weight is rho ** this. 1 is the paper's rho; 2 (default) weights each "
        "pair by the inverse variance of its AoP (the AoP's noise falls as 1 / rho), which keeps low-DoP pairs, "
        "whose AoP is mostly demosaicing and sensor noise, from pulling normals: on an environment-lit Mitsuba "
        "capture the accuracy gain rose from +15.6% to +20.9% at 40 iterations per stage (3: +21.1%; 2 at 80 "
        "iterations: +19.9%). Measured in the README.",
    )
    aop_noise: Literal["closure", "uniform"] = Field(
        default="closure",
        description="How noisy each E_pol pair's AoP is taken to be. 'closure' (default): measured per pixel "
        "from the raw mosaic, as the local RMS of the polarizer closure residual (I0 + I90) - (I45 + I135) "
        "relative to s0 (pmvir.polarization.noise; shot and Monte Carlo noise, and false polarization where "
        "the scene changes within a 2x2 block); E_pol's weight and its evidence floor then use each pair's DoP "
        "divided by its noise relative to the stage's median noise (rho * median(sigma) / sigma: the AoP's "
        "signal-to-noise ratio in DoP units) instead of the DoP. 'uniform': the same noise everywhere (the "
        "DoP alone, as before). Observations without a noise map (a library caller's) are uniform. "
        "Measured in the README.",
    )
    aop_noise_px: float = Field(
        default=3.0,
        gt=0.0,
        le=32.0,
        description="With aop_noise 'closure': standard deviation, in pixels, of the Gaussian average of the "
        "closure residual.",
    )
    dop_min: float = Field(
        default=0.05,
        ge=0.0,
        lt=1.0,
        description="Pairs whose observed DoP at the start of a stage is below this are left out of E_pol for "
        "the stage: their AoP is noise. An unpolarized surface seen with normalized Stokes noise 0.01 shows "
        "Rayleigh-distributed DoP of mean 0.0125 with random AoP; fewer than 0.3% of its pairs exceed 0.035. "
        "0.05 measured best on an environment-lit Mitsuba capture, whose diffuse DoP is about 0.02 (0.035: "
        "-3.5 points of accuracy gain, 0.08 and 0.12 worse; README). 0 keeps every pair, as the paper's "
        "equation does.",
    )
    dop_min_noise: Literal["fixed", "shot", "evidence"] = Field(
        default="evidence",
        description="How E_pol's DoP floor is set. 'fixed': dop_min everywhere. 'shot': the floor rises as "
        "1 / sqrt(I_int) below the stage's median I_int (dop_min * sqrt(median / I_int), never below "
        "dop_min), as the DoP's shot noise does. 'evidence' (default): at each stage's start the pairs above "
        "dop_min are ranked by DoP and walked from the most polarized down in bins (dop_evidence_bin pairs, "
        "at least 2% of them); the floor is the DoP at which a bin's observed AoP stops agreeing with the "
        "current surface's azimuths clearly better than chance (mean azimuth distance eta above "
        "dop_evidence_ratio of chance's pi/8), never below dop_min. Where even the most polarized pairs "
        "agree no better than chance (an unpolarized surface: its DoP is noise, sensor and Monte Carlo "
        "noise and demosaicing's false polarization at albedo edges) E_pol is off for the stage; the floor "
        "is in report.json per stage. Measured in the README.",
    )
    dop_evidence_ratio: float = Field(
        default=0.7,
        gt=0.0,
        le=1.0,
        description="With dop_min_noise 'evidence': a bin of pairs counts as polarized evidence while its mean "
        "azimuth distance to the current surface is at most this fraction of chance's (pi/8, 22.5 deg: the "
        "mean for an AoP unrelated to the surface). Measured: an unpolarized Mitsuba surface's bins sit at "
        "0.90-1.0 below DoP 0.1; an environment-lit plastic's at 0.64 (DoP 0.05-0.065) and 0.35-0.47 above 0.1. "
        "0.7 (default since session 28, with aop_noise 'closure') measured better than 0.8 on path-traced "
        "captures at 32 spp (README).",
    )
    dop_evidence_bin: int = Field(
        default=1000,
        ge=10,
        description="With dop_min_noise 'evidence': the least number of pairs per bin (bins are also at "
        "least 2% of the pairs above dop_min), so that a bin's mean azimuth distance has a standard error "
        "of at most 0.4 deg (13 deg / sqrt(1000) for a random AoP).",
    )
    stokes_smoothing_px: float = Field(
        default=0.0,
        ge=0.0,
        le=16.0,
        description="Before E_pol samples them, each view's normalized linear Stokes (rho cos 2 phi, rho sin 2 "
        "phi) is averaged with a Gaussian of this standard deviation in pixels over the valid pixels "
        "(normalized convolution: the mask's outside does not leak in) and the AoP and DoP are taken from "
        "the average. Noise that demosaicing turns into false polarization cancels; the surface's own "
        "polarization, smooth across a few pixels, stays. 0: off. Measured in the README.",
    )


class PhoOptions(_Options):
    """The photometric terms E_pho and E_psm: observed intensity, shading model, robust loss."""

    intensity: Literal["min", "int"] = Field(
        default="min",
        description="Observed colour in E_pho: 'min' = I_min = (1 - rho) I_int (the paper's), 'int' = I_int.",
    )
    intensity_scale: Literal["median", "absolute"] = Field(
        default="absolute",
        description="What E_pho and E_psm measure intensities in. 'median': multiples of the capture's median "
        "observed intensity (colour mean over every view's valid pixels) times intensity_units, so the balance "
        "between the terms does not depend on the exposure, the lighting's brightness or how much of the frame "
        "highlights take (use intensity_units 6.4 with it: the same balance at the built-in renderer's median of "
        "0.2); 'absolute': the capture's normalized units times intensity_units. Measured in the README.",
    )
    intensity_units: float = Field(
        default=32.0,
        gt=0.0,
        description="Intensities and albedos are multiplied by this in E_pho and E_psm (after dividing by the "
        "capture's median intensity with intensity_scale='median'). It sets the balance between E_pho/E_psm "
        "and E_pol/E_gsm, which the paper's tau weights assume but the paper's units do not fix. 32 ('absolute') "
        "measured best on the Stanford models (32 beat 64: bunny 46% -> 52% and 12% -> 15%, dragon 34% -> 38% "
        "and 13% -> 15%); 6.4 with 'median' is the same balance at the built-in renderer's median of 0.2.",
    )
    diffuse_fresnel_ior: float = Field(
        default=0.0,
        ge=0.0,
        description="E_pho's diffuse model. 0: Lambertian (the paper's). n > 1: the rendered colour of each "
        "(vertex, view) pair is multiplied by the unpolarized Fresnel transmittance toward the camera of a "
        "dielectric of index n, relative to normal emission (a smooth plastic's diffuse lobe, as Mitsuba's "
        "pplastic renders it: 0.95 at 60 degrees, 0.80 at 75 degrees for n = 1.5). Measured in the README.",
    )
    diffuse_dop_ior: float = Field(
        default=0.0,
        ge=0.0,
        description="Only with intensity 'min' (rejected with 'int'): n > 1 multiplies the rendered colour of each (vertex, view) pair by "
        "1 - rho_d, the fraction of a dielectric's diffuse light I_min keeps (its diffuse DoP rho_d = (T_p - "
        "T_s) / (T_p + T_s) at the emission angle, index n): a diffuse surface is darker in I_min toward grazing "
        "(0.96 at 45 degrees, 0.90 at 60 for n = 1.5), which the Lambertian model reads as a tilted normal. "
        "0: off (default: no gain measured on the built-in or Mitsuba bunny, since each view's SH shading already "
        "absorbs a darkening that depends on the normal; README).",
    )
    shadowing: Literal["none", "cast"] = Field(
        default="none",
        description="E_pho's shading. 'none': every vertex sees the whole hemisphere above it (the paper's). "
        "'cast': at each stage's start, rays along shadow_directions directions from every vertex find the "
        "part of the hemisphere the surface itself blocks, and each (vertex, view) pair's rendered colour is "
        "multiplied by the unblocked share of its irradiance under the view's lighting (fixed for the stage, "
        "like the pairs), so concavities are not read as tilted normals. Off: no gain on the Mitsuba dragon "
        "(accuracy gain +25.8% -> +25.6%), whose per-vertex albedo absorbs shadows that its nearly "
        "world-fixed lighting casts alike in every view (README).",
    )
    shadow_directions: int = Field(
        default=128,
        ge=8,
        le=4096,
        description="With shadowing 'cast': directions over the sphere (Fibonacci) tested from each vertex.",
    )
    shadow_bounce: float = Field(
        default=0.0,
        ge=0.0,
        le=1.0,
        description="With shadowing 'cast': the share of the blocked light that the blocking surface sends "
        "back (inter-reflection, not otherwise modelled); 0: none.",
    )
    robust: Literal["none", "cauchy", "specular"] = Field(
        default="cauchy",
        description="E_pho's loss. 'none': least squares (the paper's). 'cauchy': from stage 2 on, each pair's "
        "squared residual is weighted by the Cauchy weight 1 / (1 + (r / s)^2) of its residual r at the "
        "stage's start (s = pho_robust_scale times the median residual), fixed for the stage like the "
        "pairs: specular residue, cast shadows and misregistered samples lose their pull. Measured in the "
        "README.",
    )
    robust_scale: float = Field(
        default=0.5,
        gt=0.0,
        description="Scale s of the Cauchy weights of pho_robust, in multiples of the stage's median E_pho "
        "residual (RGB norm).",
    )
    robust_first_stage: bool = Field(
        default=False,
        description="With pho_robust and the lighting pre-fit: stage 1's Cauchy weights come from the pre-fit's "
        "residuals (False: stage 1 is least squares, the robust weights start at stage 2). Measured in the README.",
    )
    psm_sigma_chroma: float = Field(
        default=0.05,
        gt=0.0,
        description="E_psm weight w_ij = exp(-|c_i - c_j|^2 / s_c^2) exp(-(log I_i - log I_j)^2 / s_I^2): s_c, "
        "on chromaticity c = RGB / (R + G + B) of the observed colours.",
    )
    psm_sigma_log_intensity: float = Field(
        default=0.3, gt=0.0, description="s_I of the E_psm weight, on log mean intensity."
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
        description="Order of each view's shading S(N) in E_pho. 2: the paper's 9 SH terms (pmvir-sh9), "
        "which hold a Lambertian surface's shading under any distant lighting to about 1%. 3 and 4 add the "
        "degree-3 and degree-4 harmonics (16 and 25 terms): a Lambertian surface has almost none, but a "
        "view's glossy residue in I_min under a small bright source is a function of the normal in that "
        "view, which they can hold. 4 (default) measured best: environment-lit Mitsuba blob at 80 "
        "iterations +22.5% / +5.3% (2: +19.9% / +4.1%), MVIR +12.5% / -4.4% (2: +4.0% / -6.9%); built-in "
        "knot and gear slightly better too. illumination.json keeps the pmvir-sh9 part (their "
        "least-squares projection) in 'sh' and the rest in 'sh_high'. Measured in the README.",
    )
    coupling: float = Field(
        default=0.0,
        ge=0.0,
        le=1e6,
        description="After the last stage, the lighting and albedo are fitted once more with the geometry held "
        "and E_light added with this weight: it pulls each view's order-2 lighting (L_scale times the first 9 "
        "SH terms) toward the views' mean, in units of the mean lighting at the fit's start (the paper lights "
        "each image freely). A view's data fix its lighting only for the normals facing it; the coupling lets "
        "the other views fix the rest (the spec's illumination error is over the whole sphere). Held out of "
        "the stages, where it cost accuracy. 0: off (the paper's; default, since 0.1 halved the illumination "
        "error on path-traced captures but made the albedo worse on two of three models). README.",
    )
    final_iterations: int = Field(
        default=40,
        ge=1,
        le=100_000,
        description="L-BFGS iterations of the final lighting fit (with lighting_coupling > 0).",
    )
    prefit_iterations: int = Field(
        default=0,
        ge=0,
        le=100_000,
        description="Before the first stage, L-BFGS iterations fitting the per-view lighting (and the albedo) "
        "to the initial surface with the geometry held; with pho_robust the first stage's Cauchy weights then "
        "come from that fit's residuals instead of the first stage running least squares. 0: none (the "
        "paper's start). Measured in the README.",
    )


class ViewOptions(_Options):
    """Which (vertex, view) pairs each stage samples."""

    min_cos: float = Field(
        default=0.35,
        ge=-1.0,
        lt=1.0,
        description="A (vertex, view) pair enters a stage only when the vertex normal makes a cosine of at "
        "least this with the direction to the camera (0.35: within 69.5 degrees). Grazing pairs sample a "
        "stretched footprint and pull the surface off the truth; -1 keeps every visible pair, as the paper. "
        "0.35 measured best on the path-traced (Mitsuba) captures, whose folds and thin parts are seen mostly "
        "obliquely (three Stanford models +35.6% accuracy against +32.7% with 0.5); the built-in renderer's "
        "average loses 1.9 points with it (measurements in the README's Refinement section).",
    )
    min_pairs: int = Field(
        default=2,
        ge=0,
        description="Each vertex keeps at least this many of its most frontal visible pairs even below "
        "min_view_cos, so that parts seen only obliquely (a sparse rig, the poles of a ring) stay placed.",
    )
    silhouette_margin_px: int = Field(
        default=2,
        ge=0,
        le=64,
        description="Pixels within this distance of an observation's invalid region (outside the mask, "
        "saturated) are not sampled: demosaicing mixes the background into them, so a vertex seen there "
        "looks darker (or brighter) than it is and E_pho pulls it toward the image's interior, i.e. into "
        "the object. Measured in the README.",
    )
    refresh_visibility: bool = Field(
        default=True, description="Recompute visibility from the refined surface between stages."
    )


class SolverOptions(_Options):
    """The L-BFGS solve of each stage: iterations, stopping, unknowns, preconditioning."""

    max_iterations: int = Field(
        default=80,
        ge=1,
        le=100_000,
        description="Most L-BFGS iterations per stage. 80: on the Stanford models every stage still lowers "
        "the cost at 40 (accuracy gain 33% at 40, 39% at 80), and 300k vertices x 36 views x 3 stages of 80 "
        "take about 7 minutes on 2 CPU cores (bench/refine_speed.py).",
    )
    rel_tolerance: float = Field(
        default=1e-5,
        ge=0.0,
        description="A stage stops when one iteration lowers the cost by less than this fraction of it.",
    )
    grad_tolerance: float = Field(
        default=1e-9, ge=0.0, description="A stage stops when the largest gradient component is at most this."
    )
    history_size: int = Field(default=10, ge=1, le=100, description="L-BFGS memory (correction pairs).")
    albedo_solve: Literal["projected", "joint"] = Field(
        default="projected",
        description="'projected': at every evaluation the albedo is set to its exact minimizer for the current "
        "geometry and lighting (E_pho + tau_psm E_psm is quadratic in it; variable projection, same minimizers, "
        "much faster convergence); 'joint': the albedo is one more block of L-BFGS unknowns.",
    )
    precondition_lambda: float = Field(
        default=20.0,
        ge=0.0,
        description="Strength lam of the L-BFGS preconditioner on vertex motion, ~(I + lam L)^-1 with L the "
        "mesh graph Laplacian (0: none). Larger values let smooth, large-scale surface motion converge faster.",
    )
    precondition_iterations: int = Field(
        default=30, ge=0, le=1000, description="Terms of the Neumann series approximating the preconditioner."
    )
    vertex_motion: Literal["normal", "free"] = Field(
        default="free",
        description="'free': full 3D vertex motion (3 unknowns per vertex; measured more accurate); 'normal': "
        "each vertex moves along its normal at the start of the stage (1 unknown per vertex).",
    )


class OffsetScanOptions(_Options):
    """The offset scan: the whole mesh moved along its normals to where the views agree best."""

    mode: Literal["off", "start", "stages"] = Field(
        default="stages",
        description="Move the whole mesh along its vertex normals by the offset (within +-1.5 pixels of ground "
        "sampling distance; +-0.75 in the later scans) at which the views agree best: each view's pixels are "
        "carried into its two nearest views through the mesh and compared by ZNCC over 5x5 windows. 'start': "
        "before stage 1; 'stages' "
        "(default): before every stage and after the last; 'off': never. The stages' terms see normals, not "
        "absolute position, so they keep the inward bias the plane sweep leaves on thin and curved parts "
        "(knot: accuracy gain +11.4% -> +20.1% on the built-in renderer, +14.7% -> +21.2% on Mitsuba; "
        "Mitsuba blob: +24.8% -> +28.7%); measured in the README.",
    )
    specular: Literal["off", "same"] = Field(
        default="off",
        description="For a specular-dominated capture (pmvir.pipeline: the median over views of each view's "
        "median DoP inside its mask above 0.2, SPECULAR_MEDIAN_DOP): 'off' refines it without the offset "
        "scan, 'same' keeps offset_scan. A mirror's views agree best at the depth of its reflections, behind "
        "the surface. Path-traced smooth conductors (36 views 612x512), full method, accuracy gain with the "
        "scans -> without: armadillo -37.2 % -> +17.9 %, bunny +21.3 % -> +12.6 %, dragon +8.8 % -> +0.3 %; "
        "average -2.4 % -> +10.3 % (README). Applied by the pipeline, which knows the masks; "
        "refine_surface takes offset_scan as given.",
    )
    deblur_px: float = Field(
        default=1.6,
        ge=0.0,
        description="With offset_scan: the Gaussian blur (pixels) the decoded images are taken to hold, or 0 "
        "(off); each scan runs again on the images blurred by it and extrapolates its offset to no blur (2 o - "
        "o_blurred). Blur moves the scan's minimum inward in proportion to its variance; the default "
        "demosaicing acts like 1.6 px: at the true surfaces this takes the scan from -0.08..-0.27 px to "
        "-0.01..-0.14 px, and it raised the refined accuracy on all five measured captures (built-in bunny, "
        "dragon, armadillo; Mitsuba knot and blob; README). Doubles the scans' time.",
    )
    min_cos: float = Field(
        default=0.8,
        gt=0.0,
        lt=1.0,
        description="With offset_scan: only pixels whose triangle both views see at least at this viewing cosine "
        "count (grazing pairs pull the scan's minimum inward, as they do the plane sweep's depths).",
    )


class SurfaceMoveOptions(_Options):
    """Moves of the surface outside the stages: hull fit, rim fit and tangential relaxation."""

    hull_tolerance_px: float | None = Field(
        default=0.5,
        ge=0.0,
        description="After every offset scan and after the last stage, vertices that project more than this "
        "many pixels outside some view's mask move inward along their normals until they do (at most 3 px; "
        "pmvir.geometry.silhouette.hull_fit; needs the masks: refine_surface's masks argument). The stages' terms see "
        "normals, not position, and the scans move the whole mesh, so thin parts drift out past their "
        "silhouettes. None: off. Measured in the README.",
    )
    rim_fit_gain: float = Field(
        default=0.5,
        ge=0.0,
        le=1.0,
        description="After the last stage (and its hull fit), vertices near some view's rim that project more "
        "than a quarter pixel inside that view's mask, measured along their normals to the mask's boundary, move "
        "outward by this share of the excess, spread over the shoulders around them (pmvir.geometry.silhouette.hull_fit."
        "fit_to_rims; needs the masks). Stereo leaves weakly textured parts inside the surface, where neither the "
        "offset scans nor the shading see it. 0: off; 1 moves the whole excess (the excess includes the rims' own "
        "inset, which the truth has too: 0.5 measured best). Measured in the README.",
    )
    rim_fit_mask_margin_px: float | None = Field(
        default=None,
        ge=0.0,
        lt=4.0,
        description="How far (pixels) the masks reach past the object's true outline, discounted by the rim fit. "
        "None (default): estimated from the rims, as the 10th percentile of the vertices' distances inside the "
        "masks (0 with exact masks; 1 with masks dilated by a pixel, which would otherwise push the whole surface "
        "out: the path-traced bunny's accuracy went from 0.089 to 0.149e-2), where the offset scans run; 0 where "
        "they are off (a specular-dominated capture: its surface lies inside all round, which the estimate would "
        "take for a margin). A number: the known margin (0 trusts the masks as drawn). An estimate of 0.5 px or "
        "more beyond the margin used (beyond 0, where estimated) adds a warning to report.json. Measured in the "
        "README.",
    )
    relax_iterations: int = Field(
        default=20,
        ge=0,
        le=1000,
        description="After the last stage, steps of tangential relaxation: every interior vertex moves toward the "
        "centroid of its one-ring, along the surface only, and is projected back onto the refined surface, so "
        "vertices crowded by free motion spread out again without moving the surface (the albedo is solved again "
        "at the new positions). Completeness is measured to the nearest vertex, so crowding costs it even where "
        "the surface improved. 0: off. Measured in the README.",
    )


class RefineOptions(_Options):
    """Photometric and polarimetric refinement (pipeline stage 3, paper section 4.3 and 5.1).

    The cost E_pho + tau_pol E_pol + tau_gsm E_gsm + tau_psm E_psm is minimized in stages (see
    :class:`StageOptions`); the groups hold the options of each term and step.
    """

    demosaic: Literal["same"] | DemosaicMethod = Field(
        default="eari",
        description="Demosaicing of the frames the refinement fits (E_pho, E_pol, E_psm): 'same' uses the decode "
        "stage's images (decode.demosaic); a method name decodes the registered frames once more with it, for "
        "the refinement only (SfM, dense stereo, previews and exports keep decode.demosaic's). 'eari' (default) "
        "keeps the pixel-scale relief that 'guided' smooths out of the AoP: accuracy gain on the built-in "
        "Stanford captures +26.7% -> +42.4% on average (armadillo +22.8% -> +44.0%), on Mitsuba-rendered ones "
        "+24.9% -> +30.6%. Measured in the README.",
    )
    device: str = Field(
        default="auto",
        pattern=r"^(auto|cpu|cuda(:[0-9]+)?)$",
        description="Torch device: 'auto' (CUDA when present, else CPU), 'cpu', 'cuda' or 'cuda:N'.",
    )
    dtype: Literal["float32", "float64"] = Field(default="float32", description="Floating-point precision.")

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
