"""Options of the initial geometry (pipeline stage 2), one group per step."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, model_validator

from pmvir.config.base import _Options
from pmvir.config.sfm import SfmOptions


class MvsOptions(_Options):
    """Dense multi-view stereo (:mod:`pmvir.geometry.mvs.dense`): depth maps, consistency, fusion."""

    backend: Literal["auto", "cpu", "colmap-cuda"] = Field(
        default="auto",
        description="Dense stereo: 'cpu' (pmvir's plane sweep), 'colmap-cuda' (COLMAP PatchMatch and "
        "stereo fusion through pycolmap, needs pycolmap built with CUDA), 'auto' (colmap-cuda when "
        "pycolmap.has_cuda, else cpu).",
    )
    scale: float = Field(
        default=0.5,
        gt=0.0,
        le=1.0,
        description="CPU stereo works on images resampled by this factor (0.5: half width and height, "
        "a quarter of the pixels; chosen for the time budget on two cores), but never on a grid whose "
        "longer side is below min_grid_px.",
    )
    min_grid_px: int = Field(
        default=160,
        ge=16,
        description="CPU stereo grid: the scale is raised (up to 1) so that the longer image side keeps at "
        "least this many pixels (160: measured on 12-view 320x256 captures, full resolution gave 4x the pixels but a "
        "third of them consistent across views).",
    )
    colour: bool = Field(
        default=True,
        description="CPU stereo matches the three colour channels (ZNCC with covariances and variances "
        "summed over colours); False: their mean (faster, loses hue-only texture).",
    )
    neighbours: int = Field(
        default=5, ge=1, le=20, description="Source views matched against each reference view."
    )
    top_k: int = Field(
        default=2,
        ge=1,
        le=20,
        description="Per pixel, the mean of this many best neighbour costs is the aggregated cost "
        "(robust to occlusion and highlights in the other neighbours).",
    )
    planes: int = Field(
        default=96, ge=8, le=1024, description="Fronto-parallel depth planes, evenly spaced in inverse depth."
    )
    window: int | None = Field(
        default=None,
        ge=3,
        le=31,
        description="ZNCC window side in pixels of the stereo grid (odd). None: 3, or 7 for captures of at "
        "most sparse_rig_views registered views. A fronto-parallel window on a curved surface matches it at "
        "about the window's mean depth, behind a convex surface, so a small window keeps thin parts thick "
        "(measured on the built-in shapes, 36 views of 612x512, 7 -> 3: completeness of the knot's tube "
        "0.0031 -> 0.0020, the blob's 0.0012 -> 0.0010, mug and gear 0.0024 / 0.0021 -> 0.0014); with a few "
        "views a depth needs only one confirming view and the wider window's lower noise wins (8 views of "
        "320x256: accuracy 0.0063 with 7, 0.018 with 3).",
    )
    min_score: float = Field(
        default=0.3,
        ge=-1.0,
        lt=1.0,
        description="Smallest aggregated ZNCC for a depth to be kept before the consistency filter.",
    )
    min_angle_deg: float = Field(
        default=5.0, ge=0.0, lt=90.0, description="Smallest triangulation angle of a neighbour view, degrees."
    )
    max_angle_deg: float = Field(
        default=60.0,
        gt=0.0,
        le=180.0,
        description="Largest triangulation angle of a neighbour view, degrees.",
    )
    depth_margin: float = Field(
        default=0.1,
        ge=0.0,
        le=2.0,
        description="A view's depth range (1st to 99th percentile of its sparse points' depths) is "
        "widened on both sides by this fraction of its far depth.",
    )
    consistency_px: float = Field(
        default=1.0,
        gt=0.0,
        description="Geometric consistency: largest forward-backward reprojection error, pixels of the "
        "stereo grid.",
    )
    consistency_depth: float = Field(
        default=0.01, gt=0.0, lt=1.0, description="Geometric consistency: largest relative depth difference."
    )
    min_consistent: int = Field(
        default=2,
        ge=1,
        le=20,
        description="A depth is fused when at least this many other views agree with it.",
    )
    sparse_rig_views: int = Field(
        default=12,
        ge=0,
        description="Captures with at most this many registered views fuse a depth that one other view "
        "confirms (min_consistent is lowered to 1): their views are 45-90 degrees apart and seldom three "
        "agree (measured on 12-view 320x256 blobs: completeness 0.048 -> 0.017, accuracy 0.0022 -> 0.0029).",
    )
    voxel: float = Field(
        default=0.002,
        ge=0.0,
        description="Fused points are thinned to one per cube of this side, a fraction of the sparse "
        "points' bounding-box diagonal (0: no thinning).",
    )
    min_points: int = Field(
        default=1000,
        ge=100,
        description="Fewer fused points than this is a ReconstructionError (textureless or non-overlapping "
        "views), not an empty mesh.",
    )
    min_consistent_fraction: float = Field(
        default=0.05,
        ge=0.0,
        lt=1.0,
        description="CPU stereo: when on average less than this fraction of a registered view's object "
        "(mask) pixels (without a mask: of its depths) gets a depth that passes the consistency filter, the "
        "views are textureless or do not overlap: a ReconstructionError (measured: textured synthetic "
        "captures 0.15-0.75, a textureless sphere and frames with unrelated textures at most 0.02).",
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
        default=None,
        ge=5,
        le=12,
        description="Screened Poisson octree depth (grid at most 2^depth per side); None: automatic, the "
        "depth whose finest cell is closest to poisson_voxel_px full-resolution pixels at the median "
        "viewing distance, clamped to 6..10.",
    )
    poisson_voxel_px: float = Field(
        default=3.0,
        gt=0.0,
        description="Automatic Poisson depth: target finest-cell size in full-resolution pixels (3: measured "
        "more accurate than 1.5 on the benchmark models, the coarser grid averaging the stereo noise, and "
        "3x faster).",
    )
    trim_density_quantile: float = Field(
        default=0.0,
        ge=0.0,
        lt=1.0,
        description="Poisson vertices whose octree sample density is below this quantile are removed "
        "(0: off; the distance and silhouette trimming remove unobserved parts without cutting holes "
        "into well observed ones).",
    )
    trim_distance: float = Field(
        default=0.02,
        gt=0.0,
        description="Poisson vertices farther than this fraction of the dense points' bounding-box "
        "diagonal from every dense point are removed (unobserved guesses). 0.02 (0.01 before): the "
        "crevices where the knot's tube passes close to itself hold few fused points, and 0.01 cut holes "
        "there (measured on the built-in shapes, 36 views of 612x512: knot completeness 0.00202 -> "
        "0.00187, mug 0.00141 -> 0.00136, blob and gear unchanged, accuracy unchanged on all four).",
    )
    min_component_points: int = Field(
        default=200,
        ge=1,
        description="A connected component of the surface besides the largest is kept when at least this "
        "many fused points lie nearest to it (a thin handle or a second lobe cut off by trimming is real "
        "surface; a few stray points are not). report.json lists every component, kept or not, and why.",
    )
    target_faces: int = Field(
        default=150_000, ge=100, description="The trimmed surface is simplified to at most this many faces."
    )
    min_angle_deg: float = Field(
        default=2.0,
        ge=0.0,
        lt=30.0,
        description="Triangles with a smaller interior angle (degrees) are slivers and are collapsed.",
    )
    split_factor: float = Field(
        default=1.75,
        ge=1.0,
        description="Before visibility and subdivision, faces projecting larger than this times "
        "subdivision.max_area_px (in a view they face) are bisected, so that the uniform sqrt(3) "
        "subdivision needs one step fewer (1.75: one step then brings the largest below the threshold).",
    )
    hull_tolerance_px: float | None = Field(
        default=0.5,
        ge=0.0,
        description="After subdivision, vertices that project more than this many pixels outside some view's "
        "mask move inward along their normals until they do (at most 3 px; pmvir.geometry.silhouette.hull_fit): every "
        "point of the object lies inside the masks' visual hull, and the Poisson surface rounds thin parts "
        "out past their silhouettes. None: off. Path-traced dragon at 308x256, initial surface: accuracy "
        "0.307e-2 -> 0.280e-2, completeness 0.850e-2 -> 0.758e-2 (README).",
    )


class VisibilityOptions(_Options):
    """Per-vertex visibility (:mod:`pmvir.geometry.visibility`)."""

    min_cos: float = Field(
        default=0.05,
        ge=-1.0,
        lt=1.0,
        description="A vertex is back-facing (not visible) in a view when the cosine between its "
        "area-weighted normal and the direction to the camera centre is at most this (0.05: about 87 "
        "degrees; grazing vertices land on mixed silhouette pixels).",
    )
    rel_tol: float = Field(
        default=1e-4,
        gt=0.0,
        lt=0.5,
        description="Relative tolerance of the ray-cast occlusion test: a triangle occludes a vertex "
        "only if it crosses the camera-to-vertex segment before (1 - tol) of its length.",
    )


class SubdivisionOptions(_Options):
    """sqrt(3) subdivision of the initial surface (:mod:`pmvir.geometry.subdivision`)."""

    max_area_px: float = Field(
        default=2.0,
        gt=0.0,
        description="sqrt(3) subdivision is repeated until every triangle's projected area, in each "
        "view that sees it, is below this many pixels^2. A step divides areas by 3, so the largest ends "
        "in [2/3, 2) px^2; with about two triangles per vertex that is at most about 4 px^2 (a vertex "
        "every 2 pixels) in the view that sees the surface largest: near the image resolution the "
        "refinement samples, at a quarter of the vertices (and cost) of a 0.5 px^2 threshold.",
    )
    max_rounds: int = Field(
        default=6, ge=0, le=12, description="Most sqrt(3) steps (each triples the face count)."
    )
    max_vertices: int = Field(
        default=2_000_000,
        ge=3,
        description="Subdivision stops before a step that would make the mesh exceed this many vertices.",
    )
    min_visible_corners: Literal[1, 2, 3] = Field(
        default=3,
        description="A face counts as visible in a view when at least this many of its corners are; "
        "a vertex added by subdivision is visible in the views in which the input face it lies on is "
        "(3: all corners, conservative: no new vertex gets a view in which part of its face may be hidden).",
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

