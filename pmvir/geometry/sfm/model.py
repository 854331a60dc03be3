"""SfM's result and how a run is finished: the checks, the frontier adjustment, the silhouette registration.

:class:`SparseModel` holds a capture's cameras and sparse points. :func:`finish_model` turns an SfM
run's reconstruction (:class:`SfmRun`) into it: the views left out are registered from their masks
where they have them (:func:`~pmvir.geometry.sfm.silhouette_registration.register_from_silhouettes`),
the poses are held to the masks (:func:`~pmvir.geometry.sfm.frontier.frontier_adjust`), the sparse
points are kept inside the masks' visual hull, and a run with too few views or points fails with a
message that names the views and their feature and match counts.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np
import pycolmap

from pmvir.camera import Camera
from pmvir.config import SfmOptions
from pmvir.errors import ReconstructionError
from pmvir.geometry.sfm.colmap import Progress
from pmvir.geometry.sfm.frontier import FrontierReport, frontier_adjust
from pmvir.geometry.sfm.inputs import EXPOSURE_PERCENTILE
from pmvir.geometry.sfm.silhouette_registration import register_from_silhouettes
from pmvir.polarization.preview import srgb_encode

#: Sparse points must project into every mask grown by this many pixels (visual hull).
_HULL_TOLERANCE_PX = 3
#: Failure messages call views with fewer SIFT features than this (median) textureless.
_FEW_FEATURES = 100


@dataclass
class SparseModel:
    """Cameras and sparse 3D points of a capture.

    Attributes:
        cameras: one per view in capture order; None where the view is not registered.
        points: (P, 3) float64 world points.
        point_colors: (P, 3) uint8 sRGB colour of each point (mean of its observed pixels), or None.
        point_views: per point, the int64 indices of the views observing it, or None.
        mean_reprojection_error: mean over all observations, pixels.
        registered: per view, whether it has a camera.
        known_poses: True when the cameras were given (known-pose mode).
        timings: seconds per step: "images", "features", "matching", then "triangulation"
            (known poses) or "mapping" and "refinement" (SfM), "frontier" and
            "silhouette_registration" (SfM with masks), "finish" (those two and the checks), and
            "total"; with ``fallback_images``, "first_images" or "second_images": the run not kept;
            "without_upsampling": the run without SIFT upsampling when it was not kept; "denoised_first"
            (the first run, on denoised images, ``sfm.denoised_runs``) when it was not kept; "denoised"
            (the last run, on denoised images) or "without_denoising" (the runs before it), the one not kept.
        names: the views' names, in capture order.
        num_features: SIFT features per view.
        point_observations: per point a (k, 3) float64 array of its observations: view index,
            x, y (pixels, COLMAP convention), or None.
        fallback: True when SfM on the first images left views out or failed and the
            ``fallback_images`` of :func:`~pmvir.geometry.sfm.poses.estimate_poses` gave this model.
        frontier: the frontier adjustment's report (:class:`.frontier.FrontierReport` as a
            dict: residuals before and after, whether its poses were kept), or None where it did
            not run (known poses, no masks, ``sfm.frontier_weight`` 0, too few masked views).
        silhouette_registered: names of the views SfM left out that were registered from their
            masks (:func:`.silhouette_registration.register_from_silhouettes`, ``sfm.silhouette_register_px``).
        silhouette_refused: name -> why the silhouette search did not register a view SfM left
            out (no pose fits its mask well enough, or a distinct pose fits it about as well: an
            ambiguous, e.g. symmetric, silhouette).
        extras: what each refinement after SfM's mapping cost and gave, in order, one dict per step with
            its ``step`` name and ``seconds``: ``rematch`` rounds and ``join_rematch`` rounds (the model's
            :func:`~.colmap.track_stats` before and after, the gain in observations of tracks of 3+
            views, and why later rounds were skipped), ``join`` (models joined, stats before and after),
            ``without_upsampling`` (SfM without SIFT upsampling: registered views, whether it was kept),
            ``second_images`` (the SfM run on ``fallback_images`` and the registered views of both),
            ``frontier`` (its report), ``silhouette_registration`` (views registered) and ``denoised`` (SfM
            on denoised images: registered views before and with it, whether it was kept); a step that did
            not run says why (``skipped``); ``denoised_first`` (the first run, on denoised images: registered
            views, whether it was kept) leads; ``usual_runs`` says why they were skipped after an upsampled
            denoised run that placed enough views.
    """

    cameras: list[Camera | None]
    points: np.ndarray
    point_colors: np.ndarray | None
    point_views: list[np.ndarray] | None
    mean_reprojection_error: float
    registered: list[bool]
    known_poses: bool
    timings: dict[str, float]
    names: list[str] = field(default_factory=list)
    num_features: list[int] = field(default_factory=list)
    point_observations: list[np.ndarray] | None = None
    fallback: bool = False
    frontier: dict[str, float | int | bool] | None = None
    silhouette_registered: list[str] = field(default_factory=list)
    silhouette_refused: dict[str, str] = field(default_factory=dict)
    extras: list[dict] = field(default_factory=list)

    @property
    def num_registered(self) -> int:
        return int(sum(self.registered))


def _sparse_points(
    rec: pycolmap.Reconstruction, view_of_image: dict[int, int], images: Sequence[np.ndarray]
) -> tuple[np.ndarray, np.ndarray, list[np.ndarray], list[np.ndarray]]:
    """Points, their colours, the views observing them and the observations ((k, 3): view, x, y).

    A point's colour is the mean linear colour of the pixels holding its observations, with
    one exposure for all points (99.5th percentile of the brightest channel -> 1), sRGB 8-bit.
    """
    ids = sorted(rec.points3D.keys())
    points = np.zeros((len(ids), 3), dtype=np.float64)
    linear = np.zeros((len(ids), 3), dtype=np.float64)
    views: list[np.ndarray] = []
    observations: list[np.ndarray] = []
    for k, pid in enumerate(ids):
        p = rec.points3D[pid]
        points[k] = p.xyz
        seen, obs = [], []
        for el in p.track.elements:
            i = view_of_image[el.image_id]
            seen.append(i)
            im = images[i]
            x, y = rec.images[el.image_id].points2D[el.point2D_idx].xy
            obs.append((i, x, y))
            row = min(max(int(y), 0), im.shape[0] - 1)
            col = min(max(int(x), 0), im.shape[1] - 1)
            linear[k] += im[row, col] if im.ndim == 3 else im[row, col, None]
        linear[k] /= len(seen)
        views.append(np.unique(seen).astype(np.int64))
        observations.append(np.asarray(obs, np.float64).reshape(-1, 3))
    level = float(np.percentile(linear.max(axis=1), EXPOSURE_PERCENTILE)) if len(ids) else 1.0
    colors = np.rint(srgb_encode(linear / max(level, 1e-12)) * 255.0).astype(np.uint8)
    return points, colors, views, observations


def _inside_masks(
    points: np.ndarray, cameras: Sequence[Camera | None], masks: Sequence[np.ndarray | None] | None
) -> np.ndarray:
    """Visual-hull test: (P,) bool, True where a point projects into the (dilated) mask of every
    view with a camera and a mask that sees it in front and inside the image."""
    keep = np.ones(len(points), dtype=bool)
    if masks is None or not len(points):
        return keep
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * _HULL_TOLERANCE_PX + 1,) * 2)
    for cam, mask in zip(cameras, masks, strict=True):
        if cam is None or mask is None:
            continue
        grown = cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)
        uv, z = cam.project(points)
        col, row = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        seen = (z > 0) & (col >= 0) & (col < mask.shape[1]) & (row >= 0) & (row < mask.shape[0])
        keep[seen] &= grown[row[seen], col[seen]]
    return keep


def _failure_message(
    what: str, names: Sequence[str], failed: Sequence[int], features: list[int], partners: list[int]
) -> str:
    """``what``, the failed views with their feature and partner counts, and a likely cause."""
    shown = [f"{names[i]} ({features[i]} features, matched with {partners[i]} views)" for i in failed[:12]]
    more = f" and {len(failed) - 12} more" if len(failed) > 12 else ""
    hint = ""
    if failed and float(np.median([features[i] for i in failed])) < _FEW_FEATURES:
        hint = " The views hold almost no features: a textureless, dark or blurred object?"
    elif failed:
        hint = " The views share too few features: do the frames overlap?"
    return f"{what}; views that failed: {', '.join(shown)}{more}.{hint}"


def _silhouette_note(refused: dict[str, str]) -> str:
    """What the silhouette search said about the views it did not register, for a failure message."""
    if not refused:
        return ""
    reasons = list(refused.values())
    if reasons[0].startswith("not searched"):
        return f"; the missing views were not searched for by their masks ({reasons[0][len('not searched: '):]})"
    ambiguous = sum(why.startswith("ambiguous") for why in reasons)
    note = f"; their masks did not place {len(refused)} of the missing views"
    if ambiguous:
        note += f" ({ambiguous} ambiguous: their silhouettes fit distinct poses alike, a symmetric object?)"
    return note


@dataclass
class SfmRun:
    """What COLMAP made of one set of images, before the masks adjust and complete it (:func:`finish_model`)."""

    rec: pycolmap.Reconstruction | None
    images: Sequence[np.ndarray]
    files: list[str]
    Ks: list[np.ndarray | None]
    features: list[int]
    partners: list[int]
    known: bool
    known_cameras: list[Camera]
    timings: dict[str, float]
    seconds: float  # wall time of the run
    extras: list[dict] = field(default_factory=list)  # SparseModel.extras: the refinements after the mapping

    @property
    def num_registered(self) -> int:
        return 0 if self.rec is None else len(self.rec.reg_image_ids())


def finish_model(
    run: SfmRun,
    names: Sequence[str],
    cameras: Sequence[Camera | None] | None,
    masks: Sequence[np.ndarray | None] | None,
    options: SfmOptions,
    report: Progress,
    *,
    t0: float | None = None,
) -> SparseModel:
    """The kept run's model: held to the masks, its missing views registered from them where they
    decide a pose (``sfm.frontier_weight``, ``sfm.silhouette_register_px``), checked, as a
    SparseModel. ``t0``: when the poses step began (default: when the run began)."""
    t_finish = time.perf_counter()
    rec, images, files, Ks = run.rec, run.images, run.files, run.Ks
    features, partners, known, known_cameras = run.features, run.partners, run.known, run.known_cameras
    n = len(images)
    timings = dict(run.timings)
    extras = list(run.extras)
    frontier = None
    silhouette_views: list[str] = []
    silhouette_refused: dict[str, str] = {}
    needed = max(options.min_registered_views, math.ceil(options.min_registered_fraction * n))
    # too few views, and the masks may not complete the model: it fails whatever the adjustment does
    hopeless = run.num_registered < needed and (
        options.silhouette_register_px <= 0 or run.num_registered < options.silhouette_min_registered * n
    )
    if hopeless and not known and rec is not None and masks is not None and options.silhouette_register_px > 0:
        by_file = {f: m for f, m in zip(files, masks, strict=True) if m is not None}
        silhouette_refused = _register_missing_by_silhouette(rec, by_file, files, Ks, images, options)[1]
    elif not known and rec is not None and masks is not None and options.frontier_weight > 0:
        report(0.97, "holding the poses to the masks")
        t = time.perf_counter()
        by_file = {f: m for f, m in zip(files, masks, strict=True) if m is not None}
        frontier = frontier_adjust(
            rec, by_file, weight=options.frontier_weight, iterations=options.frontier_iterations
        )
        timings["frontier"] = time.perf_counter() - t
        extras.append({"step": "frontier", "seconds": timings["frontier"],
                       **({"skipped": "too few masked views or pairs"} if frontier is None else frontier.as_dict())})
        if options.silhouette_register_px > 0:
            t = time.perf_counter()
            missing = n - run.num_registered
            silhouette_views, silhouette_refused, last = _register_missing_by_silhouette(
                rec, by_file, files, Ks, images, options
            )
            frontier = last or frontier  # the adjustment that gave the final poses
            timings["silhouette_registration"] = time.perf_counter() - t
            extras.append({"step": "silhouette_registration", "seconds": timings["silhouette_registration"],
                           "missing": missing, "registered": len(silhouette_views),
                           **({"skipped": "every view registered"} if not missing else {})})

    index = {name: i for i, name in enumerate(files)}
    view_of_image = {} if rec is None else {im.image_id: index[im.name] for im in rec.images.values()}
    result_cameras: list[Camera | None] = list(known_cameras) if known else [None] * n
    if not known and rec is not None:
        for image in rec.images.values():
            if image.has_pose:
                i = view_of_image[image.image_id]
                pose = image.cam_from_world()
                h, w = images[i].shape[:2]
                result_cameras[i] = Camera(
                    K=image.camera.calibration_matrix(), R=pose.rotation.matrix(), t=pose.translation,
                    width=w, height=h,
                )
    registered = [c is not None for c in result_cameras]
    if sum(registered) < needed:
        raise ReconstructionError(_failure_message(
            f"SfM registered {sum(registered)} of {n} views, at least {needed} needed "
            f"(min_registered_views = {options.min_registered_views}, "
            f"min_registered_fraction = {options.min_registered_fraction})" + _silhouette_note(silhouette_refused),
            names, [i for i in range(n) if not registered[i]], features, partners,
        ))
    assert rec is not None
    points, colors, views, observations = _sparse_points(rec, view_of_image, images)
    keep = _inside_masks(points, result_cameras, masks)
    if known:  # two-view points from chance matches in the epipolar band: mostly wrong (measured ~60 %)
        keep &= np.array([len(v) >= 3 for v in views], dtype=bool)
    points, colors = points[keep], colors[keep]
    views = [v for v, k in zip(views, keep, strict=True) if k]
    observations = [o for o, k in zip(observations, keep, strict=True) if k]
    multi_view = sum(len(v) >= 3 for v in views)
    if not known and multi_view < options.min_sparse_points:  # known poses: the masks' hull bounds depth
        weakest = sorted(range(n), key=lambda i: (features[i], partners[i]))
        raise ReconstructionError(_failure_message(
            f"only {multi_view} 3D points were triangulated from 3 or more views ({len(points)} in all), at "
            f"least min_sparse_points = {options.min_sparse_points} needed",
            names, weakest, features, partners,
        ))
    now = time.perf_counter()
    timings["finish"] = now - t_finish
    timings["total"] = run.seconds + timings["finish"] if t0 is None else now - t0
    report(1.0, "poses done")
    return SparseModel(
        cameras=result_cameras, points=points, point_colors=colors, point_views=views,
        point_observations=observations,
        mean_reprojection_error=float(rec.compute_mean_reprojection_error()), registered=registered,
        known_poses=known, timings=timings, names=list(names), num_features=features,
        frontier=None if frontier is None else frontier.as_dict(),
        silhouette_registered=[names[index[f]] for f in silhouette_views],
        silhouette_refused={names[index[f]]: why for f, why in silhouette_refused.items()},
        extras=extras,
    )


def _register_missing_by_silhouette(
    rec: pycolmap.Reconstruction,
    masks: dict[str, np.ndarray],
    files: list[str],
    Ks: list[np.ndarray | None],
    images: Sequence[np.ndarray],
    options: SfmOptions,
) -> tuple[list[str], dict[str, str], FrontierReport | None]:
    """The views SfM left out, registered from their masks and adjusted with the rest (two passes:
    the views registered in the first give the second more pairs). Returns their file names, why
    the others were not registered (file name -> reason) and the last adjustment's report (None
    when none was registered)."""
    registered = {rec.images[i].name for i in rec.reg_image_ids()}
    if len(registered) < options.silhouette_min_registered * len(files):
        why = (f"not searched: SfM registered {len(registered)} of {len(files)} views, under "
               f"sfm.silhouette_min_registered = {options.silhouette_min_registered:g}")
        return [], {f: why for f in files if f not in registered and f in masks}, None
    shared = {  # estimated intrinsics: a registered view's of the same size
        images[files.index(rec.images[i].name)].shape[:2]: rec.cameras[rec.images[i].camera_id].calibration_matrix()
        for i in rec.reg_image_ids()
    }
    done: list[str] = []
    refused: dict[str, str] = {}
    last: FrontierReport | None = None
    for _ in range(2):
        missing = {}
        for i, f in enumerate(files):
            K = Ks[i] if Ks[i] is not None else shared.get(images[i].shape[:2])
            if f not in registered and f not in done and f in masks and K is not None:
                missing[f] = K
        if not missing:
            break
        searched = register_from_silhouettes(rec, masks, missing, max_rms_px=options.silhouette_register_px)
        refused.update({r.name: r.reason for r in searched if not r.registered})
        found = [r.name for r in searched if r.registered]
        if not found:
            break
        done += found
        for name in found:
            refused.pop(name, None)
        last = frontier_adjust(rec, masks, weight=options.frontier_weight, iterations=options.frontier_iterations)
    return done, refused, last
