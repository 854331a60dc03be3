"""Camera poses and sparse points (pipeline stage 2, first step), with pycolmap.

:func:`estimate_poses` runs in one of two modes:

* **known poses** (every view's Camera is given, as from a calibrated rig):
  SIFT features are matched along the known epipolar lines and triangulated
  with the poses and intrinsics held fixed (``pycolmap.triangulate_points``);
  the cameras come back as given, bit for bit. Only points seen in 3 or more
  views are kept (two-view points from chance matches in the epipolar band
  were mostly wrong: about 60 % in our measurements). With ``sift_upsample``
  'auto', SIFT sees the images upsampled where masks are given and as they are
  without masks: there the support's and the room's texture gives plenty of
  features, and the points only choose dense stereo's neighbours and bound its
  depths. On the path-traced knot on a table (36 views of 612x512, no masks)
  the features took 5.9 s instead of 21.5 s and the matching 3.0 s instead of
  21.3 s, for 1,090 points seen in 3 or more views instead of 1,381; the
  initial surface came out alike (accuracy 0.255e-2 both, completeness
  1.04e-2 against 1.03e-2).
* **SfM** (otherwise): SIFT features, exhaustive matching (or sequential in
  capture order above ``exhaustive_matching_max_views`` views), COLMAP's
  incremental mapping and a last robust bundle adjustment, then
  ``sfm.rematch_rounds`` times the known-pose matching along the estimated
  poses, triangulation and the robust bundle adjustment again (longer tracks
  between views 30-70 degrees apart; its points seen in fewer than
  ``sfm.rematch_min_track`` views are dropped; models that must be joined
  get one round per joining pass). Given intrinsics are
  held fixed (PINHOLE); missing ones are estimated as SIMPLE_PINHOLE (one focal
  length, principal point at the image centre; refined from ``focal_priors`` where
  given, e.g. EXIF, else from COLMAP's 1.2 x the longer side), shared by the views
  of one image size (and prior) unless ``sfm.shared_intrinsics`` is off. The result lives in
  SfM's own frame (known up to a similarity). Where views are left out
  (``sfm.join_models``), every model registers its missed views by absolute
  pose and models agreeing on two or more common views are joined into the
  one with most views (:mod:`pmvir.geometry.sfm.join`), which is kept.

The COLMAP plumbing (database, matching, mapping, refinement) is in
:mod:`pmvir.geometry.sfm.colmap`.

SIFT sees an 8-bit grey image per view (:func:`~pmvir.geometry.sfm.inputs.sift_image`): the channel mean,
exposed so the 99.5th percentile of the foreground is white, sRGB-encoded, optionally denoised by
non-local means (``sift_denoise``) and (``sift_equalize``) contrast-equalized with CLAHE. SfM runs
first on images denoised and not equalized (``sfm.denoised_runs``) and keeps that model when every
view registers: on noisy frames the equalization lifts the noise into features that match nowhere
and the noise moves the rest; smooth, weakly textured objects need the equalization, and the runs
described above follow. Where they leave views out, SfM runs last on the denoised images upsampled.
Where the first run placed at least 40 % of the views, the denoised images evidently carry the
matches: their upsampled run comes right after it, and the usual runs follow only where it places
fewer than three quarters of the views. The runs on denoised images match with guidance (each pair
matched again along its verified epipolar geometry), whatever ``sfm.guided_matching`` says: noisy
frames give tens of matches a pair, and guidance holds their views in one model.

Masks, eroded by ``sfm.mask_erosion_px`` (default 4) so that no feature sits on the silhouette
(a silhouette is no fixed surface point), restrict
where features are detected. Where masks are
given, sparse points must also project into every view's mask (grown by
``_HULL_TOLERANCE_PX``): the visual hull.

Failures are :class:`~pmvir.errors.ReconstructionError` naming the views that
failed with their feature and match counts: fewer views than
``min_registered_views`` (or than ``min_registered_fraction`` of them)
registered, or (SfM only) fewer than ``min_sparse_points`` points seen in 3 or
more views (a textureless object, or frames that do not overlap). Known poses
never need sparse points: dense stereo bounds its depths by the known cameras'
visual hull (:mod:`pmvir.geometry.silhouette.hull`), and the points only tighten it. COLMAP's own log lines
are silenced below FATAL while it runs.
"""

