"""The one typed configuration tree.

The CLI (`pmvir reconstruct`), the HTTP job options (`POST /v1/jobs`) and the
pipeline all read these models: one place defines each parameter, its default,
its range and its meaning. Unknown keys are errors (``extra="forbid"``).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from pmvir.stages import Stage


class _Options(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class DecodeOptions(_Options):
    """Demosaicing and polarization quantities (pipeline stage 1)."""

    noise_floor: float = Field(
        default=0.01,
        ge=0.0,
        lt=1.0,
        description="Pixels whose mean intensity (I_int averaged over colours, = s0 / 2, normalized "
        "units) is at or below this are invalid: AoP/DoP are undefined there.",
    )
    demosaic: Literal["bilinear", "edge-aware"] = Field(
        default="bilinear",
        description="Colour (Bayer) interpolation of each polarizer angle's half-resolution image: "
        "'bilinear' (float32) or 'edge-aware' (OpenCV's edge-aware demosaicing, 16-bit); the "
        "polarization interpolation back to full resolution is bilinear in both. Bilinear measured as "
        "accurate or better for AoP/DoP (bench/demosaic.py). Monochrome sensors: no colour step.",
    )


class GeometryOptions(_Options):
    """Initial geometry (pipeline stage 2, paper section 4.2): visibility and subdivision."""

    # -- poses: known-pose triangulation or SfM (pmvir.geometry.sfm)
    min_registered_views: int = Field(
        default=3,
        ge=2,
        description="Poses fail (ReconstructionError naming the views that failed) when fewer views than "
        "this are registered by SfM.",
    )
    min_registered_fraction: float = Field(
        default=0.5,
        ge=0.0,
        le=1.0,
        description="Poses also fail when SfM registers less than this fraction of the views (a capture "
        "that falls apart into pieces would otherwise give a partial object).",
    )
    min_sparse_points: int = Field(
        default=50,
        ge=1,
        description="Poses fail when fewer 3D points than this are triangulated from 3 or more views (a "
        "textureless object, or frames that do not overlap: chance matches seldom agree in 3 views); "
        "dense stereo takes its view pairs and depth ranges from them.",
    )
    sift_max_features: int = Field(default=4096, ge=64, description="Most SIFT features extracted per view.")
    sift_peak_threshold: float = Field(
        default=0.002,
        gt=0.0,
        description="SIFT detection threshold on the difference-of-Gaussians peak (COLMAP's default "
        "0.0067 finds too few features on smooth, weakly textured objects).",
    )
    sift_affine_shape: bool = Field(
        default=True,
        description="Affine-adapted SIFT (COLMAP estimate_affine_shape): about twice the extraction time, "
        "but features survive the 30-45 degree viewpoint changes of a ring of views far better.",
    )
    sift_upsample: bool = Field(
        default=True,
        description="Detect SIFT features on the image upsampled 2x (COLMAP first_octave -1): more small "
        "features (which small objects need), about 3x the extraction time.",
    )
    sift_equalize: bool = Field(
        default=True,
        description="Contrast-limited adaptive histogram equalization (CLAHE) of the 8-bit grey images "
        "before SIFT: more features on weakly textured surfaces.",
    )
    exhaustive_matching_max_views: int = Field(
        default=50,
        ge=2,
        description="Match every pair of views up to this many views; above it, each view is matched with "
        "its sequential_matching_overlap successors in capture order (and quadratically spaced ones).",
    )
    sequential_matching_overlap: int = Field(
        default=12, ge=1, description="Successors in capture order each view is matched with (many views)."
    )
    sfm_init_min_inliers: int = Field(
        default=50,
        ge=15,
        description="Verified matches the initial view pair of incremental SfM needs (COLMAP: 100).",
    )
    sfm_register_min_inliers: int = Field(
        default=15,
        ge=6,
        description="2D-3D inliers a view needs to be registered by incremental SfM (COLMAP: 30).",
    )
    sfm_max_reprojection_error: float = Field(
        default=2.0,
        ge=0.0,
        description="After incremental SfM, observations reprojecting farther than this (pixels) are "
        "dropped and a last bundle adjustment with a robust (Cauchy, 1 px) loss refines poses, focal "
        "lengths and points (0: skip; COLMAP keeps observations up to 4 px).",
    )
    sfm_shared_intrinsics: bool = Field(
        default=True,
        description="Without given intrinsics, views of one image size share one estimated camera "
        "(one focal length: far better constrained than one per view).",
    )
    sfm_seed: int = Field(default=0, ge=0, description="Random seed of RANSAC and view selection in SfM.")

    visibility_min_cos: float = Field(
        default=0.05,
        ge=-1.0,
        lt=1.0,
        description="A vertex is back-facing (not visible) in a view when the cosine between its "
        "area-weighted normal and the direction to the camera centre is at most this (0.05: about 87 "
        "degrees; grazing vertices land on mixed silhouette pixels).",
    )
    visibility_rel_tol: float = Field(
        default=1e-4,
        gt=0.0,
        lt=0.5,
        description="Relative tolerance of the ray-cast occlusion test: a triangle occludes a vertex "
        "only if it crosses the camera-to-vertex segment before (1 - tol) of its length.",
    )
    subdivision_max_area_px: float = Field(
        default=2.0,
        gt=0.0,
        description="sqrt(3) subdivision is repeated until every triangle's projected area, in each "
        "view that sees it, is below this many pixels^2. A step divides areas by 3, so the largest ends "
        "in [2/3, 2) px^2; with about two triangles per vertex that is at most about 4 px^2 (a vertex "
        "every 2 pixels) in the view that sees the surface largest: near the image resolution the "
        "refinement samples, at a quarter of the vertices (and cost) of a 0.5 px^2 threshold.",
    )
    subdivision_max_rounds: int = Field(
        default=6, ge=0, le=12, description="Most sqrt(3) steps (each triples the face count)."
    )
    subdivision_max_vertices: int = Field(
        default=2_000_000,
        ge=3,
        description="Subdivision stops before a step that would make the mesh exceed this many vertices.",
    )
    subdivision_min_visible_corners: Literal[1, 2, 3] = Field(
        default=3,
        description="A face counts as visible in a view when at least this many of its corners are; "
        "a vertex added by subdivision is visible in the views in which the input face it lies on is "
        "(3: all corners, conservative: no new vertex gets a view in which part of its face may be hidden).",
    )
    # -- dense multi-view stereo (pmvir.geometry.mvs*)
    mvs_backend: Literal["auto", "cpu", "colmap-cuda"] = Field(
        default="auto",
        description="Dense stereo: 'cpu' (pmvir's plane sweep), 'colmap-cuda' (COLMAP PatchMatch and "
        "stereo fusion through pycolmap, needs pycolmap built with CUDA), 'auto' (colmap-cuda when "
        "pycolmap.has_cuda, else cpu).",
    )
    mvs_scale: float = Field(
        default=0.5,
        gt=0.0,
        le=1.0,
        description="CPU stereo works on images resampled by this factor (0.5: half width and height, "
        "a quarter of the pixels; chosen for the time budget on two cores).",
    )
    mvs_colour: bool = Field(
        default=True,
        description="CPU stereo matches the three colour channels (ZNCC with covariances and variances "
        "summed over colours); False: their mean (faster, loses hue-only texture).",
    )
    mvs_neighbours: int = Field(
        default=5, ge=1, le=20, description="Source views matched against each reference view."
    )
    mvs_top_k: int = Field(
        default=2,
        ge=1,
        le=20,
        description="Per pixel, the mean of this many best neighbour costs is the aggregated cost "
        "(robust to occlusion and highlights in the other neighbours).",
    )
    mvs_planes: int = Field(
        default=96, ge=8, le=1024, description="Fronto-parallel depth planes, evenly spaced in inverse depth."
    )
    mvs_window: int = Field(
        default=7, ge=3, le=31, description="ZNCC window side in pixels of the stereo grid (odd)."
    )
    mvs_min_score: float = Field(
        default=0.3,
        ge=-1.0,
        lt=1.0,
        description="Smallest aggregated ZNCC for a depth to be kept before the consistency filter.",
    )
    mvs_min_angle_deg: float = Field(
        default=5.0, ge=0.0, lt=90.0, description="Smallest triangulation angle of a neighbour view, degrees."
    )
    mvs_max_angle_deg: float = Field(
        default=60.0,
        gt=0.0,
        le=180.0,
        description="Largest triangulation angle of a neighbour view, degrees.",
    )
    mvs_depth_margin: float = Field(
        default=0.1,
        ge=0.0,
        le=2.0,
        description="A view's depth range (1st to 99th percentile of its sparse points' depths) is "
        "widened on both sides by this fraction of its far depth.",
    )
    mvs_consistency_px: float = Field(
        default=1.0,
        gt=0.0,
        description="Geometric consistency: largest forward-backward reprojection error, pixels of the "
        "stereo grid.",
    )
    mvs_consistency_depth: float = Field(
        default=0.01, gt=0.0, lt=1.0, description="Geometric consistency: largest relative depth difference."
    )
    mvs_min_consistent: int = Field(
        default=2,
        ge=1,
        le=20,
        description="A depth is fused when at least this many other views agree with it.",
    )
    mvs_voxel: float = Field(
        default=0.002,
        ge=0.0,
        description="Fused points are thinned to one per cube of this side, a fraction of the sparse "
        "points' bounding-box diagonal (0: no thinning).",
    )
    mvs_min_points: int = Field(
        default=1000,
        ge=100,
        description="Fewer fused points than this is a ReconstructionError (textureless or non-overlapping "
        "views), not an empty mesh.",
    )
    mvs_min_consistent_fraction: float = Field(
        default=0.05,
        ge=0.0,
        lt=1.0,
        description="CPU stereo: when on average less than this fraction of a registered view's object "
        "(mask) pixels (without a mask: of its depths) gets a depth that passes the consistency filter, the "
        "views are textureless or do not overlap: a ReconstructionError (measured: textured synthetic "
        "captures 0.15-0.75, a textureless sphere and frames with unrelated textures at most 0.02).",
    )
    # -- initial surface (pmvir.geometry.surface)
    surface_poisson_depth: int | None = Field(
        default=None,
        ge=5,
        le=12,
        description="Screened Poisson octree depth (grid at most 2^depth per side); None: automatic, the "
        "depth whose finest cell is closest to surface_poisson_voxel_px full-resolution pixels at the median "
        "viewing distance, clamped to 6..10.",
    )
    surface_poisson_voxel_px: float = Field(
        default=3.0,
        gt=0.0,
        description="Automatic Poisson depth: target finest-cell size in full-resolution pixels (3: measured "
        "more accurate than 1.5 on the benchmark models, the coarser grid averaging the stereo noise, and "
        "3x faster).",
    )
    surface_trim_density_quantile: float = Field(
        default=0.0,
        ge=0.0,
        lt=1.0,
        description="Poisson vertices whose octree sample density is below this quantile are removed "
        "(0: off; the distance and silhouette trimming remove unobserved parts without cutting holes "
        "into well observed ones).",
    )
    surface_trim_distance: float = Field(
        default=0.01,
        gt=0.0,
        description="Poisson vertices farther than this fraction of the dense points' bounding-box "
        "diagonal from every dense point are removed (unobserved guesses).",
    )
    surface_target_faces: int = Field(
        default=150_000, ge=100, description="The trimmed surface is simplified to at most this many faces."
    )
    surface_min_angle_deg: float = Field(
        default=2.0,
        ge=0.0,
        lt=30.0,
        description="Triangles with a smaller interior angle (degrees) are slivers and are collapsed.",
    )
    surface_split_factor: float = Field(
        default=1.75,
        ge=1.0,
        description="Before visibility and subdivision, faces projecting larger than this times "
        "subdivision_max_area_px (in a view they face) are bisected, so that the uniform sqrt(3) "
        "subdivision needs one step fewer (1.75: one step then brings the largest below the threshold).",
    )

    @model_validator(mode="after")
    def _check_mvs(self) -> GeometryOptions:
        if self.mvs_window % 2 == 0:
            raise ValueError(f"mvs_window must be odd, got {self.mvs_window}")
        if self.mvs_min_angle_deg >= self.mvs_max_angle_deg:
            raise ValueError(
                f"mvs_min_angle_deg ({self.mvs_min_angle_deg}) must be below mvs_max_angle_deg "
                f"({self.mvs_max_angle_deg})"
            )
        return self


class RefineOptions(_Options):
    """Photometric and polarimetric refinement (pipeline stage 3, paper section 4.3 and 5.1).

    The cost E_pho + tau_pol E_pol + tau_gsm E_gsm + tau_psm E_psm is minimized in stages;
    stage s uses the s-th entry of each per-stage list (all lists must have the same length).
    """

    polarimetric: bool = Field(
        default=True,
        description="Use the polarimetric term E_pol (False: the MVIR baseline, --no-polarimetric).",
    )
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
    dop_min: float = Field(
        default=0.035,
        ge=0.0,
        lt=1.0,
        description="Pairs whose observed DoP at the start of a stage is below this are left out of E_pol for "
        "the stage: their AoP is noise. An unpolarized surface seen with normalized Stokes noise 0.01 shows "
        "Rayleigh-distributed DoP of mean 0.0125 with random AoP; fewer than 0.3% of its pairs exceed 0.035. "
        "0 keeps every pair, as the paper's equation does.",
    )
    intensity: Literal["min", "int"] = Field(
        default="min",
        description="Observed colour in E_pho: 'min' = I_min = (1 - rho) I_int (the paper's), 'int' = I_int.",
    )
    tau_pol: list[float] = Field(
        default=[60.0, 120.0, 360.0], min_length=1, description="Per stage: weight tau1 of E_pol."
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
    pol_k: float = Field(default=0.5, gt=0.0, description="Narrowness k of E_pol's concave cost.")
    max_iterations: int = Field(
        default=80,
        ge=1,
        description="Most L-BFGS iterations per stage. 80: on the Stanford models every stage still lowers "
        "the cost at 40 (accuracy gain 33% at 40, 39% at 80), and 300k vertices x 36 views x 3 stages of 80 "
        "take about 7 minutes on 2 CPU cores (bench/refine_speed.py).",
    )
    min_view_cos: float = Field(
        default=0.5,
        ge=-1.0,
        lt=1.0,
        description="A (vertex, view) pair enters a stage only when the vertex normal makes a cosine of at "
        "least this with the direction to the camera (0.5: within 60 degrees). Grazing pairs sample a "
        "stretched footprint and pull the surface off the truth (measurements in the README's Refinement "
        "section). -1 keeps every visible pair, as the paper.",
    )
    min_view_pairs: int = Field(
        default=2,
        ge=0,
        description="Each vertex keeps at least this many of its most frontal visible pairs even below "
        "min_view_cos, so that parts seen only obliquely (a sparse rig, the poles of a ring) stay placed.",
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
    intensity_units: float = Field(
        default=32.0,
        gt=0.0,
        description="Intensities and albedos (normalized capture units, [0, 1]) are multiplied by this in E_pho "
        "and E_psm. It sets the balance between E_pho/E_psm and E_pol/E_gsm, which the paper's tau weights "
        "assume but the paper's units do not fix. 32 is measured: on the Stanford models (plastic, 36 views) "
        "it beat 64 on accuracy and completeness (bunny 46% -> 52% and 12% -> 15%, dragon 34% -> 38% and "
        "13% -> 15%); 255 (8-bit units) leaves E_pol a tie-breaker.",
    )
    diffuse_fresnel_ior: float = Field(
        default=0.0,
        ge=0.0,
        description="E_pho's diffuse model. 0: Lambertian (the paper's). n > 1: the rendered colour of each "
        "(vertex, view) pair is multiplied by the unpolarized Fresnel transmittance toward the camera of a "
        "dielectric of index n, relative to normal emission (a smooth plastic's diffuse lobe, as Mitsuba's "
        "pplastic renders it: 0.95 at 60 degrees, 0.80 at 75 degrees for n = 1.5). Measured in the README.",
    )
    pho_robust: Literal["none", "cauchy"] = Field(
        default="cauchy",
        description="E_pho's loss. 'none': least squares (the paper's). 'cauchy': from stage 2 on, each pair's "
        "squared residual is weighted by the Cauchy weight 1 / (1 + (r / s)^2) of its residual r at the "
        "stage's start (s = pho_robust_scale times the median residual), fixed for the stage like the "
        "pairs: specular residue, cast shadows and misregistered samples lose their pull. Measured in the "
        "README.",
    )
    pho_robust_scale: float = Field(
        default=0.5,
        gt=0.0,
        description="Scale s of the Cauchy weights of pho_robust, in multiples of the stage's median E_pho "
        "residual (RGB norm).",
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
    refresh_visibility: bool = Field(
        default=True, description="Recompute visibility from the refined surface between stages."
    )
    device: str = Field(
        default="auto",
        pattern=r"^(auto|cpu|cuda(:[0-9]+)?)$",
        description="Torch device: 'auto' (CUDA when present, else CPU), 'cpu', 'cuda' or 'cuda:N'.",
    )
    dtype: Literal["float32", "float64"] = Field(default="float32", description="Floating-point precision.")

    @model_validator(mode="after")
    def _same_stage_count(self) -> RefineOptions:
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

    @property
    def n_stages(self) -> int:
        return len(self.tau_pol)


class PipelineConfig(_Options):
    """Everything a reconstruction run is told."""

    decode: DecodeOptions = Field(default_factory=DecodeOptions)
    geometry: GeometryOptions = Field(default_factory=GeometryOptions)
    refine: RefineOptions = Field(default_factory=RefineOptions)
    stop_after: Stage = Field(default=Stage.REFINE, description="Last stage to run.")
