"""SfM's features and matches in COLMAP's database (:mod:`pmvir.geometry.sfm.colmap` runs them).

* Features (:func:`extract_features`): SIFT per camera group (one extraction per known K, or per
  image size when the intrinsics are estimated), masks restricting where features are detected.
  With known poses and masks, SIFT runs on each view's crop to its mask's bounding box (grown by
  ``_CROP_MARGIN_PX``) and the keypoints are shifted back: 97 % of the features are found as on the
  whole view, in half the time where the object fills a third of the frame. SfM keeps whole views:
  the other 3 % are large features near a crop's edge, and SfM on the dragon, which hangs on them,
  estimated the focal length twice as far off (-0.9 to -1.0 % against -0.3 to -0.6 %).
* Matching, SfM (:func:`match_images`): exhaustive up to ``exhaustive_matching_max_views`` views,
  else sequential in capture order; RANSAC verification (COLMAP).
* Matching, known poses (:func:`match_known_poses`): epipolar-guided; every feature's candidates
  are the other view's features within ``_EPIPOLAR_MAX_ERROR_PX`` of its epipolar line, then
  Lowe's ratio test and mutual nearest neighbours; no RANSAC, so wide baselines with a handful of
  true matches still count. The band's candidates come from the features sorted by their angle
  about the epipole, and only they are compared: a view pair of 612x512 views of a textured table
  takes a quarter of the time the whole arrays of feature pairs took.
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np
import pycolmap
from threadpoolctl import threadpool_limits

from pmvir.camera import Camera
from pmvir.config import SfmOptions
from pmvir.errors import ReconstructionError
from pmvir.geometry.sfm.inputs import SCRATCH_PNG
from pmvir.threads import configured_threads, usable_threads

#: Known poses: a candidate match lies within this distance of the known epipolar line, both ways (px).
_EPIPOLAR_MAX_ERROR_PX = 2.0


#: Known poses: features within this many epipolar bands of the epipole are candidates of every line.
_NEAR_EPIPOLE = 16.0


#: Known poses: a view pair is used when at least this many matches fit its epipolar geometry.
KNOWN_POSE_MIN_MATCHES = 8


#: Known poses: Lowe's ratio test among the candidates in the epipolar band (COLMAP's global test: 0.8).
_KNOWN_POSE_MAX_RATIO = 0.8


#: Known poses: largest descriptor distance of a match (unit descriptors; COLMAP: 0.7).
_MAX_DESCRIPTOR_DISTANCE = 0.7


#: Known poses: view pairs whose optical axes differ by more than this are not matched (degrees).
_KNOWN_POSE_MAX_AXIS_DEG = 80.0


#: Features with known poses and masks: SIFT runs on the mask's bounding box grown by this many pixels
#: (of the SIFT image, before upsampling) on every side. Features found as on the whole view, dragon:
#: 94 % with 16 px, 97 % with 32, 98 % with 64, all with 128; extraction time 43, 51, 68 and 100 %.
_CROP_MARGIN_PX = 32


#: Features with known poses and masks: a crop's corner lies on a multiple of this many pixels, so
#: that SIFT's octaves (each half the resolution of the one before) sample the pixels they sample on
#: the whole view.
_CROP_ALIGN_PX = 16


#: Features with known poses and masks: views are cropped only when the crops hold less than this
#: fraction of the pixels.
_CROP_MAX_FRACTION = 0.8


def colmap_threads() -> int:
    """Threads for COLMAP's extraction, matching and mapping: ``OMP_NUM_THREADS`` when it holds a
    positive integer (the service sets it from ``PMVIR_JOB_THREADS``), else -1 (every core)."""
    configured = configured_threads()
    return -1 if configured is None else configured


def extract_features(
    database: Path,
    image_dir: Path,
    mask_dir: Path | None,
    files: list[str],
    sizes: list[tuple[int, int]],
    Ks: list[np.ndarray | None],
    options: SfmOptions,
    *,
    focal_priors: Sequence[float | None] | None = None,
    crop: bool = False,
) -> None:
    """SIFT into the database, one extraction per camera group (same K, or same size and focal prior
    when estimated: a prior is the estimated camera's starting focal length, refined by SfM);
    ``crop`` (with masks): on each view's crop around its mask (module docstring)."""
    groups: dict[tuple, list[int]] = {}
    for i, (K, (h, w)) in enumerate(zip(Ks, sizes, strict=True)):
        prior = None if focal_priors is None else focal_priors[i]
        if K is not None:
            key: tuple = ("known", w, h, K[0, 0], K[1, 1], K[0, 2], K[1, 2])
        elif options.shared_intrinsics:
            key = ("estimated", w, h, prior)
        else:
            key = ("estimated", w, h, prior, i)
        groups.setdefault(key, []).append(i)
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = colmap_threads()
    extraction.sift.max_num_features = options.sift_max_features
    extraction.sift.peak_threshold = options.sift_peak_threshold
    extraction.sift.estimate_affine_shape = options.sift_affine_shape
    extraction.sift.first_octave = 0 if options.sift_upsample is False else -1  # 'auto' is resolved by SfM
    masks = None if mask_dir is None or not crop else [_read_png(mask_dir / f"{name}.png") for name in files]
    boxes = None if masks is None else _crop_boxes(masks)
    # COLMAP numbers images in the order its extraction threads finish them, which varies from run
    # to run; the matching and the mapper visit views in image-id order, so importing the images
    # first (one thread, group by group, in the views' order) makes SfM and the known-pose matches
    # repeatable.
    pycolmap.Database.open(str(database)).close()  # import_images needs the file
    for key, members in groups.items():
        reader = pycolmap.ImageReaderOptions()
        if mask_dir is not None:
            reader.mask_path = str(mask_dir)
        if key[0] == "known":
            reader.camera_model = "PINHOLE"
            reader.camera_params = ",".join(repr(float(v)) for v in key[3:])
        else:
            reader.camera_model = "SIMPLE_PINHOLE"
            if key[3] is not None:  # has_prior_focal_length: the mapper starts from it and refines it
                reader.camera_params = f"{float(key[3])!r},{key[1] / 2.0!r},{key[2] / 2.0!r}"
        names = [files[i] for i in members]
        pycolmap.import_images(
            database, image_dir, camera_mode=pycolmap.CameraMode.SINGLE, image_names=names, options=reader
        )
        if boxes is None:
            pycolmap.extract_features(
                database,
                image_dir,
                image_names=names,
                camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader,
                extraction_options=extraction,
            )
    if boxes is not None and masks is not None:
        _extract_cropped(database, image_dir, masks, files, boxes, extraction)


def _crop_boxes(masks: list[np.ndarray]) -> list[tuple[int, int, int, int]] | None:
    """Per view the box (x0, y0, x1, y1) SIFT runs on: its mask's bounding box grown by
    ``_CROP_MARGIN_PX`` (the corner moved out onto a multiple of ``_CROP_ALIGN_PX``); None when the
    boxes hold ``_CROP_MAX_FRACTION`` of the pixels or more."""
    boxes, inside, total = [], 0, 0
    for mask in masks:
        h, w = mask.shape
        rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
        if not len(rows):  # no features in this view: a small crop SIFT still reads
            rows, cols = np.array([0]), np.array([0])
        x0, y0 = (max(int(v) - _CROP_MARGIN_PX, 0) // _CROP_ALIGN_PX * _CROP_ALIGN_PX
                  for v in (cols[0], rows[0]))
        x1, y1 = min(int(cols[-1]) + 1 + _CROP_MARGIN_PX, w), min(int(rows[-1]) + 1 + _CROP_MARGIN_PX, h)
        boxes.append((x0, y0, x1, y1))
        inside += (x1 - x0) * (y1 - y0)
        total += w * h
    return boxes if inside < _CROP_MAX_FRACTION * total else None


def _read_png(path: Path) -> np.ndarray:
    """An 8-bit grey image SfM wrote (SIFT image or mask)."""
    image = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    if image is None:
        raise ReconstructionError(f"{path}: SfM's scratch image could not be read back (disk full?)")
    return image


def _extract_cropped(
    database: Path,
    image_dir: Path,
    masks: list[np.ndarray],
    files: list[str],
    boxes: list[tuple[int, int, int, int]],
    extraction: pycolmap.FeatureExtractionOptions,
) -> None:
    """SIFT on each view's crop (``boxes``; ``masks``: per view its COLMAP mask, 0 = no features), into
    a scratch database beside ``database`` (removed afterwards, also on failure); the keypoints
    shifted back to the full view and written with the descriptors for the views already imported
    into ``database``."""
    crop_dir = database.parent / "crops"
    shutil.rmtree(crop_dir, ignore_errors=True)
    (crop_dir / "masks").mkdir(parents=True)
    try:
        for name, mask, (x0, y0, x1, y1) in zip(files, masks, boxes, strict=True):
            image = _read_png(image_dir / name)
            cv2.imwrite(str(crop_dir / name), image[y0:y1, x0:x1], SCRATCH_PNG)
            cv2.imwrite(str(crop_dir / "masks" / f"{name}.png"), mask[y0:y1, x0:x1], SCRATCH_PNG)
        scratch = crop_dir / "database.db"
        reader = pycolmap.ImageReaderOptions()
        reader.mask_path = str(crop_dir / "masks")
        pycolmap.extract_features(
            scratch, crop_dir, image_names=files, camera_mode=pycolmap.CameraMode.PER_IMAGE,
            reader_options=reader, extraction_options=extraction,
        )
        offset = {name: box[:2] for name, box in zip(files, boxes, strict=True)}
        source, target = pycolmap.Database.open(str(scratch)), pycolmap.Database.open(str(database))
        try:
            ids = {image.name: image.image_id for image in target.read_all_images()}
            for view in source.read_all_images():
                keypoints = np.array(source.read_keypoints(view.image_id), dtype=np.float32)
                keypoints[:, :2] += np.asarray(offset[view.name], dtype=np.float32)  # shape columns stay
                target.write_keypoints(ids[view.name], keypoints)
                target.write_descriptors(ids[view.name], source.read_descriptors(view.image_id))
        finally:
            source.close()
            target.close()
    finally:
        shutil.rmtree(crop_dir, ignore_errors=True)


def match_images(database: Path, n: int, options: SfmOptions) -> None:
    """SIFT matching (exhaustive or sequential, module docstring) with RANSAC verification."""
    verification = pycolmap.TwoViewGeometryOptions()
    verification.ransac.random_seed = options.seed
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = colmap_threads()
    matching.guided_matching = options.guided_matching
    matching.sift.max_ratio = options.match_max_ratio
    if n <= options.exhaustive_matching_max_views:
        pycolmap.match_exhaustive(database, matching_options=matching, verification_options=verification)
    else:
        pairing = pycolmap.SequentialPairingOptions()
        pairing.overlap = options.sequential_matching_overlap
        pairing.quadratic_overlap = True
        pycolmap.match_sequential(
            database, matching_options=matching, pairing_options=pairing, verification_options=verification
        )


def match_known_poses(database: Path, files: list[str], cameras: Sequence[Camera | None]) -> None:
    """Epipolar-guided matching with the known poses (replaces COLMAP's matching and RANSAC).

    For every pair of views whose optical axes differ by at most ``_KNOWN_POSE_MAX_AXIS_DEG``,
    a feature's candidates are the features of the other view within ``_EPIPOLAR_MAX_ERROR_PX``
    of its epipolar line (both ways); among them the nearest descriptor must pass Lowe's ratio
    test against the second nearest candidate and be nearest both ways. Restricting the
    search to the epipolar band keeps matches that a global ratio test loses between views
    30-70 degrees apart. The matches are written as CALIBRATED two-view geometries, pair by pair in
    view order. The pairs are matched on :func:`~pmvir.threads.usable_threads` threads (NumPy releases
    the interpreter for the sorting and indexing that take the time: 1.9x faster on 2 cores), and BLAS
    runs on one thread in each: a pair's products are small (hundreds of features), and BLAS's own
    threads would compete with the pool's.
    """
    index = {name: i for i, name in enumerate(files)}
    db = pycolmap.Database.open(str(database))
    one_thread = threadpool_limits(1, user_api="blas")
    try:
        view = {im.image_id: index[im.name] for im in db.read_all_images()}
        posed: dict[int, Camera] = {k: c for k, i in view.items() if (c := cameras[i]) is not None}
        ids = sorted(posed)
        xy = {k: db.read_keypoints(k)[:, :2].astype(np.float64) for k in ids}
        desc = {}
        for k in ids:
            d = db.read_descriptors(k).data.astype(np.float32)
            desc[k] = d / np.maximum(np.linalg.norm(d, axis=1, keepdims=True), 1e-12)
        axes = {k: posed[k].R[2] for k in ids}
        min_cos = math.cos(math.radians(_KNOWN_POSE_MAX_AXIS_DEG))
        pairs = [
            (id1, id2, fundamental_matrix(posed[id1], posed[id2]))
            for a_pos, id1 in enumerate(ids) for id2 in ids[a_pos + 1:]
            if float(axes[id1] @ axes[id2]) >= min_cos and len(xy[id1]) and len(xy[id2])
        ]

        def match(pair: tuple[int, int, np.ndarray]) -> np.ndarray:
            id1, id2, F = pair
            return _guided_matches(xy[id1], xy[id2], desc[id1], desc[id2], F)

        with ThreadPoolExecutor(max_workers=usable_threads()) as pool:
            for (id1, id2, F), m in zip(pairs, pool.map(match, pairs), strict=True):
                if len(m) < KNOWN_POSE_MIN_MATCHES:
                    continue
                db.write_matches(id1, id2, m)
                geometry = pycolmap.TwoViewGeometry()
                geometry.config = pycolmap.TwoViewGeometryConfiguration.CALIBRATED
                geometry.F = F
                geometry.inlier_matches = m
                db.write_two_view_geometry(id1, id2, geometry)
    finally:
        one_thread.restore_original_limits()
        db.close()


def _guided_matches(
    x1: np.ndarray, x2: np.ndarray, d1: np.ndarray, d2: np.ndarray, F: np.ndarray
) -> np.ndarray:
    """Mutual nearest descriptors within the epipolar band, ratio-tested; (M, 2) uint32 indices.

    The band's pairs are found first (:func:`_band_pairs`), and the descriptors compared on them
    alone: on 612x512 views of a textured table (4,000-6,000 features each) the band holds 0.5 %
    of the pairs, and the whole (N1, N2) arrays took 0.24 s a view pair.

    Args:
        x1, x2: (N1, 2), (N2, 2) keypoint pixel coordinates.
        d1, d2: (N1, 128), (N2, 128) float32 unit descriptors.
        F: (3, 3) fundamental matrix, ``x2^T F x1 = 0``.
    """
    none = np.zeros((0, 2), np.uint32)
    if len(x1) < 2 or len(x2) < 2:
        return none
    rows, cols = _band_pairs(x1, x2, F)
    if not len(rows):
        return none
    # Unit descriptors: distance^2 = 2 - 2 cos. The ratio test compares the nearest candidate in
    # the band with the second nearest in the band, or (a lone candidate) with the nearest
    # other feature anywhere in view 2.
    cos = np.einsum("ij,ij->i", d1[rows], d2[cols])
    order = np.lexsort((-cos, rows))  # by row, nearest first
    rows, cols, cos = rows[order], cols[order], cos[order]
    first = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    lone = np.r_[first[1:], len(rows)] - first == 1
    i, best2, top = rows[first], cols[first], cos[first]
    by_col = np.lexsort((-cos, cols))  # by column, nearest first
    col_first = by_col[np.r_[True, cols[by_col][1:] != cols[by_col][:-1]]]
    nearest_row = np.full(len(x2), -1, np.int64)
    nearest_row[cols[col_first]] = rows[col_first]
    top_dist = np.sqrt(np.maximum(2.0 - 2.0 * top, 0.0))
    ok = (nearest_row[best2] == i) & (top_dist < _MAX_DESCRIPTOR_DISTANCE)  # mutual nearest, near enough
    second = np.full_like(top, -2.0)
    second[~lone] = cos[first[~lone] + 1]
    outside = np.flatnonzero(lone & ok)  # a lone candidate's ratio test looks at the whole view
    if len(outside):
        full = d1[i[outside]] @ d2.T
        full[np.arange(len(full)), best2[outside]] = -2.0
        second[outside] = full.max(axis=1)
    ok &= top_dist < _KNOWN_POSE_MAX_RATIO * np.sqrt(np.maximum(2.0 - 2.0 * second, 0.0))
    return np.stack([i[ok], best2[ok]], axis=1).astype(np.uint32)


def _band_pairs(x1: np.ndarray, x2: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K,) int64 row and column indices of the feature pairs within ``_EPIPOLAR_MAX_ERROR_PX`` of
    each other's epipolar lines, both ways.

    Every epipolar line in view 2 passes through the epipole: a feature at distance r from it lies
    within the band of a line when their angles about the epipole differ by at most asin(band / r).
    The features are sorted by that angle (modulo 180 deg) and each line takes those within the
    angle the band spans at the nearest feature's r (features within ``_NEAR_EPIPOLE`` bands of the
    epipole are candidates of every line);
    with the epipole at infinity the lines are parallel and the features are sorted by their offset
    along the lines' normal. The candidates are then checked exactly, in both views.
    """
    band = _EPIPOLAR_MAX_ERROR_PX
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1)
    l2 = h1 @ F.T  # epipolar lines in view 2 of the view-1 features, (N1, 3)
    l1 = h2 @ F  # epipolar lines in view 1 of the view-2 features, (N2, 3)
    l2 /= np.maximum(np.hypot(l2[:, :1], l2[:, 1:2]), 1e-12)
    l1 /= np.maximum(np.hypot(l1[:, :1], l1[:, 1:2]), 1e-12)
    epipole = np.linalg.svd(F)[0][:, 2]  # F^T e2 = 0
    near = np.zeros(len(x2), bool)
    if abs(epipole[2]) > 1e-12 * np.linalg.norm(epipole[:2]):
        offset = x2 - epipole[:2] / epipole[2]
        r = np.hypot(offset[:, 0], offset[:, 1])
        near = r < _NEAR_EPIPOLE * band
        key = np.mod(np.arctan2(offset[:, 1], offset[:, 0]), np.pi)
        at = np.mod(np.arctan2(-l2[:, 0], l2[:, 1]), np.pi)
        half = float(np.arcsin(min(1.0, band / float(r[~near].min(initial=np.inf)))))
        period = np.pi
        if half >= 0.5 * np.pi - 1e-9:  # a span as wide as the period: every feature a candidate
            near[:] = True
    else:  # parallel lines: their common normal, each line's offset along it
        normal = l2[int(np.argmax(np.abs(l2[:, :2]).sum(axis=1))), :2]
        key = x2 @ normal
        at = -l2[:, 2] * np.sign(l2[:, :2] @ normal)
        half, period = band * (1.0 + 1e-6), 0.0
    far = np.flatnonzero(~near)
    order = far[np.argsort(key[far], kind="stable")]
    sorted_key = key[order]
    spans = [(at - half, at + half)]
    if period:  # the angle wraps around at 0 and 180 deg
        spans += [(at - half + period, at + half + period), (at - half - period, at + half - period)]
    rows_parts, cols_parts = [], []
    for lo, hi in spans:
        start, stop = np.searchsorted(sorted_key, lo), np.searchsorted(sorted_key, hi, side="right")
        count = np.maximum(stop - start, 0)
        rows_parts.append(np.repeat(np.arange(len(x1)), count))
        cols_parts.append(order[np.repeat(start, count) + _ranks(count)])
    nearest = np.flatnonzero(near)
    rows_parts.append(np.repeat(np.arange(len(x1)), len(nearest)))
    cols_parts.append(np.tile(nearest, len(x1)))
    rows, cols = np.concatenate(rows_parts), np.concatenate(cols_parts)  # no pair twice: spans < period
    ok = np.abs(np.einsum("ij,ij->i", l2[rows], h2[cols])) < band
    ok &= np.abs(np.einsum("ij,ij->i", h1[rows], l1[cols])) < band
    return rows[ok], cols[ok]


def _ranks(count: np.ndarray) -> np.ndarray:
    """0, 1, ..., count[0] - 1, 0, 1, ..., count[1] - 1, ...: each run's position within it."""
    total = int(count.sum())
    if not total:
        return np.zeros(0, np.int64)
    starts = np.cumsum(count) - count
    return np.arange(total) - np.repeat(starts, count)