from __future__ import annotations

import functools
import math
import shutil
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import pycolmap

from pmvir.camera import Camera
from pmvir.config import SfmOptions
from pmvir.errors import ReconstructionError, ShapeError
from pmvir.geometry.sfm.colmap import Progress, quiet_colmap, run_colmap
from pmvir.geometry.sfm.frontier import FrontierReport, frontier_adjust, register_from_silhouettes
from pmvir.geometry.sfm.inputs import EXPOSURE_PERCENTILE, check_inputs, view_intrinsics, write_inputs
from pmvir.io.colmap_text import image_from_camera, pinhole_from_camera, write_colmap_text_model
from pmvir.polarization.preview import srgb_encode

__all__ = ["Progress", "SparseModel", "estimate_poses", "write_poses_text"]

#: Sparse points must project into every mask grown by this many pixels (visual hull).
_HULL_TOLERANCE_PX = 3

#: Failure messages call views with fewer SIFT features than this (median) textureless.
_FEW_FEATURES = 100

#: SfM on denoised images: where the first run (not upsampled) places at least this share of the views
#: (all of them only where its model failed the checks), the upsampled run on the same images comes
#: next, before the usual (equalized) runs. The path-traced knot on a table: 33 of 36 views, then 34
#: upsampled, while the usual runs placed 19-21 of them at ten times the cost; the Stanford armadillo:
#: 27, then 36. Below it the equalized images are needed (the Stanford dragon, smooth: 14 of 36).
_DENOISED_LEAD = 0.4

#: ... and where that upsampled run places at least this share, it is kept without the usual runs.
_DENOISED_KEEP = 0.75


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
            ``fallback_images`` of :func:`estimate_poses` gave this model.
        frontier: the frontier adjustment's report (:class:`.frontier.FrontierReport` as a
            dict: residuals before and after, whether its poses were kept), or None where it did
            not run (known poses, no masks, ``sfm.frontier_weight`` 0, too few masked views).
        silhouette_registered: names of the views SfM left out that were registered from their
            masks (:func:`.frontier.register_from_silhouettes`, ``sfm.silhouette_register_px``).
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


