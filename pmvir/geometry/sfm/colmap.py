"""COLMAP's mapping and refinement for :mod:`pmvir.geometry.sfm.poses` (features and matches: :mod:`.matching`).

* Known poses: the epipolar-guided matches (:func:`~pmvir.geometry.sfm.matching.match_known_poses`)
  triangulated by ``pycolmap.triangulate_points`` with the poses fixed.
* SfM: ``pycolmap.incremental_mapping`` (or ``global_mapping``), then a last robust bundle
  adjustment (:func:`_refine_sfm`); then, ``rematch_rounds`` times, the known-pose matching with
  SfM's poses, triangulation and the robust bundle adjustment (:func:`_rematch_and_refine`);
  where views are missing, the models are re-matched once, completed and joined
  (:func:`_join_models`), one re-matching round per joining pass.
"""

from __future__ import annotations

import contextlib
import shutil
import time
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pycolmap

from pmvir.camera import Camera
from pmvir.config import SfmOptions
from pmvir.geometry.sfm.join import (
    PNP_MIN_INLIERS,
    register_by_pnp,
    similarity_from_shared,
    transform_camera,
)
from pmvir.geometry.sfm.matching import (
    KNOWN_POSE_MIN_MATCHES,
    colmap_threads,
    database_stats,
    extract_features,
    match_images,
    match_known_poses,
)

Progress = Callable[[float, str], None]


#: SfM, joining models: passes of absolute-pose registration (and joining) before the last matching.
_JOIN_PASSES = 3

#: SfM's re-matching: a round that lengthens the tracks (observations in tracks of 3+ views) by less
#: than this fraction is the last.
_REMATCH_MIN_GAIN = 0.02

#: SfM's re-matching: a round whose adjustment moved the model's points in every view by less than this
#: (median, px), the epipolar band's half-width, is the last: the next would find nearly the same matches
#: (bunny, 36 views: after shifts of 1.2-1.3 px a second round added 0.2-0.8 % observations and left the
#: camera centres as they were, 0.060 % of the rig against 0.063 % after one round).
_REMATCH_MIN_SHIFT_PX = 2.0

#: SfM's re-matching: a view with fewer observations of long tracks keeps its short ones (drop_short_tracks).
_MIN_LONG_TRACK_OBSERVATIONS = 40


@contextlib.contextmanager
def quiet_colmap() -> Iterator[None]:
    """Silence COLMAP's log below FATAL (the library never prints; failures raise ReconstructionError)."""
    before = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = int(pycolmap.logging.Level.FATAL)
    try:
        yield
    finally:
        pycolmap.logging.minloglevel = before


