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
import shutil
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

from pmvir.camera import Camera
from pmvir.config import SfmOptions
from pmvir.errors import ReconstructionError, ShapeError
from pmvir.geometry.sfm.colmap import Progress, quiet_colmap, run_colmap
from pmvir.geometry.sfm.inputs import check_inputs, view_intrinsics, write_inputs
from pmvir.geometry.sfm.model import SfmRun, SparseModel, finish_model
from pmvir.io.colmap_text import image_from_camera, pinhole_from_camera, write_colmap_text_model

__all__ = ["Progress", "SparseModel", "estimate_poses", "write_poses_text"]


#: SfM on denoised images: where the first run (not upsampled) places at least this share of the views
#: (all of them only where its model failed the checks), the upsampled run on the same images comes
#: next, before the usual (equalized) runs. The path-traced knot on a table: 33 of 36 views, then 34
#: upsampled, while the usual runs placed 19-21 of them at ten times the cost; the Stanford armadillo:
#: 27, then 36. Below it the equalized images are needed (the Stanford dragon, smooth: 14 of 36).
_DENOISED_LEAD = 0.4

#: ... and where that upsampled run places at least this share, it is kept without the usual runs.
_DENOISED_KEEP = 0.75


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
            model = finish_model(quick, names, cameras, masks, denoised, report)
        except ReconstructionError as exc:
            quick_error = exc
        else:
            model.extras.insert(0, _denoised_entry(quick, None, time.perf_counter() - t0, kept=True))
            return model
    tried = _denoised_entry(quick, quick_error, time.perf_counter() - t0, kept=False)

    def denoised_upsampled(start: float, span: float) -> SparseModel:
        """SfM on the first run's denoised images, upsampled; progress over ``span`` from ``start``."""
        return finish_model(_run_sfm(
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


def _denoised_entry(run: SfmRun | None, error: ReconstructionError | None, seconds: float, *, kept: bool) -> dict:
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
                    model = finish_model(quick, names, cameras, masks, options, report)
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
        return _noting(tried, finish_model(run, names, cameras, masks, options, report))
    return _noting(tried, _first_then_second(
        images, fallback_images, Path(workdir), report,
        sfm=lambda ims, where, rep: _run_sfm(
            ims, cameras, intrinsics, masks, options, where, rep, names=names, focal_priors=focal_priors
        ),
        finish=lambda run, rep, t0: finish_model(run, names, cameras, masks, options, rep, t0=t0),
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
    sfm: Callable[[Sequence[np.ndarray], Path, Progress], SfmRun],
    finish: Callable[[SfmRun, Progress, float], SparseModel],
    completable: Callable[[SfmRun], bool],
) -> SparseModel:
    """SfM on ``images``, and on ``fallback_images`` where views are left out (:func:`estimate_poses`):
    ``sfm(images, workdir, report)`` runs SfM, ``finish(run, report, t0)`` is :func:`finish_model`,
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


def _completable(run: SfmRun, masks: Sequence[np.ndarray | None] | None, options: SfmOptions) -> bool:
    """Whether :func:`finish_model` registers the views ``run`` left out from their masks where their
    silhouettes decide a pose: masks, the frontier adjustment and the silhouette registration on, and
    at least ``sfm.silhouette_min_registered`` of the views registered."""
    return (
        not run.known and run.rec is not None and masks is not None and any(m is not None for m in masks)
        and options.frontier_weight > 0 and options.silhouette_register_px > 0
        and run.num_registered >= options.silhouette_min_registered * len(run.images)
    )


def _upsampling_try(
    run: SfmRun | None, error: ReconstructionError | None, seconds: float, *, kept: bool
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


def _attempt(run: Callable[[], SfmRun]) -> tuple[SfmRun | None, ReconstructionError | None]:
    """``run()``, or its ReconstructionError."""
    try:
        return run(), None
    except ReconstructionError as exc:
        return None, exc


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
) -> SfmRun:
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
    return SfmRun(
        rec, images, files, Ks, features, partners, known, known_cameras, timings, time.perf_counter() - t_start,
        extras,
    )


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