def estimate_poses(
    images: Sequence[np.ndarray],
    names: Sequence[str],
    *,
    cameras: Sequence[Camera | None] | None = None,
    intrinsics: Sequence[np.ndarray | None] | None = None,
    masks: Sequence[np.ndarray | None] | None = None,
    options: SfmOptions,
    workdir: str | Path,
    progress: Progress | None = None,
    fallback_images: Sequence[np.ndarray] | None = None,
    focal_priors: Sequence[float | None] | None = None,
) -> SparseModel:
    """Cameras and sparse points of a set of views (module docstring: the two modes).

    Args:
        images: per view (H, W, 3) float32 linear intensities (I_int; I_min holds fewer
            view-dependent specular highlights).
        names: per view a distinct name (used in messages and :func:`write_poses_text`).
        cameras: per view the known Camera or None; known-pose mode when every entry is given.
        intrinsics: per view a known (3, 3) K or None (SfM mode; a given camera's K counts too).
        masks: per view an (H, W) bool foreground mask or None; features only inside.
        options: the ``geometry.sfm`` options. With ``sift_upsample`` 'auto', SfM runs first without
            SIFT upsampling (in ``workdir/without-upsampling``) and is kept when every view registers;
            otherwise everything below runs with it. Known poses with 'auto' use it where masks are
            given, not without them.
        workdir: scratch folder (created; its images/, masks/, sparse/, database.db and guided.db are
            replaced, and fallback/ and without-upsampling/ for those runs).
        progress: called as ``progress(fraction, step)`` between steps; it may raise
            CanceledError to stop.
        fallback_images: per view a second image of the same kind as ``images`` (e.g. I_int
            when ``images`` are I_min), or None. In SfM mode, when SfM on ``images`` registers
            fewer than every view (or fails), it runs again on these (in ``workdir/fallback``)
            and the model with more registered views is kept (ties: the first); the result's
            ``fallback`` says which. Only the kept model is held to the masks and completed from
            them (``sfm.frontier_weight``, ``sfm.silhouette_register_px``), except that a first
            model the masks may complete (``sfm.silhouette_min_registered``) is held and completed
            first, and the second run is made only where views are still missing. Ignored with
            known poses.
        focal_priors: per view a focal length in pixels to start from (e.g. from EXIF) or None;
            SfM refines it (SIMPLE_PINHOLE, principal point at the image centre). Used only for
            views whose intrinsics are not given.

    With ``sfm.denoised_runs`` above 0, SfM runs first on ``images`` denoised (non-local means) and not
    equalized, without upsampling where ``sift_upsample`` is 'auto' (in ``workdir/denoised-first``), and
    that model is kept when every view registers. Otherwise the runs above follow, and where they still
    leave views out (or fail) and ``sift_upsample`` is 'auto', SfM runs once more on the denoised images
    upsampled (in ``workdir/denoised``, reusing the first run's images); the model with more registered
    views is kept (ties: the first). Where the first run placed at least ``_DENOISED_LEAD`` of the views,
    that upsampled run is made right after it, and kept without the runs above where it places at least
    ``_DENOISED_KEEP`` of them (extras: a skipped ``usual_runs`` step).

    Returns:
        The SparseModel; in known-pose mode its cameras are the given objects.

    Raises:
        ShapeError: inconsistent lengths or shapes of the arguments.
        InputError: repeated names, or a skewed K.
        ReconstructionError: fewer views than ``min_registered_views``; too few registered
            views; too few 3D points. The message names the views that failed.
    """
    report = progress or (lambda fraction, step: None)
    _enough_views(len(images), options)  # once, before any run (each run would say it again)
    known = cameras is not None and all(c is not None for c in cameras) and len(cameras) == len(images)
    if fallback_images is not None and len(fallback_images) != len(images):
        raise ShapeError(f"expected {len(images)} fallback images (one per view), got {len(fallback_images)}")
    if known or options.denoised_runs <= 0:
        return _cascade(images, names, cameras, intrinsics, masks, options, workdir, report, fallback_images,
                        focal_priors, known=known)
    n = len(images)
    denoised = _denoised_options(options)
    # SfM on denoised images first ('auto': without upsampling), kept when every view registers
    auto = options.sift_upsample == "auto"
    first_images = Path(workdir) / "denoised-first" / "images"
    shutil.rmtree(first_images, ignore_errors=True)  # (the last run reuses what this call writes there)
    t0 = time.perf_counter()
    quick, quick_error = _attempt(lambda: _run_sfm(
        images, cameras, intrinsics, masks, denoised.model_copy(update={"sift_upsample": not auto and
                                                                        options.sift_upsample}),
        Path(workdir) / "denoised-first", lambda f, s: report(0.15 * f, f"{s} (denoised images)"),
        names=names, focal_priors=focal_priors, complete_or_stop=True,
    ))
    if quick is not None and quick.num_registered == n:
        try:
            model = _finish(quick, names, cameras, masks, denoised, report)
        except ReconstructionError as exc:
            quick_error = exc
        else:
            model.extras.insert(0, _denoised_entry(quick, None, time.perf_counter() - t0, kept=True))
            return model
    tried = _denoised_entry(quick, quick_error, time.perf_counter() - t0, kept=False)

    def denoised_upsampled(start: float, span: float) -> SparseModel:
        """SfM on the first run's denoised images, upsampled; progress over ``span`` from ``start``."""
        return _finish(_run_sfm(
            images, cameras, intrinsics, masks, denoised, Path(workdir) / "denoised",
            lambda f, s: report(start + span * min(f, 0.99), f"{s} (denoised images)"), names=names,
            focal_priors=focal_priors, reuse_images=first_images,
        ), names, cameras, masks, denoised, lambda f, s: None)

    # the denoised images placed many views: their upsampled run comes before the usual runs, which
    # are made only where it leaves too many views out
    early: SparseModel | None = None
    early_error: ReconstructionError | None = None
    early_s = 0.0
    if auto and quick is not None and quick.num_registered >= _DENOISED_LEAD * n:
        t_early = time.perf_counter()
        try:
            early = denoised_upsampled(0.15, 0.15)
        except ReconstructionError as exc:
            early_error = exc
        early_s = time.perf_counter() - t_early
        if early is not None and early.num_registered >= _DENOISED_KEEP * n:
            early.extras.insert(0, tried)
            early.extras.append({"step": "denoised", "seconds": early_s, "registered_before": quick.num_registered,
                                 "registered": early.num_registered, "kept": True})
            early.extras.append({"step": "usual_runs", "seconds": 0.0, "skipped": (
                f"the denoised images placed {quick.num_registered} of {n} views, then {early.num_registered} "
                f"upsampled (at least {_DENOISED_KEEP:.0%})")})
            early.timings["denoised_first"] = tried["seconds"]
            early.timings["total"] += tried["seconds"]
            report(1.0, "poses done")
            return early
    t1 = time.perf_counter()
    cascade: SparseModel | None = None
    error: ReconstructionError | None = None
    try:  # (its "poses done" waits: the upsampled run on denoised images may follow)
        cascade = _cascade(
            images, names, cameras, intrinsics, masks, options, workdir,
            lambda f, s: report(0.15 + 0.75 * min(f, 0.99), s) if f < 1.0 else None,
            fallback_images, focal_priors, known=False,
        )
    except ReconstructionError as exc:
        error = exc
    if early is not None or early_error is not None:  # made first: compared and counted in any case
        cascade = _denoised_retry(cascade, error, time.perf_counter() - t1,
                                  functools.partial(_made, early, early_error), spent=early_s)
    elif auto and (cascade is None or cascade.num_registered < n):
        cascade = _denoised_retry(cascade, error, time.perf_counter() - t1,
                                  functools.partial(denoised_upsampled, 0.9, 0.1))
    if cascade is None:
        assert error is not None
        raise error
    cascade.extras.insert(0, tried)
    cascade.timings["denoised_first"] = tried["seconds"]
    cascade.timings["total"] += tried["seconds"]
    report(1.0, "poses done")
    return cascade


