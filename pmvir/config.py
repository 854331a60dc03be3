"""The one typed configuration tree.

The CLI (`pmvir reconstruct`), the HTTP job options (`POST /v1/jobs`) and the
pipeline all read these models: one place defines each parameter, its default,
its range and its meaning. Unknown keys are errors (``extra="forbid"``).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator


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


class RefineOptions(_Options):
    """Photometric and polarimetric refinement (pipeline stage 3, paper section 4.3 and 5.1).

    The cost E_pho + tau_pol E_pol + tau_gsm E_gsm + tau_psm E_psm is minimized in stages;
    stage s uses the s-th entry of each per-stage list (all lists must have the same length).
    """

    polarimetric: bool = Field(
        default=True, description="Use the polarimetric term E_pol (False: the MVIR baseline, --no-polarimetric)."
    )
    dop_weight: bool = Field(default=True, description="Weight each E_pol pair by its observed DoP rho.")
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
    max_iterations: int = Field(default=40, ge=1, description="Most L-BFGS iterations per stage.")
    rel_tolerance: float = Field(
        default=1e-5,
        ge=0.0,
        description="A stage stops when one iteration lowers the cost by less than this fraction of it.",
    )
    grad_tolerance: float = Field(
        default=1e-9, ge=0.0, description="A stage stops when the largest gradient component is at most this."
    )
    history_size: int = Field(default=10, ge=1, le=100, description="L-BFGS memory (correction pairs).")
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
        default="normal",
        description="'normal': each vertex moves along its normal at the start of the stage (1 unknown per "
        "vertex); 'free': full 3D motion (3 unknowns per vertex).",
    )
    intensity_units: float = Field(
        default=255.0,
        gt=0.0,
        description="Intensities and albedos (normalized capture units) are multiplied by this in E_pho "
        "and E_psm: 255 puts them in 8-bit pixel units, for which the paper's tau weights were tuned.",
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
    def _same_stage_count(self) -> "RefineOptions":
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
    stop_after: Literal["decode", "geometry", "refine"] = Field(
        default="refine", description="Last stage to run."
    )