def run_colmap(
    workdir: Path,
    image_dir: Path,
    mask_dir: Path | None,
    files: list[str],
    sizes: list[tuple[int, int]],
    Ks: list[np.ndarray | None],
    known_cameras: list[Camera] | None,
    options: SfmOptions,
    timings: dict[str, float],
    report: Progress,
    *,
    focal_priors: Sequence[float | None] | None = None,
    extras: list[dict] | None = None,
    complete_or_stop: bool = False,
) -> tuple[pycolmap.Reconstruction | None, list[int], list[int]]:
    """Features, matches, then triangulation (known poses) or incremental SfM.

    ``focal_priors``: per view a focal length (pixels) that SfM starts from and refines, for
    views whose ``Ks`` entry is None (else COLMAP's default guess, 1.2 x the longer side).
    ``extras``: SfM appends what each refinement after the mapping cost and gave (:func:`track_stats`
    before and after each re-matching round, the joining passes).
    ``complete_or_stop``: when the mapper's largest model leaves a view out, return it as it is (no
    refinement, no joining): the caller will run SfM again on better features anyway.

    Returns:
        The reconstruction (SfM: the model with most registered views, joined with the others
        where ``options.join_models``; None when SfM made none), per-view feature counts and
        per-view numbers of verified partner views.
    """
    database = workdir / "database.db"
    database.unlink(missing_ok=True)
    sparse_dir = workdir / "sparse"
    sparse_dir.mkdir(parents=True, exist_ok=True)

    report(0.1, "extracting SIFT features")
    t0 = time.perf_counter()
    extract_features(
        database, image_dir, mask_dir, files, sizes, Ks, options, focal_priors=focal_priors,
        crop=known_cameras is not None,
    )
    timings["features"] = time.perf_counter() - t0

    report(0.4, "matching features")
    t0 = time.perf_counter()
    if known_cameras is not None:
        match_known_poses(database, files, known_cameras)
    else:
        match_images(database, len(files), options)
    timings["matching"] = time.perf_counter() - t0
    features, partners = database_stats(database, files)

    t0 = time.perf_counter()
    if known_cameras is not None:
        report(0.6, "triangulating with the known poses")
        rec = pycolmap.triangulate_points(
            _known_pose_reconstruction(database, files, known_cameras), database, image_dir, sparse_dir,
            clear_points=True, options=_pipeline_options(options, set(), min_matches=KNOWN_POSE_MIN_MATCHES),
            refine_intrinsics=False,
        )
        if options.max_reprojection_error > 0:
            filter_observations(rec, options.max_reprojection_error)
            rec.update_point_3d_errors()
        timings["triangulation"] = time.perf_counter() - t0
        return rec, features, partners
    report(0.6, f"{options.mapper} SfM")
    constant = _known_camera_ids(database, files, Ks)
    if options.mapper == "global":
        models = pycolmap.global_mapping(database, image_dir, sparse_dir, options=_global_options(options, constant))
    else:
        models = pycolmap.incremental_mapping(
            database, image_dir, sparse_dir, options=_pipeline_options(options, constant)
        )
    ranked = sorted(models.values(), key=lambda r: r.num_reg_images(), reverse=True)
    timings["mapping"] = time.perf_counter() - t0
    if not ranked:
        return None, features, partners
    if complete_or_stop and ranked[0].num_reg_images() < len(files):
        return ranked[0], features, partners
    report(0.9, "refining the poses")
    t0 = time.perf_counter()
    joining = options.join_models and ranked[0].num_reg_images() < len(files)
    if not joining:
        ranked = ranked[:1]
    run = _Workspace(database, image_dir, sparse_dir, files, options, constant, [] if extras is None else extras)
    # Joined models keep their two-view points: the absolute poses that join them vote with every
    # point, and on the dragon (32 of 36 views joined) a last round without them was worse (largest
    # centre error 1.10 -> 1.17 % of the rig with the intrinsics given, 1.05 -> 1.09 % without).
    min_track = 2 if joining else options.rematch_min_track
    # Models to be joined are matched again once per pass: their sides are linked through a few
    # views, and each round along the bent poses kept the bend and added to it (dragon, 32 views:
    # largest centre error 1.10 -> 1.34 % of the rig with two rounds, 1.05 -> 1.40 % estimating K).
    rounds = min(1, options.rematch_rounds) if joining else options.rematch_rounds
    for k, rec in enumerate(ranked):
        _refine_sfm(rec, options, constant)
        if rounds:
            ranked[k] = _rematch_and_refine(rec, run, rounds, min_track=min_track, model=k)
    best = ranked[0]
    timings["refinement"] = time.perf_counter() - t0
    if joining:
        report(0.95, "joining the models")
        t0 = time.perf_counter()
        before = track_stats(ranked[0])
        joined = len(ranked)
        best = _join_models(ranked, run)
        timings["joining"] = time.perf_counter() - t0
        run.extras.append({"step": "join", "models": joined, "seconds": timings["joining"], "before": before,
                           "after": track_stats(best)})
    return best, features, partners