def _denoised_entry(run: _SfmRun | None, error: ReconstructionError | None, seconds: float, *, kept: bool) -> dict:
    """The ``extras`` entry of the first SfM run, on denoised images (``sfm.denoised_runs``)."""
    entry: dict = {"step": "denoised_first", "seconds": seconds, "kept": kept,
                   "registered": 0 if run is None else run.num_registered}
    if error is not None:
        entry["error"] = str(error)
    return entry


def _denoised_options(options: SfmOptions) -> SfmOptions:
    """The options of SfM's runs on denoised images (``sfm.denoised_runs``): denoised, not equalized,
    upsampled, matched again along each pair's verified geometry (guided matching: on noisy frames the
    ratio test leaves tens of matches a pair, and the first run on the path-traced knot on a table placed
    33 of 36 views in one model with it, 18 of 36 in the largest of three without)."""
    return options.model_copy(update={"sift_denoise": options.denoised_runs, "sift_equalize": False,
                                      "sift_upsample": options.sift_upsample is not False,
                                      "guided_matching": True})


def _made(model: SparseModel | None, error: ReconstructionError | None) -> SparseModel:
    """A run made earlier, as :func:`_denoised_retry`'s ``retry``: its model, or its error raised."""
    if model is None:
        assert error is not None
        raise error
    return model


