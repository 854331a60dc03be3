"""Joining SfM's disconnected models through the views both can register (``sfm.join_models``).

A capture whose views fall into groups that share too few verified matches (the dragon's two
sides, joined only by the views looking along its body) makes the mapper return one model per
group. Each model registers the views it missed with an absolute pose from its 3D points
(:func:`register_by_pnp`: the raw, unverified matches of the view with the model's views,
P3P LO-RANSAC with the intrinsics held, a tight reprojection threshold). Two models whose
poses of at least two common views agree on one similarity (:func:`similarity_from_shared`)
are joined: the second model's cameras move into the first's frame.
"""

from __future__ import annotations

import numpy as np
import pycolmap

from pmvir.camera import Camera

#: Absolute pose of a view missed by the mapper: RANSAC inlier threshold (pixels).
PNP_MAX_ERROR_PX = 4.0

#: Absolute pose: the fewest inlier 2D-3D correspondences accepted.
PNP_MIN_INLIERS = 7

#: Absolute pose: the smallest fraction of the correspondences that must be inliers.
PNP_MIN_INLIER_RATIO = 0.5

#: Joining: the common views' rotations must agree on the models' relative rotation within this (degrees).
JOIN_MAX_ROTATION_DEG = 5.0

#: Joining: the common views' centres must fit the similarity within this fraction of their spread.
JOIN_MAX_CENTRE_ERROR = 0.05


def register_by_pnp(
    rec: pycolmap.Reconstruction,
    database: pycolmap.Database,
    view_of_image: dict[int, int],
    cameras: dict[int, pycolmap.Camera],
) -> dict[int, tuple[Camera, int]]:
    """Absolute poses of the database's images that ``rec`` does not register.

    A feature of the view corresponds to the 3D point its raw matches with the registered
    views observe most often; the pose (intrinsics held) needs ``PNP_MIN_INLIERS`` inliers
    within ``PNP_MAX_ERROR_PX``, at least ``PNP_MIN_INLIER_RATIO`` of the correspondences.

    Args:
        rec: the model (its cameras' intrinsics are used where it holds the image's camera).
        database: the open database holding keypoints and raw matches.
        view_of_image: database image id -> view index.
        cameras: database camera id -> camera (used where ``rec`` lacks the camera).

    Returns:
        View index -> (Camera in ``rec``'s frame, number of inliers), for the views that passed.
    """
    registered = set(rec.reg_image_ids())
    posed: dict[int, tuple[Camera, int]] = {}
    for image in database.read_all_images():
        if image.image_id in registered:
            continue
        votes: dict[int, list[int]] = {}
        for other in registered:
            matches = database.read_matches(image.image_id, other)
            points2D = rec.images[other].points2D
            for mine, theirs in matches:
                point = points2D[int(theirs)]
                if point.has_point3D():
                    votes.setdefault(int(mine), []).append(point.point3D_id)
        if len(votes) < PNP_MIN_INLIERS:
            continue
        features = sorted(votes)
        xy = database.read_keypoints(image.image_id)[features, :2].astype(np.float64)
        xyz = np.array([rec.points3D[max(set(votes[f]), key=votes[f].count)].xyz for f in features])
        camera = rec.cameras[image.camera_id] if image.camera_id in rec.cameras else cameras[image.camera_id]
        estimation = pycolmap.AbsolutePoseEstimationOptions()
        estimation.ransac.max_error = PNP_MAX_ERROR_PX
        estimation.ransac.min_inlier_ratio = 0.1
        estimation.ransac.min_num_trials = 1000
        refinement = pycolmap.AbsolutePoseRefinementOptions()
        refinement.refine_focal_length = False
        refinement.refine_extra_params = False
        result = pycolmap.estimate_and_refine_absolute_pose(xy, xyz, camera, estimation, refinement)
        if result is None:
            continue
        inliers = int(result["num_inliers"])
        if inliers < PNP_MIN_INLIERS or inliers < PNP_MIN_INLIER_RATIO * len(features):
            continue
        pose = result["cam_from_world"]
        posed[view_of_image[image.image_id]] = (
            Camera(
                K=camera.calibration_matrix(),
                R=pose.rotation.matrix(),
                t=pose.translation,
                width=camera.width,
                height=camera.height,
            ),
            inliers,
        )
    return posed


def similarity_from_shared(
    base: dict[int, Camera], other: dict[int, Camera]
) -> tuple[float, np.ndarray, np.ndarray] | None:
    """The similarity ``x_base = s R x_other + t`` from the views posed in both, or None.

    Needs two or more common views whose rotations agree on R within ``JOIN_MAX_ROTATION_DEG``
    and whose centres fit within ``JOIN_MAX_CENTRE_ERROR`` of their spread.

    Returns:
        (s, R (3, 3), t (3,)) float64.
    """
    shared = sorted(set(base) & set(other))
    if len(shared) < 2:
        return None
    # cam_from_world: R_b (x_b - c_b) = R_o (x_o - c_o)  ->  x_b = R_b^T R_o x_o + ...
    rotations = [base[v].R.T @ other[v].R for v in shared]
    u, _, vt = np.linalg.svd(sum(rotations))
    R = u @ np.diag([1.0, 1.0, np.linalg.det(u @ vt)]) @ vt
    for Ri in rotations:
        cos = (np.trace(R.T @ Ri) - 1.0) / 2.0
        if np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))) > JOIN_MAX_ROTATION_DEG:
            return None
    cb = np.stack([base[v].center for v in shared])
    co = np.stack([other[v].center for v in shared]) @ R.T
    db, do = cb - cb.mean(axis=0), co - co.mean(axis=0)
    spread = float(np.linalg.norm(db, axis=1).max())
    if spread <= 0.0 or float((do * do).sum()) <= 0.0:
        return None
    s = float((db * do).sum() / (do * do).sum())
    if s <= 0.0:
        return None
    t = cb.mean(axis=0) - s * co.mean(axis=0)
    if float(np.linalg.norm(s * co + t - cb, axis=1).max()) > JOIN_MAX_CENTRE_ERROR * spread:
        return None
    return s, R, t


def transform_camera(camera: Camera, s: float, R: np.ndarray, t: np.ndarray) -> Camera:
    """The camera moved by ``x -> s R x + t`` (same intrinsics)."""
    R_new = camera.R @ R.T
    centre = s * R @ camera.center + t
    return Camera(K=camera.K, R=R_new, t=-R_new @ centre, width=camera.width, height=camera.height)