def fundamental_matrix(camera1: Camera, camera2: Camera) -> np.ndarray:
    """F with ``x2^T F x1 = 0`` for pixel coordinates (u, v, 1) of one point in two views, (3, 3)."""
    R = camera2.R @ camera1.R.T
    t = camera2.t - R @ camera1.t
    tx = np.array([[0.0, -t[2], t[1]], [t[2], 0.0, -t[0]], [-t[1], t[0], 0.0]])
    return np.linalg.inv(camera2.K).T @ tx @ R @ np.linalg.inv(camera1.K)


def sampson_error(x1: np.ndarray, x2: np.ndarray, F: np.ndarray) -> np.ndarray:
    """Squared Sampson distances (pixels^2) of (M, 2) pixel correspondences to F, (M,) float64."""
    h1 = np.concatenate([x1, np.ones((len(x1), 1))], axis=1)
    h2 = np.concatenate([x2, np.ones((len(x2), 1))], axis=1)
    Fx1 = h1 @ F.T
    Ftx2 = h2 @ F
    num = np.einsum("ij,ij->i", h2, Fx1) ** 2
    den = Fx1[:, 0] ** 2 + Fx1[:, 1] ** 2 + Ftx2[:, 0] ** 2 + Ftx2[:, 1] ** 2
    return num / np.maximum(den, 1e-30)


def database_stats(database: Path, files: list[str]) -> tuple[list[int], list[int]]:
    """Per view: SIFT features, and the number of other views it has verified matches with."""
    index = {name: i for i, name in enumerate(files)}
    features, partners = [0] * len(files), [0] * len(files)
    db = pycolmap.Database.open(str(database))
    try:
        by_id = {}
        for im in db.read_all_images():
            by_id[im.image_id] = index[im.name]
            features[index[im.name]] = db.num_keypoints_for_image(im.image_id)
        pair_ids, counts = db.read_two_view_geometry_num_inliers()
        for pair_id, count in zip(pair_ids, counts, strict=True):
            if count > 0:
                a, b = pycolmap.pair_id_to_image_pair(pair_id)
                partners[by_id[a]] += 1
                partners[by_id[b]] += 1
    finally:
        db.close()
    return features, partners