def _denoised_retry(
    model: SparseModel | None, error: ReconstructionError | None, seconds: float, retry: Callable[[], SparseModel],
    *, spent: float | None = None,
) -> SparseModel:
    """The model with more registered views of ``model`` (SfM's usual runs, which took ``seconds``; None
    where they failed with ``error``) and ``retry()`` (SfM on denoised, upsampled images; ``spent``: its
    seconds where it was made earlier); ties keep ``model``. The kept model's extras get a ``denoised``
    step, its timings the time of the one not kept ("denoised" or "without_denoising"), in the total as
    well."""
    t0 = time.perf_counter()
    other: SparseModel | None = None
    try:
        other = retry()
    except ReconstructionError as exc:
        if model is None:
            raise ReconstructionError(f"{error}; on denoised images: {exc}") from exc
    if spent is None:
        spent = time.perf_counter() - t0
    before = 0 if model is None else model.num_registered
    after = 0 if other is None else other.num_registered
    kept = model if model is not None and (other is None or before >= after) else other
    assert kept is not None  # (both None raised above)
    kept.extras.append({"step": "denoised", "seconds": spent, "registered_before": before, "registered": after,
                        "kept": kept is other})
    if kept is other:
        kept.timings["without_denoising"] = seconds
    else:
        kept.timings["denoised"] = spent
    kept.timings["total"] = seconds + spent
    return kept


def _cascade(
    images: Sequence[np.ndarray],
    names: Sequence[str],
    cameras: Sequence[Camera | None] | None,
    intrinsics: Sequence[np.ndarray | None] | None,
    masks: Sequence[np.ndarray | None] | None,
    options: SfmOptions,
    workdir: str | Path,
    report: Progress,
    fallback_images: Sequence[np.ndarray] | None,
    focal_priors: Sequence[float | None] | None,
    *,
    known: bool,
) -> SparseModel:
    """SfM without upsampling, with it, and on the fallback images, as far as views are left out (or
    the known-pose triangulation): :func:`estimate_poses` without the run on denoised images."""
    tried: dict | None = None  # the SfM run without SIFT upsampling, when it was not kept
    if options.sift_upsample == "auto":
        # known poses: upsampled where masks bound the features to the object, which needs every one
        # of them; not without masks (module docstring)
        unmasked = masks is None or all(m is None for m in masks)
        options = options.model_copy(update={"sift_upsample": not (known and unmasked)})  # what every run below uses
        if not known:  # (known poses: one triangulation, no run to try first)
            # SfM without upsampling first (a third of the extraction time); kept when every view registers
            t_try = time.perf_counter()
            quick, quick_error = _attempt(lambda: _run_sfm(
                images, cameras, intrinsics, masks, options.model_copy(update={"sift_upsample": False}),
                Path(workdir) / "without-upsampling", lambda f, s: report(0.3 * f, f"{s} (without upsampling)"),
                names=names, focal_priors=focal_priors, complete_or_stop=True,
            ))
            if quick is not None and quick.num_registered == len(images):
                try:
                    model = _finish(quick, names, cameras, masks, options, report)
                except ReconstructionError as exc:
                    quick_error = exc
                else:
                    return _noting(_upsampling_try(quick, None, time.perf_counter() - t_try, kept=True), model)
            tried = _upsampling_try(quick, quick_error, time.perf_counter() - t_try, kept=False)
            report = functools.partial(_rescaled, report, 0.3, 0.7)  # the runs below: the rest of the range
    if fallback_images is None or known:
        run = _run_sfm(
            images, cameras, intrinsics, masks, options, workdir, report, names=names, focal_priors=focal_priors
        )
        return _noting(tried, _finish(run, names, cameras, masks, options, report))
    return _noting(tried, _first_then_second(
        images, fallback_images, Path(workdir), report,
        sfm=lambda ims, where, rep: _run_sfm(
            ims, cameras, intrinsics, masks, options, where, rep, names=names, focal_priors=focal_priors
        ),
        finish=lambda run, rep, t0: _finish(run, names, cameras, masks, options, rep, t0=t0),
        completable=lambda run: _completable(run, masks, options),
    ))


def _enough_views(n: int, options: SfmOptions) -> None:
    """Raise ReconstructionError when ``n`` views are fewer than ``sfm.min_registered_views``."""
    if n < options.min_registered_views:
        raise ReconstructionError(
            f"too few views: {n} given, poses need at least min_registered_views = {options.min_registered_views}"
        )