def _pipeline_options(
    options: SfmOptions, constant_cameras: set[int], *, min_matches: int = 15
) -> pycolmap.IncrementalPipelineOptions:
    po = pycolmap.IncrementalPipelineOptions()
    po.num_threads = colmap_threads()
    po.min_num_matches = min_matches
    po.random_seed = options.seed
    po.min_model_size = options.min_registered_views
    po.ba_refine_principal_point = False
    po.ba_refine_extra_params = False
    po.constant_cameras = constant_cameras
    po.mapper.init_min_num_inliers = options.init_min_inliers
    po.mapper.abs_pose_min_num_inliers = options.register_min_inliers
    return po


def _global_options(options: SfmOptions, constant_cameras: set[int]) -> pycolmap.GlobalPipelineOptions:
    """GLOMAP options: seeded, CPU, given intrinsics held fixed (focal lengths refined only when estimated)."""
    po = pycolmap.GlobalPipelineOptions()
    po.num_threads = colmap_threads()
    po.random_seed = options.seed
    po.min_model_size = options.min_registered_views
    po.mapper.random_seed = options.seed
    po.mapper.global_positioning.use_gpu = False
    po.mapper.global_positioning.random_seed = options.seed
    po.mapper.bundle_adjustment.refine_principal_point = False
    po.mapper.bundle_adjustment.refine_extra_params = False
    po.mapper.bundle_adjustment.refine_focal_length = not constant_cameras
    return po


def _known_pose_reconstruction(
    database: Path,
    files: list[str],
    cameras: Sequence[Camera | None],
    intrinsics: pycolmap.Reconstruction | None = None,
) -> pycolmap.Reconstruction:
    """A reconstruction holding the database's cameras and images, those with a given pose registered.

    The cameras (intrinsics) are the database's, or ``intrinsics``'s where it holds them.
    """
    index = {name: i for i, name in enumerate(files)}
    db = pycolmap.Database.open(str(database))
    try:
        rec = pycolmap.Reconstruction()
        for cam in db.read_all_cameras():
            known = intrinsics is not None and cam.camera_id in intrinsics.cameras
            rec.add_camera(intrinsics.cameras[cam.camera_id] if known else cam)  # type: ignore[union-attr]
        for rig in db.read_all_rigs():
            rec.add_rig(rig)
        images = {im.image_id: im for im in db.read_all_images()}
        frames = db.read_all_frames()
        posed = []
        for frame in frames:
            (data_id,) = frame.image_ids  # one camera per rig: one image per frame
            pose = cameras[index[images[data_id.id].name]]
            if pose is not None:
                frame.rig_from_world = pycolmap.Rigid3d(pycolmap.Rotation3d(pose.R), pose.t)
                posed.append(frame.frame_id)
            rec.add_frame(frame)
        for image in images.values():
            rec.add_image(image)
        for frame_id in posed:
            rec.register_frame(frame_id)
    finally:
        db.close()
    return rec


def _known_camera_ids(database: Path, files: list[str], Ks: list[np.ndarray | None]) -> set[int]:
    """Database camera ids of the views whose intrinsics were given (held fixed in SfM)."""
    index = {name: i for i, name in enumerate(files)}
    db = pycolmap.Database.open(str(database))
    try:
        return {im.camera_id for im in db.read_all_images() if Ks[index[im.name]] is not None}
    finally:
        db.close()


def filter_observations(rec: pycolmap.Reconstruction, max_error: float) -> int:
    """Delete observations whose reprojection error exceeds ``max_error`` px (and points left with < 2)."""
    removed = 0
    for pid in list(rec.points3D.keys()):
        point = rec.points3D[pid]
        bad = []
        for el in point.track.elements:
            image = rec.images[el.image_id]
            uv = image.project_point(point.xyz)
            if uv is None or np.linalg.norm(uv - image.points2D[el.point2D_idx].xy) > max_error:
                bad.append((el.image_id, el.point2D_idx))
        if len(point.track.elements) - len(bad) < 2:
            rec.delete_point3D(pid)
            removed += 1
            continue
        for image_id, idx in bad:
            rec.delete_observation(image_id, idx)
    return removed


