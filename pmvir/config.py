"""The one typed configuration tree.

The CLI (`pmvir reconstruct`), the HTTP job options (`POST /v1/jobs`) and the
pipeline all read these models: one place defines each parameter, its default,
its range and its meaning. Unknown keys are errors (``extra="forbid"``).
"""

from __future__ import annotations

import math
import warnings
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

from pmvir.stages import Stage

#: No numeric option accepts a magnitude above this (fields state narrower ranges of their own).
OPTION_MAGNITUDE_LIMIT = 1e9


class _Options(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    @field_validator("*", mode="after")
    @classmethod
    def _finite_and_bounded(cls, value: Any) -> Any:
        """Every number (and every number in a list) is finite and within +-OPTION_MAGNITUDE_LIMIT."""
        numbers = value if isinstance(value, list) else [value]
        for x in numbers:
            is_number = isinstance(x, (int, float)) and not isinstance(x, bool)
            if is_number and (not math.isfinite(x) or abs(x) > OPTION_MAGNITUDE_LIMIT):
                raise ValueError(f"{x!r} is out of range; no option accepts a magnitude above 1e9")
        return value


#: The demosaicing methods (:mod:`pmvir.polarization.demosaic`), for decode.demosaic and refine.demosaic.
DemosaicMethod = Literal["bilinear", "edge-aware", "guided", "eari", "eari-guided"]


class DecodeOptions(_Options):
    """Demosaicing and polarization quantities (pipeline stage 1)."""

    noise_floor: float = Field(
        default=0.01,
        ge=0.0,
        lt=1.0,
        description="Pixels whose mean intensity (I_int averaged over colours, = s0 / 2, normalized "
        "units) is at or below this are invalid: AoP/DoP are undefined there.",
    )
    demosaic: DemosaicMethod = Field(
        default="guided",
        description="Demosaicing method: 'bilinear' (per-angle Bayer then polarization interpolation, "
        "float32), 'edge-aware' (OpenCV's edge-aware Bayer step, 16-bit, then bilinear), 'guided' "
        "(bilinear intensity; the colour-mean polarization from a guided filter with the intensity as "
        "guide, windows weighted by their fitting error: much less false polarization from texture and "
        "noise, reach 13 px around saturated samples), 'eari' (Morimatsu et al.'s edge-aware residual "
        "interpolation: every angle and colour from an edge-aware guide; keeps each sample and its "
        "noise, reach 16 px) or 'eari-guided' (EARI, then the guided polarization step; reach 27 px). "
        "Measured in bench/demosaic.py. Monochrome sensors: no colour step.",
    )


class SfmOptions(_Options):
    """Camera poses and sparse points (:mod:`pmvir.geometry.sfm`): known-pose triangulation or SfM."""

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
        description="SfM fails when fewer 3D points than this are triangulated from 3 or more views (a "
        "textureless object, or frames that do not overlap: chance matches seldom agree in 3 views). Known "
        "poses never need sparse points: the cameras' visual hull bounds the depth search and the points, "
        "where there are some, only tighten it.",
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
    init_min_inliers: int = Field(
        default=50,
        ge=15,
        description="Verified matches the initial view pair of incremental SfM needs (COLMAP: 100).",
    )
    register_min_inliers: int = Field(
        default=15,
        ge=6,
        description="2D-3D inliers a view needs to be registered by incremental SfM (COLMAP: 30).",
    )
    max_reprojection_error: float = Field(
        default=2.0,
        ge=0.0,
        description="After incremental SfM, observations reprojecting farther than this (pixels) are "
        "dropped and a last bundle adjustment with a robust (Cauchy, 1 px) loss refines poses, focal "
        "lengths and points (0: skip; COLMAP keeps observations up to 4 px).",
    )
    shared_intrinsics: bool = Field(
        default=True,
        description="Without given intrinsics, views of one image size share one estimated camera "
        "(one focal length: far better constrained than one per view).",
    )
    seed: int = Field(default=0, ge=0, description="Random seed of RANSAC and view selection in SfM.")
    mapper: Literal["incremental", "global"] = Field(
        default="incremental",
        description="SfM mapper: COLMAP's incremental mapping, or its global mapper (GLOMAP: rotation "
        "averaging and global positioning), both followed by the robust bundle adjustment.",
    )
    guided_matching: bool = Field(
        default=False,
        description="SfM matching: after RANSAC, match again along the verified epipolar geometry (COLMAP "
        "guided matching). Off: on the 36-view 432x360 test blob it moved the estimated focal length from "
        "within 1% to 1.1% off.",
    )
    match_max_ratio: float = Field(
        default=0.8,
        gt=0.0,
        le=1.0,
        description="SfM matching: Lowe's ratio test, the largest ratio of a match's descriptor distance to "
        "the second best's (COLMAP's 0.8). 0.9 with mask_erosion_px 0 was tried for the dragon's thin "
        "parts: all 36 views registered, but in a broken model (camera centres 58% of the rig off), and "
        "the 24-view test blob lost its 0.5% centre accuracy (README, SfM).",
    )
    mask_erosion_px: int = Field(
        default=4,
        ge=0,
        le=64,
        description="SfM features: the masks are eroded by this many pixels before SIFT detection, to keep "
        "features off the silhouette, which is no fixed surface point (its matches are consistent with "
        "wrong geometry). 0 keeps thin parts' features but lets silhouette matches in.",
    )
    rematch_rounds: int = Field(
        default=2,
        ge=0,
        le=5,
        description="After SfM, rounds of matching again along the epipolar lines of the estimated poses "
        "(as with known poses: the matches between views 30-70 degrees apart that RANSAC verification "
        "loses), triangulating with the poses held and the robust bundle adjustment with them free (0: "
        "off). Models that had to be joined (join_models) get one round per joining pass: along their "
        "bent poses a second round added to the bend (dragon, 32 views: 1.10 -> 1.34 % of the rig). "
        "Measured on the 36-view 612x512 captures, largest centre error in % of the rig with the "
        "intrinsics given / estimated, one round -> two: armadillo 0.28 / 0.502 -> 0.28 / 0.31, bunny "
        "0.18 / 0.18 -> 0.14 / 0.17; about 1-3 s per round on 2 cores.",
    )
    rematch_min_track: int = Field(
        default=3,
        ge=2,
        le=10,
        description="The re-matching's points seen in fewer views than this are dropped before and after its "
        "bundle adjustment. A two-view match along an estimated epipolar line is checked only by that line, "
        "and the poses it helps estimate can bend to fit a wrong one; three views check each other. On the "
        "36-view 612x512 armadillo (intrinsics given), under the true poses 32 of the 37 observations that "
        "miss them by more than 2 px were two-view tracks, and dropping them took the largest centre error "
        "from 0.60 % to 0.28 % of the rig (0.88 -> 0.50 % estimating the intrinsics; the bunny 0.23 -> 0.18 %). "
        "Models that had to be joined (join_models) keep their two-view points: the joins vote with them, "
        "and on the dragon dropping them after the join was slightly worse (1.10 -> 1.17 %). 2: keep every "
        "point (the behaviour before Nov 27, session 22).",
    )
    frontier_weight: float = Field(
        default=1.0,
        ge=0.0,
        le=100.0,
        description="After SfM, when the views have masks: the poses and sparse points are adjusted to their "
        "tracks and to the masks' epipolar tangencies together (pmvir.geometry.sfm_frontier; the outermost "
        "epipolar planes that touch silhouette i must be those that touch silhouette j), with this weight on "
        "the tangency residuals (px, Huber 3 px) against the tracks' (px, Cauchy 1 px); 0: off. The new poses "
        "are kept only when they fit the masks better and the tracks' median reprojection error stays within "
        "1 px. Measured on the dragon (32 registered views, intrinsics given), whose hue texture bends its "
        "SIFT tracks: largest camera-centre error 1.08 -> 0.21 % of the rig (tangency RMS 7.5 -> 0.30 px; the "
        "true poses: 0.34 px). The masks must hold the whole object.",
    )
    frontier_iterations: int = Field(
        default=1000,
        ge=1,
        le=100000,
        description="L-BFGS iterations of the frontier adjustment (frontier_weight). Its variables are in pixels "
        "(a unit step moves an image point about a pixel); on the dragon 300 / 1000 / 2000 iterations gave "
        "0.42 / 0.21 / 0.21 % of the rig.",
    )
    silhouette_register_px: float = Field(
        default=1.0,
        ge=0.0,
        le=20.0,
        description="Views SfM left out are registered from their masks when frontier_weight > 0: cameras on a "
        "sphere around the sparse points (at the registered cameras' median distance and 15% nearer and "
        "farther) aim the mask's centroid at them with 24 rolls; the best candidate of each of the 200 best "
        "directions by frontier residual against the registered views is polished briefly (that view's pose "
        "alone, robust least squares), the best of 5 distinct basins in full, and the best is kept when its RMS "
        "frontier residual is at most this many pixels over 10 or more pairs and no distinct pose fits within "
        "2x + 0.2 px of it (an ambiguous silhouette: a symmetric object); then every pose is adjusted again "
        "(frontier_weight). Runs only when SfM registered silhouette_min_registered of the views. "
        "Two passes. On the dragon the four end-on views SfM leaves out polished to 0.22-0.31 px (the next best "
        "basin: 1.27 px or more in session 25's search; 3.4-6.3 px among distinct basins since session 26): 36 of 36 views within 0.18 % of the rig. Assumes the cameras frame the object "
        "from about the registered ones' distance. 0: off.",
    )
    silhouette_min_registered: float = Field(
        default=0.75,
        ge=0.0,
        le=1.0,
        description="The silhouette search (silhouette_register_px) runs only when SfM registered at least this "
        "fraction of the views: it completes a model that surrounds the object, it does not build one. On the "
        "built-in torus knot, of whose 36 views SfM registers 16 (its texture gives SIFT few matches), the "
        "search fitted 20 more views' masks within 1.2 px, 19 of them at wrong poses (18-67 % of the rig off); "
        "the dragon's 32 of 36 surround it and its four views land within 0.1 %.",
    )
    join_models: bool = Field(
        default=True,
        description="When SfM leaves views out: every model registers its missed views by absolute pose "
        "(P3P RANSAC on the raw matches to its points, intrinsics held, 4 px, at least 7 inliers and half "
        "the correspondences), models whose poses of two or more common views agree on one similarity are "
        "joined into the largest, and the poses are matched again, triangulated and bundle-adjusted (as "
        "rematch_rounds), in up to 3 passes. When no two models join, the largest is completed with only "
        "the poses of register_min_inliers or more inliers (7-inlier poses that no second model confirmed "
        "once broke the armadillo's model: 32 views at 19 % of the rig). Measured (36 views 612x512, SIFT "
        "on I_int, no guided matching; before -> after): the dragon, whose two sides the mapper builds as "
        "two models, 14 views (error) -> 32 of 36 at a largest centre error of 1.02 % of the rig with the "
        "intrinsics given, 1.05 % estimating them; the armadillo 22 -> 36 views (1.83 -> 1.55 %) with the "
        "intrinsics given, 20 -> 26 views (3.12 -> 3.09 %) estimating them. Captures that register whole "
        "never reach it.",
    )
    grey: Literal["auto", "int", "min"] = Field(
        default="auto",
        description="The image SIFT sees: 'int' = I_int, 'min' = I_min = (1 - DoP) I_int, the "
        "unpolarized part, in which specular highlights (strongly polarized on dielectrics) are dimmed; "
        "'auto' = I_min for SfM, and I_int again when SfM on I_min leaves views out (the model with more "
        "views is kept), I_int with known poses. Highlights move with the view, so their features are no "
        "fixed surface points and bend SfM's model: on the armadillo (36 views 612x512, plastic, "
        "intrinsics given) 3.2 % of the I_int tracks miss the true poses by more than 2 px against 0.3 % "
        "of the I_min tracks, and the largest centre error drops from 1.51 % to 0.60 % of the rig. I_min "
        "holds fewer features, and on the dragon SfM on I_min registers 14 of 36 views against 32 on "
        "I_int, hence the fallback.",
    )


class MvsOptions(_Options):
    """Dense multi-view stereo (:mod:`pmvir.geometry.mvs_dense`): depth maps, consistency, fusion."""

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
    """The initial surface (:mod:`pmvir.geometry.surface`): screened Poisson, trimming, cleaning."""

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
        "mask move inward along their normals until they do (at most 3 px; pmvir.geometry.hull_fit): every "
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


#: The flat keys of GeometryOptions before it was grouped (deprecated; accepted for one release):
#: old key -> (group, key in the group).
DEPRECATED_GEOMETRY_KEYS: dict[str, tuple[str, str]] = {
    "min_registered_views": ("sfm", "min_registered_views"),
    "min_registered_fraction": ("sfm", "min_registered_fraction"),
    "min_sparse_points": ("sfm", "min_sparse_points"),
    "sift_max_features": ("sfm", "sift_max_features"),
    "sift_peak_threshold": ("sfm", "sift_peak_threshold"),
    "sift_affine_shape": ("sfm", "sift_affine_shape"),
    "sift_upsample": ("sfm", "sift_upsample"),
    "sift_equalize": ("sfm", "sift_equalize"),
    "exhaustive_matching_max_views": ("sfm", "exhaustive_matching_max_views"),
    "sequential_matching_overlap": ("sfm", "sequential_matching_overlap"),
    "sfm_init_min_inliers": ("sfm", "init_min_inliers"),
    "sfm_register_min_inliers": ("sfm", "register_min_inliers"),
    "sfm_max_reprojection_error": ("sfm", "max_reprojection_error"),
    "sfm_shared_intrinsics": ("sfm", "shared_intrinsics"),
    "sfm_seed": ("sfm", "seed"),
    "visibility_min_cos": ("visibility", "min_cos"),
    "visibility_rel_tol": ("visibility", "rel_tol"),
    "subdivision_max_area_px": ("subdivision", "max_area_px"),
    "subdivision_max_rounds": ("subdivision", "max_rounds"),
    "subdivision_max_vertices": ("subdivision", "max_vertices"),
    "subdivision_min_visible_corners": ("subdivision", "min_visible_corners"),
    "mvs_backend": ("mvs", "backend"),
    "mvs_scale": ("mvs", "scale"),
    "mvs_colour": ("mvs", "colour"),
    "mvs_neighbours": ("mvs", "neighbours"),
    "mvs_top_k": ("mvs", "top_k"),
    "mvs_planes": ("mvs", "planes"),
    "mvs_window": ("mvs", "window"),
    "mvs_min_score": ("mvs", "min_score"),
    "mvs_min_angle_deg": ("mvs", "min_angle_deg"),
    "mvs_max_angle_deg": ("mvs", "max_angle_deg"),
    "mvs_depth_margin": ("mvs", "depth_margin"),
    "mvs_consistency_px": ("mvs", "consistency_px"),
    "mvs_consistency_depth": ("mvs", "consistency_depth"),
    "mvs_min_consistent": ("mvs", "min_consistent"),
    "mvs_voxel": ("mvs", "voxel"),
    "mvs_min_points": ("mvs", "min_points"),
    "mvs_min_consistent_fraction": ("mvs", "min_consistent_fraction"),
    "surface_poisson_depth": ("surface", "poisson_depth"),
    "surface_poisson_voxel_px": ("surface", "poisson_voxel_px"),
    "surface_trim_density_quantile": ("surface", "trim_density_quantile"),
    "surface_trim_distance": ("surface", "trim_distance"),
    "surface_target_faces": ("surface", "target_faces"),
    "surface_min_angle_deg": ("surface", "min_angle_deg"),
    "surface_split_factor": ("surface", "split_factor"),
}


def nest_deprecated_geometry_keys(data: Any) -> Any:
    """Geometry options with the flat keys of earlier releases moved into their groups.

    Warns (DeprecationWarning) naming each old key and its new place; anything but a dict
    passes through. Used by :class:`GeometryOptions` and wherever partial options are merged
    before validation (the service's rerun).

    >>> import warnings
    >>> with warnings.catch_warnings():
    ...     warnings.simplefilter("ignore")
    ...     nest_deprecated_geometry_keys({"mvs_planes": 64, "mvs": {"window": 7}})
    {'mvs': {'window': 7, 'planes': 64}}

    Raises:
        ValueError: an old key and its new place are both given.
    """
    if not isinstance(data, dict):
        return data
    old = [k for k in data if k in DEPRECATED_GEOMETRY_KEYS]
    if not old:
        return data
    warnings.warn(
        "flat geometry options are deprecated and will be removed in the next release: "
        + ", ".join(f"{k} -> {'.'.join(DEPRECATED_GEOMETRY_KEYS[k])}" for k in old),
        DeprecationWarning,
        stacklevel=3,
    )
    out = {k: v for k, v in data.items() if k not in DEPRECATED_GEOMETRY_KEYS}
    for key in old:
        group, name = DEPRECATED_GEOMETRY_KEYS[key]
        section = out.get(group, {})
        if not isinstance(section, dict):  # a model instance: the flat key updates a copy of it
            section = section.model_dump(exclude_unset=True) if isinstance(section, BaseModel) else section
        section = dict(section)
        if name in section:
            raise ValueError(f"geometry.{key} and geometry.{group}.{name} are the same option; give one")
        section[name] = data[key]
        out[group] = section
    return out


class GeometryOptions(_Options):
    """Initial geometry (pipeline stage 2, paper section 4.2), one group per step, each passed whole to it.

    The flat keys of earlier releases (``mvs_planes``, ``surface_poisson_depth``, ...; see
    :data:`DEPRECATED_GEOMETRY_KEYS`) are still accepted, with a DeprecationWarning, and mapped to
    their group (``mvs.planes``, ``surface.poisson_depth``).
    """

    sfm: SfmOptions = Field(default_factory=SfmOptions, description="Poses and sparse points.")
    mvs: MvsOptions = Field(default_factory=MvsOptions, description="Dense multi-view stereo.")
    surface: SurfaceOptions = Field(default_factory=SurfaceOptions, description="The initial surface.")
    visibility: VisibilityOptions = Field(
        default_factory=VisibilityOptions, description="Per-vertex visibility."
    )
    subdivision: SubdivisionOptions = Field(
        default_factory=SubdivisionOptions, description="sqrt(3) subdivision of the initial surface."
    )

    @model_validator(mode="before")
    @classmethod
    def _map_deprecated_keys(cls, data: Any) -> Any:
        """Move the old flat keys into their groups, with a DeprecationWarning naming the new key."""
        return nest_deprecated_geometry_keys(data)


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
    silhouette_margin_px: int = Field(
        default=2,
        ge=0,
        le=64,
        description="Pixels within this distance of an observation's invalid region (outside the mask, "
        "saturated) are not sampled: demosaicing mixes the background into them, so a vertex seen there "
        "looks darker (or brighter) than it is and E_pho pulls it toward the image's interior, i.e. into "
        "the object. Measured in the README.",
    )
    demosaic: Literal["same"] | DemosaicMethod = Field(
        default="eari",
        description="Demosaicing of the frames the refinement fits (E_pho, E_pol, E_psm): 'same' uses the decode "
        "stage's images (decode.demosaic); a method name decodes the registered frames once more with it, for "
        "the refinement only (SfM, dense stereo, previews and exports keep decode.demosaic's). 'eari' (default) "
        "keeps the pixel-scale relief that 'guided' smooths out of the AoP: accuracy gain on the built-in "
        "Stanford captures +26.7% -> +42.4% on average (armadillo +22.8% -> +44.0%), on Mitsuba-rendered ones "
        "+24.9% -> +30.6%. Measured in the README.",
    )
    intensity: Literal["min", "int"] = Field(
        default="min",
        description="Observed colour in E_pho: 'min' = I_min = (1 - rho) I_int (the paper's), 'int' = I_int.",
    )
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
    pol_k: float = Field(default=0.5, gt=0.0, description="Narrowness k of E_pol's concave cost.")
    max_iterations: int = Field(
        default=80,
        ge=1,
        le=100_000,
        description="Most L-BFGS iterations per stage. 80: on the Stanford models every stage still lowers "
        "the cost at 40 (accuracy gain 33% at 40, 39% at 80), and 300k vertices x 36 views x 3 stages of 80 "
        "take about 7 minutes on 2 CPU cores (bench/refine_speed.py).",
    )
    min_view_cos: float = Field(
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
    hull_tolerance_px: float | None = Field(
        default=0.5,
        ge=0.0,
        description="After every offset scan and after the last stage, vertices that project more than this "
        "many pixels outside some view's mask move inward along their normals until they do (at most 3 px; "
        "pmvir.geometry.hull_fit; needs the masks: refine_surface's masks argument). The stages' terms see "
        "normals, not position, and the scans move the whole mesh, so thin parts drift out past their "
        "silhouettes. None: off. Measured in the README.",
    )
    rim_fit_gain: float = Field(
        default=0.5,
        ge=0.0,
        le=1.0,
        description="After the last stage (and its hull fit), vertices near some view's rim that project more "
        "than a quarter pixel inside that view's mask, measured along their normals to the mask's boundary, move "
        "outward by this share of the excess, spread over the shoulders around them (pmvir.geometry.hull_fit."
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
    pho_robust: Literal["none", "cauchy", "specular"] = Field(
        default="cauchy",
        description="E_pho's loss. 'none': least squares (the paper's). 'cauchy': from stage 2 on, each pair's "
        "squared residual is weighted by the Cauchy weight 1 / (1 + (r / s)^2) of its residual r at the "
        "stage's start (s = pho_robust_scale times the median residual), fixed for the stage like the "
        "pairs: specular residue, cast shadows and misregistered samples lose their pull. Measured in the "
        "README.",
    )
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
    lighting_coupling: float = Field(
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
    lighting_final_iterations: int = Field(
        default=40,
        ge=1,
        le=100_000,
        description="L-BFGS iterations of the final lighting fit (with lighting_coupling > 0).",
    )
    lighting_prefit_iterations: int = Field(
        default=0,
        ge=0,
        le=100_000,
        description="Before the first stage, L-BFGS iterations fitting the per-view lighting (and the albedo) "
        "to the initial surface with the geometry held; with pho_robust the first stage's Cauchy weights then "
        "come from that fit's residuals instead of the first stage running least squares. 0: none (the "
        "paper's start). Measured in the README.",
    )
    pho_robust_first_stage: bool = Field(
        default=False,
        description="With pho_robust and the lighting pre-fit: stage 1's Cauchy weights come from the pre-fit's "
        "residuals (False: stage 1 is least squares, the robust weights start at stage 2). Measured in the README.",
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
    offset_scan: Literal["off", "start", "stages"] = Field(
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
    specular_offset_scan: Literal["off", "same"] = Field(
        default="off",
        description="For a specular-dominated capture (pmvir.pipeline: the median over views of each view's "
        "median DoP inside its mask above 0.2, SPECULAR_MEDIAN_DOP): 'off' refines it without the offset "
        "scan, 'same' keeps offset_scan. A mirror's views agree best at the depth of its reflections, behind "
        "the surface. Path-traced smooth conductors (36 views 612x512), full method, accuracy gain with the "
        "scans -> without: armadillo -37.2 % -> +17.9 %, bunny +21.3 % -> +12.6 %, dragon +8.8 % -> +0.3 %; "
        "average -2.4 % -> +10.3 % (README). Applied by the pipeline, which knows the masks; "
        "refine_surface takes offset_scan as given.",
    )
    offset_scan_deblur_px: float = Field(
        default=1.6,
        ge=0.0,
        description="With offset_scan: the Gaussian blur (pixels) the decoded images are taken to hold, or 0 "
        "(off); each scan runs again on the images blurred by it and extrapolates its offset to no blur (2 o - "
        "o_blurred). Blur moves the scan's minimum inward in proportion to its variance; the default "
        "demosaicing acts like 1.6 px: at the true surfaces this takes the scan from -0.08..-0.27 px to "
        "-0.01..-0.14 px, and it raised the refined accuracy on all five measured captures (built-in bunny, "
        "dragon, armadillo; Mitsuba knot and blob; README). Doubles the scans' time.",
    )
    offset_scan_min_cos: float = Field(
        default=0.8,
        gt=0.0,
        lt=1.0,
        description="With offset_scan: only pixels whose triangle both views see at least at this viewing cosine "
        "count (grazing pairs pull the scan's minimum inward, as they do the plane sweep's depths).",
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
        if self.diffuse_dop_ior > 0.0 and self.intensity != "min":
            raise ValueError(
                f"diffuse_dop_ior {self.diffuse_dop_ior} models I_min (the part of the diffuse light I_min "
                "keeps) but intensity is 'int', which keeps all of it; set diffuse_dop_ior 0 or intensity 'min'"
            )
        return self

    @property
    def n_stages(self) -> int:
        return len(self.tau_pol)


class ExportOptions(_Options):
    """Files written beside the result for people and other tools (previews, residuals, glTF, OBJ)."""

    textured: bool = Field(
        default=True,
        description="Write textured.glb and textured.obj/.mtl/_albedo.png: the refined mesh decimated to "
        "face_budget faces, UV-mapped with xatlas and its albedo baked into a texture.",
    )
    face_budget: int = Field(
        default=100_000, ge=100, le=5_000_000, description="Most faces of the textured meshes."
    )
    texture_size: int = Field(
        default=2048, ge=64, le=8192, description="Texels per side the UV atlas is packed into (about)."
    )
    preview_max_size: int = Field(
        default=512,
        ge=32,
        le=4096,
        description="Widest per-view preview and residual image (frames are reduced by an integer factor).",
    )


class PipelineConfig(_Options):
    """Everything a reconstruction run is told."""

    decode: DecodeOptions = Field(default_factory=DecodeOptions)
    geometry: GeometryOptions = Field(default_factory=GeometryOptions)
    refine: RefineOptions = Field(default_factory=RefineOptions)
    export: ExportOptions = Field(default_factory=ExportOptions)
    stop_after: Stage = Field(default=Stage.REFINE, description="Last stage to run.")