def _first_then_second(
    images: Sequence[np.ndarray],
    fallback_images: Sequence[np.ndarray],
    workdir: Path,
    report: Progress,
    *,
    sfm: Callable[[Sequence[np.ndarray], Path, Progress], _SfmRun],
    finish: Callable[[_SfmRun, Progress, float], SparseModel],
    completable: Callable[[_SfmRun], bool],
) -> SparseModel:
    """SfM on ``images``, and on ``fallback_images`` where views are left out (:func:`estimate_poses`):
    ``sfm(images, workdir, report)`` runs SfM, ``finish(run, report, t0)`` is :func:`_finish`,
    ``completable(run)`` is :func:`_completable`."""
    t0 = time.perf_counter()
    n = len(images)
    first, first_error = _attempt(lambda: sfm(images, workdir, lambda f, s: report(0.5 * f, s)))
    finished: SparseModel | None = None  # the first run finished before the second images were tried
    if first is not None and (first.num_registered == n or completable(first)):
        # every view registered, or few enough left out that their masks may register them: a second
        # SfM run (as long as the first) only where the first, finished, still leaves views out
        left_out = n - first.num_registered
        try:  # (its progress ends at half the range: the second run may follow)
            finished = finish(first, lambda f, s: report(0.5 * f, s) if f < 1.0 else None, t0)
        except ReconstructionError as exc:  # e.g. too few sparse points: the second images may give more
            first, first_error = None, exc
        else:
            if finished.num_registered == n:
                if left_out:
                    finished.extras.insert(0, {"step": "second_images", "seconds": 0.0, "skipped":
                                               f"the masks registered the {left_out} view(s) SfM left out"})
                report(1.0, "poses done")
                return finished
    t1 = time.perf_counter()
    second, second_error = _attempt(lambda: sfm(
        fallback_images, workdir / "fallback", lambda f, s: report(0.5 + 0.45 * f, f"{s} (second images)")
    ))
    seconds = {"first_images": t1 - t0, "second_images": time.perf_counter() - t1}
    registered_first = (
        finished.num_registered if finished is not None else 0 if first is None else first.num_registered
    )
    # the model with more registered views first (ties: the first images'); only the kept one is finished
    errors = [first_error, second_error]
    runs = [(registered_first, r) for r in (first,) if r is not None]
    runs += [(second.num_registered, second)] if second is not None else []
    for _, run in sorted(runs, key=lambda r: -r[0]):
        if run is first and finished is not None:
            model = finished
            model.timings["total"] = time.perf_counter() - t0
        else:
            try:
                model = finish(run, report, t0)
            except ReconstructionError as exc:
                errors[1 if run is second else 0] = exc
                continue
        model.fallback = run is second
        # the total counts both runs; "first_images" / "second_images" is the time of the run not kept
        other = "first_images" if model.fallback else "second_images"
        model.timings[other] = seconds[other]
        model.extras.insert(0, {
            "step": "second_images", "seconds": seconds["second_images"],
            "registered_first": registered_first,
            "registered_second": 0 if second is None else second.num_registered, "kept": "second" if model.fallback
            else "first",
        })
        report(1.0, "poses done")
        return model
    raise ReconstructionError(f"{errors[0]}; on the second images: {errors[1]}")


def _completable(run: _SfmRun, masks: Sequence[np.ndarray | None] | None, options: SfmOptions) -> bool:
    """Whether :func:`_finish` registers the views ``run`` left out from their masks where their
    silhouettes decide a pose: masks, the frontier adjustment and the silhouette registration on, and
    at least ``sfm.silhouette_min_registered`` of the views registered."""
    return (
        not run.known and run.rec is not None and masks is not None and any(m is not None for m in masks)
        and options.frontier_weight > 0 and options.silhouette_register_px > 0
        and run.num_registered >= options.silhouette_min_registered * len(run.images)
    )