def _refine_sfm(rec: pycolmap.Reconstruction, options: SfmOptions, constant_cameras: set[int]) -> None:
    """Final robust bundle adjustment (Cauchy loss, 1 px scale) between two outlier filters.

    Poses, points and the focal lengths of estimated cameras are refined; given intrinsics
    stay constant. (Uses the bundle adjuster directly: ``pycolmap.bundle_adjustment`` resets
    COLMAP's log level.)
    """
    if options.max_reprojection_error <= 0:
        return
    filter_observations(rec, options.max_reprojection_error)
    ba = pycolmap.BundleAdjustmentOptions()
    ba.refine_principal_point = False
    ba.refine_extra_params = False
    ba.print_summary = False
    ba.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
    ba.ceres.loss_function_scale = 1.0
    ba.ceres.solver_options.num_threads = colmap_threads()
    config = pycolmap.BundleAdjustmentConfig()
    for image_id in rec.reg_image_ids():
        config.add_image(image_id)
    for camera_id in constant_cameras & set(rec.cameras.keys()):
        config.set_constant_cam_intrinsics(camera_id)
    config.fix_gauge(pycolmap.BundleAdjustmentGauge.TWO_CAMS_FROM_WORLD)
    pycolmap.create_default_bundle_adjuster(ba, config, rec).solve()
    filter_observations(rec, options.max_reprojection_error)
    rec.update_point_3d_errors()


def _cameras_of(rec: pycolmap.Reconstruction, files: list[str]) -> list[Camera | None]:
    """Per view (``files`` order) the registered image's Camera, or None."""
    index = {name: i for i, name in enumerate(files)}
    cameras: list[Camera | None] = [None] * len(files)
    for image in rec.images.values():
        if image.has_pose:
            pose = image.cam_from_world()
            cameras[index[image.name]] = Camera(
                K=image.camera.calibration_matrix(), R=pose.rotation.matrix(), t=pose.translation,
                width=image.camera.width, height=image.camera.height,
            )
    return cameras


@dataclass(frozen=True)
class _Workspace:
    """What the steps after SfM's mapping share: the database, the image and model folders, the
    views' file names, the options and the cameras whose intrinsics are held."""

    database: Path
    image_dir: Path
    sparse_dir: Path
    files: list[str]
    options: SfmOptions
    constant_cameras: set[int]
    extras: list[dict]


def track_stats(rec: pycolmap.Reconstruction) -> dict[str, float | int]:
    """A model's size and its tracks: registered views, points, observations, points and observations of
    tracks of 3 or more views, mean track length, mean reprojection error (px)."""
    lengths = np.array([p.track.length() for p in rec.points3D.values()], dtype=np.int64)
    long = lengths >= 3
    return {
        "registered": rec.num_reg_images(),
        "points": len(lengths),
        "observations": int(lengths.sum()),
        "points_3plus": int(long.sum()),
        "observations_3plus": int(lengths[long].sum()),
        "mean_track": round(float(lengths.mean()), 3) if len(lengths) else 0.0,
        "reprojection_px": round(float(rec.compute_mean_reprojection_error()), 4) if len(lengths) else 0.0,
    }


