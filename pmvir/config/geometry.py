"""Options of the initial geometry (pipeline stage 2), one group per step."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pmvir.config.base import _Options, advanced, basic
from pmvir.config.isolate import IsolateOptions
from pmvir.config.sfm import SfmOptions


class MvsOptions(_Options):
    """Dense multi-view stereo (:mod:`pmvir.geometry.mvs.dense`): depth maps, consistency, fusion."""

    backend: Literal["auto", "cpu", "colmap-cuda"] = Field(
        default="auto",
        description="Dense stereo: 'cpu' (pmvir's plane sweep), 'colmap-cuda' (COLMAP PatchMatch and stereo "
        "fusion through pycolmap, needs pycolmap built with CUDA), 'auto' (colmap-cuda when "
        "pycolmap.has_cuda, else cpu).",
        json_schema_extra=basic(),
    )
    scale: float = Field(
        default=0.5, gt=0.0, le=1.0,
        description="CPU stereo works on images resampled by this factor (0.5: a quarter of the pixels), "
        "never on a grid whose longer side is below min_grid_px, (0, 1].",
        json_schema_extra=advanced(),
    )
    min_grid_px: int = Field(
        default=160, ge=16,
        description="CPU stereo: the scale is raised (up to 1) so the longer image side keeps at least this "
        "many pixels.",
        json_schema_extra=advanced("px"),
    )
    unmasked_full_grid_px: int = Field(
        default=320, ge=0,
        description="CPU stereo without masks: views at most this many pixels on the longer side are matched "
        "first at full resolution (window 5), resolving gaps between an object's parts; 0: off.",
        json_schema_extra=advanced("px"),
    )
    unmasked_full_min_consistent: float = Field(
        default=0.15, ge=0.0, lt=1.0,
        description="CPU stereo without masks: the full-resolution grid is kept when at least this mean fraction "
        "of its depths is consistent, else the views are matched again on the half grid (noisy images), [0, 1).",
        json_schema_extra=advanced(),
    )
    colour: bool = Field(
        default=True,
        description="CPU stereo matches the three colour channels (ZNCC with covariances and variances "
        "summed over colours); False: their mean (faster, loses hue-only texture).",
        json_schema_extra=advanced(),
    )
    neighbours: int = Field(
        default=5, ge=1, le=20,
        description="Source views matched against each reference view.",
        json_schema_extra=advanced(),
    )
    top_k: int = Field(
        default=2, ge=1, le=20,
        description="Per pixel, the aggregated cost is the mean of this many best neighbour costs (robust to "
        "occlusion and highlights).",
        json_schema_extra=advanced(),
    )
    planes: int = Field(
        default=96, ge=8, le=1024,
        description="Fronto-parallel depth planes, evenly spaced in inverse depth.",
        json_schema_extra=advanced(),
    )
    window: int | None = Field(
        default=None, ge=3, le=31,
        description="ZNCC window side (px of the stereo grid, odd, 3..31). None: 3; 5 on the full-resolution "
        "grid of unmasked_full_grid_px; 7 for captures of at most sparse_rig_views registered views.",
        json_schema_extra=advanced("px"),
    )
    min_score: float = Field(
        default=0.3, ge=-1.0, lt=1.0,
        description="Smallest aggregated ZNCC for a depth to be kept before the consistency filter, [-1, 1).",
        json_schema_extra=advanced(),
    )
    min_angle_deg: float = Field(
        default=5.0, ge=0.0, lt=90.0,
        description="Smallest triangulation angle of a neighbour view, degrees.",
        json_schema_extra=advanced("deg"),
    )
    max_angle_deg: float = Field(
        default=60.0, gt=0.0, le=180.0,
        description="Largest triangulation angle of a neighbour view, degrees.",
        json_schema_extra=advanced("deg"),
    )
    depth_margin: float = Field(
        default=0.1, ge=0.0, le=2.0,
        description="A view's depth range (1st to 99th percentile of its sparse points' depths) is widened "
        "on both sides by this fraction of its far depth.",
        json_schema_extra=advanced(),
    )
    consistency_px: float = Field(
        default=1.0, gt=0.0,
        description="Geometric consistency: largest forward-backward reprojection error, pixels of the "
        "stereo grid.",
        json_schema_extra=advanced("px"),
    )
    consistency_depth: float = Field(
        default=0.01, gt=0.0, lt=1.0,
        description="Geometric consistency: largest relative depth difference.",
        json_schema_extra=advanced(),
    )
    min_consistent: int = Field(
        default=2, ge=1, le=20,
        description="A depth is fused when at least this many other views agree with it.",
        json_schema_extra=advanced(),
    )
    sparse_rig_views: int = Field(
        default=12, ge=0,
        description="Captures with at most this many registered views fuse a depth that one other view "
        "confirms (min_consistent lowered to 1).",
        json_schema_extra=advanced(),
    )
    max_occluding: int | None = Field(
        default=1, ge=0, le=20,
        description="CPU stereo: a depth is dropped where more than this many views (and no fewer than agree with "
        "it) see a surface in front of it along its ray; null: no occlusion test.",
        json_schema_extra=advanced(),
    )
    voxel: float = Field(
        default=0.002, ge=0.0,
        description="Fused points are thinned to one per cube of this side, a fraction of the sparse points' "
        "bounding-box diagonal (0: no thinning).",
        json_schema_extra=advanced("bbox diagonal"),
    )
    min_points: int = Field(
        default=1000, ge=100,
        description="Fewer fused points than this is a ReconstructionError (textureless or non-overlapping "
        "views), not an empty mesh.",
        json_schema_extra=advanced(),
    )
    min_consistent_fraction: float = Field(
        default=0.05, ge=0.0, lt=1.0,
        description="CPU stereo: below this mean fraction of a view's object pixels with a consistent depth, "
        "the views are textureless or do not overlap (ReconstructionError).",
        json_schema_extra=advanced(),
    )

    @model_validator(mode="after")
    def _check_window_and_angles(self) -> MvsOptions:
        if self.window is not None and self.window % 2 == 0:
            raise ValueError(f"window must be odd, got {self.window}")
        if self.min_angle_deg >= self.max_angle_deg:
            raise ValueError(
                f"min_angle_deg ({self.min_angle_deg}) must be below max_angle_deg ({self.max_angle_deg})"
            )
        return self


class SurfaceOptions(_Options):
    """The initial surface (:mod:`pmvir.geometry.surface.initial`): screened Poisson, trimming, cleaning."""

    poisson_depth: int | None = Field(
        default=None, ge=5, le=12,
        description="Screened Poisson octree depth, 5..12. None: the depth whose finest cell is closest to "
        "poisson_voxel_px at the median viewing distance, clamped to 6..10.",
        json_schema_extra=advanced(),
    )
    poisson_voxel_px: float = Field(
        default=3.0, gt=0.0,
        description="Automatic Poisson depth: target finest-cell size, in pixels of the working resolution "
        "(decode.max_working_size_px).",
        json_schema_extra=advanced("px"),
    )
    trim_density_quantile: float = Field(
        default=0.0, ge=0.0, lt=1.0,
        description="Poisson vertices whose octree sample density is below this quantile are removed (0: "
        "off; the distance and silhouette trimming remove unobserved parts without cutting holes into well "
        "observed ones).",
        json_schema_extra=advanced(),
    )
    trim_distance: float = Field(
        default=0.02, gt=0.0,
        description="Poisson vertices farther than this (fraction of the dense points' bounding-box "
        "diagonal) from every dense point are removed.",
        json_schema_extra=advanced("bbox diagonal"),
    )
    min_component_points: int = Field(
        default=200, ge=1,
        description="A surface component besides the largest is kept when at least this many fused points "
        "lie nearest to it; report.json lists every component.",
        json_schema_extra=advanced(),
    )
    target_faces: int = Field(
        default=150_000, ge=100,
        description="The trimmed surface is simplified to at most this many faces.",
        json_schema_extra=advanced(),
    )
    min_angle_deg: float = Field(
        default=2.0, ge=0.0, lt=30.0,
        description="Triangles with a smaller interior angle (degrees) are slivers and are collapsed.",
        json_schema_extra=advanced("deg"),
    )
    split_factor: float = Field(
        default=1.75, ge=1.0,
        description="Faces projecting larger than this times subdivision.max_area_px are bisected before "
        "visibility and subdivision (one sqrt(3) step fewer), >= 1.",
        json_schema_extra=advanced(),
    )
    hull_tolerance_px: float | None = Field(
        default=0.5, ge=0.0,
        description="After subdivision, vertices projecting more than this (px) outside a view's mask move "
        "inward along their normals (at most 3 px). None: off.",
        json_schema_extra=advanced("px"),
    )


class VisibilityOptions(_Options):
    """Per-vertex visibility (:mod:`pmvir.geometry.visibility`)."""

    min_cos: float = Field(
        default=0.05, ge=-1.0, lt=1.0,
        description="A vertex is back-facing in a view when the cosine between its normal and the direction "
        "to the camera is at most this, [-1, 1).",
        json_schema_extra=advanced(),
    )
    rel_tol: float = Field(
        default=1e-4, gt=0.0, lt=0.5,
        description="Ray-cast occlusion: a triangle occludes a vertex only if it crosses the "
        "camera-to-vertex segment before (1 - tol) of its length, (0, 0.5).",
        json_schema_extra=advanced(),
    )


class SubdivisionOptions(_Options):
    """sqrt(3) subdivision of the initial surface (:mod:`pmvir.geometry.subdivision`)."""

    max_area_px: float = Field(
        default=2.0, gt=0.0,
        description="sqrt(3) subdivision is repeated until every triangle's projected area, in each view "
        "that sees it, is below this (px^2 of the working resolution).",
        json_schema_extra=basic("px^2"),
    )
    max_rounds: int = Field(
        default=6, ge=0, le=12,
        description="Most sqrt(3) steps (each triples the face count).",
        json_schema_extra=advanced(),
    )
    max_vertices: int = Field(
        default=2_000_000, ge=3,
        description="Subdivision stops before a step that would exceed this many vertices.",
        json_schema_extra=advanced(),
    )
    min_visible_corners: Literal[1, 2, 3] = Field(
        default=3,
        description="A face is visible in a view when at least this many of its corners are (1..3); new "
        "vertices inherit their input face's views.",
        json_schema_extra=advanced(),
    )


class GeometryOptions(_Options):
    """Initial geometry (pipeline stage 2, paper section 4.2), one group per step, each passed whole to it."""

    sfm: SfmOptions = Field(default_factory=SfmOptions, description="Poses and sparse points.")
    mvs: MvsOptions = Field(default_factory=MvsOptions, description="Dense multi-view stereo.")
    surface: SurfaceOptions = Field(default_factory=SurfaceOptions, description="The initial surface.")
    visibility: VisibilityOptions = Field(
        default_factory=VisibilityOptions, description="Per-vertex visibility."
    )
    subdivision: SubdivisionOptions = Field(
        default_factory=SubdivisionOptions, description="sqrt(3) subdivision of the initial surface."
    )
    isolate: IsolateOptions = Field(
        default_factory=IsolateOptions, description="The object and its masks found in a capture without masks."
    )