def _upsampling_try(
    run: _SfmRun | None, error: ReconstructionError | None, seconds: float, *, kept: bool
) -> dict:
    """The ``extras`` entry of the SfM run without SIFT upsampling (``sfm.sift_upsample`` 'auto')."""
    entry: dict = {"step": "without_upsampling", "seconds": seconds, "kept": kept,
                   "registered": 0 if run is None else run.num_registered}
    if error is not None:
        entry["error"] = str(error)
    return entry


def _rescaled(report: Progress, start: float, span: float, fraction: float, step: str) -> None:
    """``report`` of a step that takes ``span`` of the range from ``start``."""
    report(start + span * fraction, step)


def _noting(tried: dict | None, model: SparseModel) -> SparseModel:
    """``model`` with the SfM run without upsampling first in its extras; a run not kept also counts in
    its timings (``without_upsampling``, and the total)."""
    if tried is not None:
        model.extras.insert(0, tried)
        if not tried["kept"]:
            model.timings["without_upsampling"] = tried["seconds"]
            model.timings["total"] += tried["seconds"]
    return model


def _attempt(run: Callable[[], _SfmRun]) -> tuple[_SfmRun | None, ReconstructionError | None]:
    """``run()``, or its ReconstructionError."""
    try:
        return run(), None
    except ReconstructionError as exc:
        return None, exc


@dataclass
class _SfmRun:
    """What COLMAP made of one set of images, before the masks adjust and complete it (:func:`_finish`)."""

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


def _run_sfm(
    images: Sequence[np.ndarray],
    cameras: Sequence[Camera | None] | None,
    intrinsics: Sequence[np.ndarray | None] | None,
    masks: Sequence[np.ndarray | None] | None,
    options: SfmOptions,
    workdir: str | Path,
    report: Progress,
    *,
    names: Sequence[str],
    focal_priors: Sequence[float | None] | None = None,
    complete_or_stop: bool = False,
    reuse_images: Path | None = None,
) -> _SfmRun:
    """COLMAP's features, matches and model (or triangulation with known poses) on one set of images
    (``complete_or_stop``: see :func:`~.colmap.run_colmap`; ``reuse_images``: see
    :func:`~.inputs.write_inputs`)."""
    t_start = time.perf_counter()
    n = len(images)
    check_inputs(images, names, cameras, intrinsics, masks)
    _enough_views(n, options)
    known_cameras = [c for c in cameras or () if c is not None]
    known = cameras is not None and len(known_cameras) == n
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    timings: dict[str, float] = {}

    report(0.0, "writing SIFT images")
    t0 = time.perf_counter()
    image_dir, mask_dir, files = write_inputs(workdir, images, masks, options, reuse=reuse_images)
    timings["images"] = time.perf_counter() - t0
    Ks = [view_intrinsics(i, cameras, intrinsics) for i in range(n)]
    extras: list[dict] = []
    with quiet_colmap():
        rec, features, partners = run_colmap(
            workdir, image_dir, mask_dir, files, [im.shape[:2] for im in images], Ks,
            known_cameras if known else None, options, timings, report, focal_priors=focal_priors, extras=extras,
            complete_or_stop=complete_or_stop,
        )
    return _SfmRun(
        rec, images, files, Ks, features, partners, known, known_cameras, timings, time.perf_counter() - t_start,
        extras,
    )


def _finish(
    run: _SfmRun,
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


def write_poses_text(model: SparseModel, directory: str | Path) -> Path:
    """Write the registered cameras as a COLMAP text model (cameras.txt, images.txt, empty points3D.txt).

    Each registered view gets its own PINHOLE camera (CAMERA_ID = IMAGE_ID = view index + 1)
    and its ``names`` entry as image name (names must not hold whitespace).

    Returns:
        The directory.
    """
    cams, imgs = [], []
    for i, cam in enumerate(model.cameras):
        if cam is not None:
            cams.append(pinhole_from_camera(i + 1, cam))
            imgs.append(image_from_camera(i + 1, i + 1, model.names[i], cam))
    write_colmap_text_model(directory, cams, imgs)
    return Path(directory)
