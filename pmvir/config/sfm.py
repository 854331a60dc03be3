"""Options of camera poses and sparse points (structure from motion)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pmvir.config.base import _Options


class SfmOptions(_Options):
    """Camera poses and sparse points (:mod:`pmvir.geometry.sfm.poses`): known-pose triangulation or SfM."""

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
        "tracks and to the masks' epipolar tangencies together (pmvir.geometry.sfm.frontier; the outermost "
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