def _rematch_and_refine(
    rec: pycolmap.Reconstruction, run: _Workspace, rounds: int, *, min_track: int, model: int = 0,
    step: str = "rematch",
) -> pycolmap.Reconstruction:
    """SfM's poses as if known: epipolar-guided matching, triangulation, robust bundle adjustment.

    The features of the registered views are matched again along the epipolar lines of the
    estimated poses (:func:`match_known_poses`, in a copy of the database), triangulated
    with the poses held, and refined by :func:`_refine_sfm` with the poses free: the guided
    matches between views 30-70 degrees apart, which RANSAC verification loses, make longer
    tracks. Points seen in fewer than ``min_track`` views (``sfm.rematch_min_track``) are dropped
    before and after the adjustment (:func:`drop_short_tracks`): a two-view match is checked only
    by the estimated epipolar line, and the poses bend to fit the wrong ones. Repeated ``rounds``
    times, stopping after a round that lengthened the tracks by less than ``_REMATCH_MIN_GAIN``
    (their observations in tracks of 3 or more views) or whose adjustment moved the poses by less
    than ``_REMATCH_MIN_SHIFT_PX`` (:func:`pose_shift_px`): the next round would match along the same
    epipolar lines. Each round's time and effect go to ``run.extras``.
    """
    guided = run.database.with_name("guided.db")
    out = run.sparse_dir / "guided"
    out.mkdir(parents=True, exist_ok=True)
    before = track_stats(rec)
    for k in range(rounds):
        t0 = time.perf_counter()
        shutil.copyfile(run.database, guided)
        db = pycolmap.Database.open(str(guided))
        try:
            db.clear_matches()
            db.clear_two_view_geometries()
        finally:
            db.close()
        matched_with = _cameras_of(rec, run.files)
        match_known_poses(guided, run.files, matched_with)
        rec = pycolmap.triangulate_points(
            rec,
            guided,
            run.image_dir,
            out,
            clear_points=True,
            options=_pipeline_options(run.options, run.constant_cameras, min_matches=KNOWN_POSE_MIN_MATCHES),
            refine_intrinsics=False,
        )
        drop_short_tracks(rec, min_track)
        _refine_sfm(rec, run.options, run.constant_cameras)
        drop_short_tracks(rec, min_track)
        after = track_stats(rec)
        gain = after["observations_3plus"] / max(int(before["observations_3plus"]), 1) - 1.0
        shift = pose_shift_px(rec, matched_with, run.files)
        entry: dict = {"step": step, "model": model, "round": k + 1, "seconds": time.perf_counter() - t0,
                       "before": before, "after": after, "gain": round(gain, 4), "pose_shift_px": round(shift, 4)}
        run.extras.append(entry)
        before = after
        if k + 1 < rounds and (gain < _REMATCH_MIN_GAIN or shift < _REMATCH_MIN_SHIFT_PX):
            why = (f"the round lengthened the tracks by {100 * gain:.1f} %, under {100 * _REMATCH_MIN_GAIN:.0f} %"
                   if gain < _REMATCH_MIN_GAIN else
                   f"its adjustment moved the points by at most {shift:.2f} px in a view, under {_REMATCH_MIN_SHIFT_PX} px")
            entry["stopped"] = f"{why}: {rounds - k - 1} more round(s) skipped"
            break
    return rec


def pose_shift_px(rec: pycolmap.Reconstruction, before: Sequence[Camera | None], files: list[str]) -> float:
    """How far ``rec``'s poses moved from ``before`` (per view, ``files`` order): the largest over the views
    registered in both of the median distance (px) between the model's points projected by the two."""
    if not rec.points3D:
        return 0.0
    points = np.stack([p.xyz for p in rec.points3D.values()])
    largest = 0.0
    for old, new in zip(before, _cameras_of(rec, files), strict=True):
        if old is None or new is None:
            continue
        uv_old, z_old = old.project(points)
        uv_new, z_new = new.project(points)
        front = (z_old > 0) & (z_new > 0)
        if front.any():
            largest = max(largest, float(np.median(np.linalg.norm(uv_new[front] - uv_old[front], axis=1))))
    return largest


