"""Options of camera poses and sparse points (structure from motion)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pmvir.config.base import _Options, advanced


class SfmOptions(_Options):
    """Camera poses and sparse points (:mod:`pmvir.geometry.sfm.poses`): known-pose triangulation or SfM."""

    min_registered_views: int = Field(
        default=3, ge=2,
        description="Poses fail (ReconstructionError naming the views that failed) when fewer views than "
        "this are registered by SfM.",
        json_schema_extra=advanced(),
    )
    min_registered_fraction: float = Field(
        default=0.5, ge=0.0, le=1.0,
        description="Poses also fail when SfM registers less than this fraction of the views (a capture that "
        "falls apart into pieces would otherwise give a partial object).",
        json_schema_extra=advanced(),
    )
    min_sparse_points: int = Field(
        default=50, ge=1,
        description="SfM fails when fewer 3D points than this are triangulated from 3 or more views "
        "(textureless or non-overlapping frames). Known poses need no sparse points.",
        json_schema_extra=advanced(),
    )
    sift_max_features: int = Field(
        default=4096, ge=64,
        description="Most SIFT features extracted per view.",
        json_schema_extra=advanced(),
    )
    sift_peak_threshold: float = Field(
        default=0.002, gt=0.0,
        description="SIFT detection threshold on the difference-of-Gaussians peak (lower: more features on "
        "smooth, weakly textured objects).",
        json_schema_extra=advanced(),
    )
    sift_affine_shape: bool = Field(
        default=True,
        description="Affine-adapted SIFT (COLMAP estimate_affine_shape): about twice the extraction time, "
        "but features survive the 30-45 degree viewpoint changes of a ring of views far better.",
        json_schema_extra=advanced(),
    )
    sift_upsample: bool | Literal["auto"] = Field(
        default="auto",
        description="SIFT on the images upsampled 2x (COLMAP first_octave -1): more small features, 3x the "
        "extraction time. 'auto': only when SfM without it leaves a view out; with known poses, only where "
        "masks are given.",
        json_schema_extra=advanced(),
    )
    sift_equalize: bool = Field(
        default=True,
        description="Equalize the 8-bit grey images (CLAHE) before SIFT: more features on weakly textured "
        "surfaces. Off: the 0.5th percentile is taken as black instead.",
        json_schema_extra=advanced(),
    )
    sift_denoise: float = Field(
        default=0.0, ge=0.0, le=50.0,
        description="Non-local-means denoising of SIFT's 8-bit grey images before equalization, strength in "
        "grey levels, 0..50 (0: off). Noisy frames keep fewer spurious features.",
        json_schema_extra=advanced(),
    )
    denoised_runs: float = Field(
        default=5.0, ge=0.0, le=50.0,
        description="SfM runs first on images denoised with this strength (grey levels) and not equalized, "
        "kept if every view registers, and last where views are still left out. 0..50, 0: off.",
        json_schema_extra=advanced(),
    )
    exhaustive_matching_max_views: int = Field(
        default=50, ge=2,
        description="Match every pair of views up to this many views; above it, each view is matched with "
        "its sequential_matching_overlap successors in capture order (and quadratically spaced ones).",
        json_schema_extra=advanced(),
    )
    sequential_matching_overlap: int = Field(
        default=12, ge=1,
        description="Successors in capture order each view is matched with (many views).",
        json_schema_extra=advanced(),
    )
    init_min_inliers: int = Field(
        default=50, ge=15,
        description="Verified matches the initial view pair of incremental SfM needs.",
        json_schema_extra=advanced(),
    )
    register_min_inliers: int = Field(
        default=15, ge=6,
        description="2D-3D inliers a view needs to be registered by incremental SfM.",
        json_schema_extra=advanced(),
    )
    max_reprojection_error: float = Field(
        default=2.0, ge=0.0,
        description="After SfM, observations reprojecting farther than this (px) are dropped and a robust "
        "bundle adjustment refines poses, focal lengths and points. 0: skip.",
        json_schema_extra=advanced("px"),
    )
    shared_intrinsics: bool = Field(
        default=True,
        description="Without given intrinsics, views of one image size share one estimated camera (one focal "
        "length: far better constrained than one per view).",
        json_schema_extra=advanced(),
    )
    seed: int = Field(
        default=0, ge=0,
        description="Random seed of RANSAC and view selection in SfM.",
        json_schema_extra=advanced(),
    )
    mapper: Literal["incremental", "global"] = Field(
        default="incremental",
        description="SfM mapper: COLMAP's incremental mapping, or its global mapper (GLOMAP: rotation "
        "averaging and global positioning), both followed by the robust bundle adjustment.",
        json_schema_extra=advanced(),
    )
    guided_matching: bool = Field(
        default=False,
        description="After RANSAC, match again along the verified epipolar geometry (COLMAP guided "
        "matching) in the runs on images not denoised; the runs on denoised images always do.",
        json_schema_extra=advanced(),
    )
    match_max_ratio: float = Field(
        default=0.8, gt=0.0, le=1.0,
        description="Lowe's ratio test: largest ratio of a match's descriptor distance to the second best's, "
        "(0, 1].",
        json_schema_extra=advanced(),
    )
    mask_erosion_px: int = Field(
        default=4, ge=0, le=64,
        description="Masks are eroded by this many pixels before SIFT, keeping features off the silhouette "
        "(no fixed surface point). 0 keeps thin parts' features, 0..64.",
        json_schema_extra=advanced("px"),
    )
    rematch_rounds: int = Field(
        default=2, ge=0, le=5,
        description="After SfM, rounds of matching again along the estimated epipolar lines, then "
        "triangulation and robust bundle adjustment, 0..5 (0: off).",
        json_schema_extra=advanced(),
    )
    rematch_min_track: int = Field(
        default=3, ge=2, le=10,
        description="Re-matched points seen in fewer views than this are dropped around its bundle "
        "adjustment (joined models keep two-view points), 2..10; 2 keeps every point.",
        json_schema_extra=advanced(),
    )
    frontier_weight: float = Field(
        default=1.0, ge=0.0, le=100.0,
        description="With masks: weight of the masks' epipolar tangencies against the tracks when poses and "
        "points are adjusted together after SfM (kept only if better), 0..100; 0: off.",
        json_schema_extra=advanced(),
    )
    frontier_iterations: int = Field(
        default=100, ge=1, le=100000,
        description="Most Levenberg-Marquardt iterations of the frontier adjustment (frontier_weight); it stops "
        "earlier once converged, 1..100000.",
        json_schema_extra=advanced(),
    )
    silhouette_register_px: float = Field(
        default=1.0, ge=0.0, le=20.0,
        description="Views SfM left out are registered from their masks when their best pose's RMS frontier "
        "residual is at most this (px) and unambiguous, 0..20; 0: off.",
        json_schema_extra=advanced("px"),
    )
    silhouette_min_registered: float = Field(
        default=0.75, ge=0.0, le=1.0,
        description="The silhouette registration runs only when SfM registered at least this fraction of the "
        "views (it completes a model, it does not build one).",
        json_schema_extra=advanced(),
    )
    join_models: bool = Field(
        default=True,
        description="When SfM leaves views out: register them in every model by absolute pose and join "
        "models that agree on a similarity, then match and adjust again (up to 3 passes).",
        json_schema_extra=advanced(),
    )
    grey: Literal["auto", "int", "min"] = Field(
        default="auto",
        description="Image SIFT sees: 'int' = I_int, 'min' = I_min (highlights dimmed), 'auto' = I_min for "
        "SfM with I_int as fallback when views are left out, I_int with known poses.",
        json_schema_extra=advanced(),
    )