def drop_short_tracks(rec: pycolmap.Reconstruction, min_views: int) -> int:
    """Delete the points observed in fewer than ``min_views`` views; returns how many.

    A view left with fewer than ``_MIN_LONG_TRACK_OBSERVATIONS`` observations of longer tracks
    keeps its short ones: a pose with a handful of observations is worse than one with some
    unchecked ones (the dragon's end-on views, registered by absolute pose).
    """
    if min_views <= 2:
        return 0
    long_obs: dict[int, int] = {}
    short = []
    for pid, point in rec.points3D.items():
        if point.track.length() < min_views:
            short.append(pid)
        else:
            for el in point.track.elements:
                long_obs[el.image_id] = long_obs.get(el.image_id, 0) + 1
    weak = {i for i in rec.reg_image_ids() if long_obs.get(i, 0) < _MIN_LONG_TRACK_OBSERVATIONS}
    removed = 0
    for pid in short:
        if not weak.intersection(el.image_id for el in rec.points3D[pid].track.elements):
            rec.delete_point3D(pid)
            removed += 1
    return removed


def _join_models(ranked: list[pycolmap.Reconstruction], run: _Workspace) -> pycolmap.Reconstruction:
    """The largest model joined with the others and completed by absolute poses (:mod:`.join`).

    First with every absolute pose of ``PNP_MIN_INLIERS`` or more inliers (:func:`_grow_and_join`);
    when that joins no two models, its poses had no second model to confirm them, and the
    largest model is completed again with only the poses that reach the mapper's own
    ``options.register_min_inliers``; a single model is completed so at once.
    """
    if len(ranked) > 1:  # (one model: nothing to join, no second model to confirm its poses)
        rec, joined = _grow_and_join(ranked, run, min_inliers=PNP_MIN_INLIERS)
        if joined:
            return rec
    return _grow_and_join(ranked[:1], run, min_inliers=run.options.register_min_inliers)[0]


def _grow_and_join(
    ranked: list[pycolmap.Reconstruction], run: _Workspace, *, min_inliers: int
) -> tuple[pycolmap.Reconstruction, bool]:
    """Passes of absolute poses and joining; the first model and whether another joined it.

    Each pass: every model registers the views it missed by PnP (at least ``min_inliers``
    inliers besides :func:`register_by_pnp`'s own tests); a model whose poses of two or more
    common views agree on a similarity with the first's moves into its frame and joins it; every
    model that gained views is matched again along its poses, triangulated and bundle-adjusted
    (:func:`_rematch_and_refine`), which gives the next pass more points. At most
    ``_JOIN_PASSES`` passes, fewer when one changes nothing.
    """
    files = run.files
    index = {name: i for i, name in enumerate(files)}
    models = list(ranked)
    rounds = 1  # see run_colmap: more rounds along joined poses add to their bend
    joined_any = False
    for _ in range(_JOIN_PASSES):
        db = pycolmap.Database.open(str(run.database))
        try:
            view_of_image = {im.image_id: index[im.name] for im in db.read_all_images()}
            db_cameras = {cam.camera_id: cam for cam in db.read_all_cameras()}
            posed = []
            for model in models:
                cameras = {i: c for i, c in enumerate(_cameras_of(model, files)) if c is not None}
                found = register_by_pnp(model, db, view_of_image, db_cameras)
                cameras.update({i: c for i, (c, n) in found.items() if n >= min_inliers})
                posed.append(cameras)
        finally:
            db.close()
        kept = [0]
        for k in range(1, len(models)):
            similarity = similarity_from_shared(posed[0], posed[k])
            if similarity is None:
                kept.append(k)
                continue
            joined_any = True
            for i, camera in posed[k].items():
                posed[0].setdefault(i, transform_camera(camera, *similarity))
        changed = False
        for k in kept:
            if len(posed[k]) > models[k].num_reg_images():
                changed = True
                poses = [posed[k].get(i) for i in range(len(files))]
                known = _known_pose_reconstruction(run.database, files, poses, models[k])
                models[k] = _rematch_and_refine(known, run, rounds, min_track=2, model=k, step="join_rematch")
        models = [models[k] for k in kept]
        if not changed:
            break
    return models[0], joined_any


