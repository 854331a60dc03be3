"""Views SfM left out, registered from their silhouettes: a pose search scored by frontier residuals.

Where SfM leaves views out and the views have masks, :func:`register_from_silhouettes` looks for
each missing view's pose among camera directions (a Fibonacci sphere), distances and rolls around
the object, scores the candidates by the frontier residuals of the view's silhouette against the
registered views' masks (:mod:`pmvir.geometry.sfm.frontier`), polishes the best basins by
Levenberg-Marquardt, and registers a pose only where no distinct pose fits the silhouette about as
well (a symmetric object shows the same silhouette from several poses). Used by
:func:`pmvir.geometry.sfm.estimate_poses` (``sfm.silhouette_register_px``).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import pycolmap
from scipy.spatial.transform import Rotation

from pmvir.geometry.sfm.frontier import FRONTIER_SCALE_PX, MAX_ANGLE, MAX_SPAN, _contour_rays

#: The search for a view's pose from its silhouette: camera directions (a Fibonacci sphere),
#: distances from the object (times the registered cameras' median), rolls about the aim; the
#: best candidate of each of the best ``SEARCH_POLISHED`` directions is screened by a short polish
#: (``SCREEN_ITERATIONS`` Levenberg-Marquardt steps, all candidates at once) and the best of
#: ``SEARCH_FINALS`` distinct basins polished in full (``FINAL_ITERATIONS``).
SEARCH_DIRECTIONS = 300
SEARCH_DISTANCES = (0.85, 1.0, 1.15)
SEARCH_ROLLS = 24
SEARCH_POLISHED = 200
SCREEN_ITERATIONS = 15
SEARCH_FINALS = 5
FINAL_ITERATIONS = 100
#: Two polished poses are distinct basins when their rotations differ by more than ``DISTINCT_DEG``
#: or their centres by more than ``DISTINCT_DISTANCE`` of the distance to the object (screened
#: poses, only partly polished, by 3 times that). A silhouette that a distinct pose fits about as
#: well (RMS below ``AMBIGUITY_RATIO`` times the best's plus ``AMBIGUITY_MARGIN_PX``) is ambiguous
#: and not registered: a symmetric object (the built-in torus knot, D3) shows the same silhouette
#: from several poses, and the search picked a wrong one for 19 of the 20 views SfM left out, each
#: fitting its mask within 1.2 px (camera centres 18-67% of the rig off). This check refused 16 of
#: them; the other 4 had no rival among the finals, hence also ``sfm.silhouette_min_registered``
#: (:mod:`pmvir.geometry.sfm.poses`). Without symmetry the next basin fits far worse (the dragon's four
#: views: 0.22-0.32 px, their rivals 3.4-6.3 px).
DISTINCT_DEG = 5.0
DISTINCT_DISTANCE = 0.05
AMBIGUITY_RATIO = 2.0
AMBIGUITY_MARGIN_PX = 0.2


@dataclass(frozen=True)
class SilhouetteRegistration:
    """A view's silhouette search: its name, the RMS frontier residual (px) of the best pose
    against the registered views' masks, the number of pairs that residual is over, the RMS of the
    best pose distinct from it (``rival_px``: another basin; inf when none was found), and whether
    the pose was registered (``reason`` says why not)."""

    name: str
    rms_px: float
    pairs: int
    rival_px: float = float("inf")
    registered: bool = True
    reason: str = ""


def register_from_silhouettes(
    rec: pycolmap.Reconstruction,
    masks: dict[str, np.ndarray],
    intrinsics: dict[str, np.ndarray],
    *,
    max_rms_px: float,
    min_pairs: int = 10,
) -> list[SilhouetteRegistration]:
    """Register the views SfM left out (``intrinsics``' names not registered in ``rec``) by their masks.

    For each, cameras on a sphere around the sparse points' median (at the registered cameras'
    median distance, and 15% nearer and farther) aim the mask's centroid at it with 24 rolls;
    the best candidate of each of the 200 directions whose frontier residuals against the
    registered views are lowest is polished briefly (robust least squares over the view's pose
    alone), the best of 5 distinct basins in full, and the best is kept when its RMS residual is at
    most ``max_rms_px`` over at least ``min_pairs`` pairs and no distinct pose fits about as well
    (``AMBIGUITY_RATIO``, ``AMBIGUITY_MARGIN_PX``: a symmetric object). On the dragon the right
    poses polished to 0.22-0.32 px and the best distinct basins to 3.4-6.3 px. The views are
    added to ``rec`` (no keypoints; :func:`frontier_adjust` then adjusts them with the others).

    Assumes the cameras look at the object from roughly the distance of the registered ones, as
    on any rig that frames the object; the masks must hold the whole object.

    Returns:
        One entry per view searched, registered or not (``reason`` says why not).
    """
    names = {rec.images[i].name: i for i in rec.reg_image_ids()}
    if len(names) < 3 or rec.num_points3D() == 0:
        return []
    reg = sorted(n for n in names if n in masks and masks[n].any())
    if len(reg) < min_pairs:
        return []
    centre = np.median(np.stack([p.xyz for p in rec.points3D.values()]), axis=0)
    Rr = np.stack([rec.images[names[n]].cam_from_world().rotation.matrix() for n in reg])
    Cr = np.stack([rec.images[names[n]].projection_center() for n in reg])
    hulls = _padded([
        _contour_rays(masks[n], rec.cameras[rec.images[names[n]].camera_id].calibration_matrix())[0] @ Rr[k]
        for k, n in enumerate(reg)
    ])  # world directions
    distance = float(np.median(np.linalg.norm(Cr - centre, axis=1)))
    out = []
    for name in sorted(intrinsics):
        if name in names or name not in masks or not masks[name].any():
            continue
        K = np.asarray(intrinsics[name], dtype=np.float64)
        found = _search_pose(masks[name], K, centre, distance, Cr, hulls, min_pairs)
        if found is None:
            out.append(SilhouetteRegistration(name, float("inf"), 0, registered=False,
                                              reason=f"no pose sees {min_pairs} registered views' frontier points"))
            continue
        rms, npairs, R, C, rival = found
        entry = SilhouetteRegistration(name=name, rms_px=float(rms), pairs=int(npairs), rival_px=float(rival))
        if rms > max_rms_px:
            entry = replace(entry, registered=False, reason=f"best pose fits within {rms:.2f} px > {max_rms_px:g} px")
        elif rival <= AMBIGUITY_RATIO * rms + AMBIGUITY_MARGIN_PX:
            entry = replace(entry, registered=False,
                            reason=f"ambiguous: a distinct pose fits within {rival:.2f} px (best {rms:.2f} px)")
        else:
            _add_view(rec, name, K, masks[name].shape, R, C)
        out.append(entry)
    return out


def _padded(hulls: list[np.ndarray]) -> np.ndarray:
    """The registered views' hull rays as one (J, M, 3) array, each padded with copies of its first
    ray (a repeated ray leaves a view's extreme angles as they are)."""
    m = max(len(h) for h in hulls)
    return np.stack([np.concatenate([h, np.repeat(h[:1], m - len(h), axis=0)]) for h in hulls])


def _pair_frames(
    C: np.ndarray, centre: np.ndarray, Cr: np.ndarray, hulls: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The epipolar frames of B cameras at C (B, 3) paired with the registered cameras at Cr (J, 3):
    per pair (B, J) the sine of the angle at C between the baseline and the object's centre, two unit
    axes (B, J, 3) normal to the baseline (a1 towards the centre, a2 = b x a1), and the highest and
    lowest angle about the baseline of the registered view's hull rays ``hulls`` (J, M, 3)."""
    b = Cr[None] - C[:, None]
    b /= np.linalg.norm(b, axis=2, keepdims=True)
    to_centre = centre - C
    a1 = to_centre[:, None] - np.einsum("bji,bi->bj", b, to_centre)[:, :, None] * b
    sin = np.linalg.norm(a1, axis=2) / np.linalg.norm(to_centre, axis=1)[:, None]
    a1 /= np.linalg.norm(a1, axis=2, keepdims=True)
    a2 = np.cross(b, a1)
    pj = np.arctan2(hulls @ a2.transpose(1, 2, 0), hulls @ a1.transpose(1, 2, 0))  # (J, M, B)
    return sin, a1, a2, pj.max(axis=1).T, pj.min(axis=1).T


def _frontier_residuals(
    R: np.ndarray, C: np.ndarray, hull: np.ndarray, centre: np.ndarray, Cr: np.ndarray, hulls: np.ndarray,
    f: float, keep: np.ndarray | None, frames: tuple[np.ndarray, ...] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The frontier residuals (px) of B poses of a view (R (B, 3, 3) world -> camera, C (B, 3); its
    hull rays ``hull``) against the registered views (``hulls``: their padded (J, M, 3) world hull
    rays, :func:`_padded`): (B, 2 J), the high and low extremes of each pair in turn, 0 for pairs not
    kept; and the (B, J) pairs kept (``keep``; None: those with frontier points at these poses).
    ``frames``: :func:`_pair_frames` at C when known."""
    sin, a1, a2, pj_hi, pj_lo = _pair_frames(C, centre, Cr, hulls) if frames is None else frames
    d = hull @ R  # (B, M', 3) world directions of the view's hull rays
    pv = np.arctan2(d @ a2.transpose(0, 2, 1), d @ a1.transpose(0, 2, 1))  # (B, M', J)
    pv_hi, pv_lo = pv.max(axis=1), pv.min(axis=1)
    if keep is None:
        reach = np.maximum(np.maximum(np.abs(pv_hi), np.abs(pv_lo)), np.maximum(np.abs(pj_hi), np.abs(pj_lo)))
        keep = (reach < MAX_ANGLE) & (np.maximum(pv_hi - pv_lo, pj_hi - pj_lo) < MAX_SPAN)
    scale = np.where(keep, f * sin, 0.0)
    return np.stack([scale * (pv_hi - pj_hi), scale * (pv_lo - pj_lo)], axis=2).reshape(len(R), -1), keep


def _polish(
    R0: np.ndarray, C0: np.ndarray, hull: np.ndarray, centre: np.ndarray, Cr: np.ndarray, hulls: np.ndarray,
    f: float, distance: float, iterations: int,
) -> list[tuple[float, int, np.ndarray, np.ndarray]]:
    """B candidate poses of a view (R0 (B, 3, 3) world -> camera, C0 (B, 3)) polished together:
    ``iterations`` Levenberg-Marquardt steps over each pose alone on its frontier residuals over the
    pairs it has at its start, Huber-weighted (``FRONTIER_SCALE_PX``), forward-difference Jacobians.
    Returns per candidate (RMS px, pairs, R, C); a candidate without pairs keeps its pose, RMS inf."""
    n = len(R0)
    r, keep = _frontier_residuals(R0, C0, hull, centre, Cr, hulls, f, None)
    pairs = keep.sum(axis=1)

    def pose(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return R0 @ Rotation.from_rotvec(x[:, :3]).as_matrix(), C0 + x[:, 3:] * distance

    def cost(r: np.ndarray) -> np.ndarray:  # the Huber cost: sum of rho(r^2 / s^2) s^2 / 2, as scipy's
        a = np.abs(r) / FRONTIER_SCALE_PX
        return 0.5 * FRONTIER_SCALE_PX**2 * np.where(a <= 1, a * a, 2 * a - 1).sum(axis=1)

    x, c = np.zeros((n, 6)), cost(r)
    damping = np.full(n, 1e-3)
    step = np.sqrt(np.finfo(np.float64).eps)
    eye = np.eye(6)
    for _ in range(iterations):
        frames = _pair_frames(pose(x)[1], centre, Cr, hulls)  # the rotations' derivatives keep C
        jac = np.stack(
            [(_frontier_residuals(*pose(x + step * eye[k]), hull, centre, Cr, hulls, f, keep,
                                  frames if k < 3 else None)[0] - r) / step
             for k in range(6)], axis=2,
        )  # (B, 2 J, 6)
        w = np.minimum(1.0, FRONTIER_SCALE_PX / np.maximum(np.abs(r), 1e-12))  # the Huber loss's IRLS weights
        jtj = np.einsum("bnk,bn,bnl->bkl", jac, w, jac)
        jtr = np.einsum("bnk,bn,bn->bk", jac, w, r)
        lhs = jtj + damping[:, None, None] * (np.einsum("bkk->bk", jtj)[:, :, None] + 1e-12) * eye
        x_new = x - np.linalg.solve(lhs, jtr[:, :, None])[:, :, 0]
        r_new = _frontier_residuals(*pose(x_new), hull, centre, Cr, hulls, f, keep)[0]
        c_new = cost(r_new)
        better = c_new < c
        # converged: a step lowered the cost by less than 1e-9 of it, or none lowers it however short
        done = (better & (c - c_new <= 1e-9 * c)) | (~better & (damping > 1e6))
        x[better], r[better], c[better] = x_new[better], r_new[better], c_new[better]
        damping = np.where(better, damping / 3, damping * 4)
        if done.all():
            break
    rms = np.where(pairs > 0, np.sqrt((r**2).sum(axis=1) / np.maximum(2 * pairs, 1)), np.inf)
    R, C = pose(x)
    return [(float(rms[i]), int(pairs[i]), R[i], C[i]) for i in range(n)]


def _search_pose(
    mask: np.ndarray, K: np.ndarray, centre: np.ndarray, distance: float, Cr: np.ndarray,
    hulls: np.ndarray, min_pairs: int,
) -> tuple[float, int, np.ndarray, np.ndarray, float] | None:
    """(RMS px, pairs, R, C) of the best polished candidate pose for a mask and the RMS of the best
    polished pose in another basin (inf when none), or None."""
    hull = _contour_rays(mask, K)[0]
    ys, xs = np.nonzero(mask)
    aim = np.linalg.solve(K, np.array([xs.mean() + 0.5, ys.mean() + 0.5, 1.0]))
    aim /= np.linalg.norm(aim)
    f = float(K[0, 0])
    i = np.arange(SEARCH_DIRECTIONS) + 0.5
    polar, azimuth = np.arccos(1 - 2 * i / SEARCH_DIRECTIONS), np.pi * (1 + 5**0.5) * i
    directions = np.stack([np.cos(azimuth) * np.sin(polar), np.sin(azimuth) * np.sin(polar), np.cos(polar)], 1)
    candidates = []
    rolls = np.linspace(0, 2 * np.pi, SEARCH_ROLLS, endpoint=False)
    for d_index, direction in enumerate(directions):
        u = -direction
        # the rotation taking the camera's aim ray to u, then rolls about u (camera -> world)
        v = np.cross(aim, u)
        vx = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        to_u = np.eye(3) + vx + vx @ vx / (1 + aim @ u)
        rotations = (Rotation.from_rotvec(rolls[:, None] * u).as_matrix() @ to_u).transpose(0, 2, 1)  # world -> camera
        for scale in SEARCH_DISTANCES:
            C = np.repeat((centre + direction * distance * scale)[None], SEARCH_ROLLS, axis=0)
            # the rolls share a centre, so its pair frames are computed once
            frames = tuple(np.repeat(a, SEARCH_ROLLS, axis=0) for a in _pair_frames(C[:1], centre, Cr, hulls))
            r, ok = _frontier_residuals(rotations, C, hull, centre, Cr, hulls, f, None, frames)
            count = ok.sum(axis=1)
            rms = np.sqrt((r**2).sum(axis=1) / np.maximum(2 * count, 1))
            for k in np.nonzero(count >= min_pairs)[0]:
                candidates.append((float(rms[k]), rotations[k], C[0], d_index))
    # The best candidate of each direction, best first, screened by a short polish and the best
    # few polished in full: a candidate 7 degrees from the right pose can rank below wrong basins
    # (the dragon's view 23: its right pose polishes to 0.24 px from 15 degrees and 10% off, but
    # all of the 40 best candidates overall polished to 3.97 px).
    candidates.sort(key=lambda c: c[0])
    seen: set[int] = set()
    distinct = []
    for c in candidates:
        if c[3] not in seen:
            seen.add(c[3])
            distinct.append(c)

    def polish(
        poses: list[tuple[float, np.ndarray, np.ndarray]], iterations: int
    ) -> list[tuple[float, int, np.ndarray, np.ndarray]]:
        if not poses:
            return []
        R0, C0 = np.stack([p[-2] for p in poses]), np.stack([p[-1] for p in poses])
        return sorted(_polish(R0, C0, hull, centre, Cr, hulls, f, distance, iterations), key=lambda c: c[0])

    def same_basin(
        a: tuple[float, int, np.ndarray, np.ndarray], b: tuple[float, int, np.ndarray, np.ndarray], widen: float = 1.0
    ) -> bool:
        cos = np.clip((np.trace(a[2] @ b[2].T) - 1) / 2, -1.0, 1.0)
        return bool(
            np.degrees(np.arccos(cos)) <= widen * DISTINCT_DEG
            and np.linalg.norm(a[3] - b[3]) <= widen * DISTINCT_DISTANCE * distance
        )

    screened = polish([c[:3] for c in distinct[:SEARCH_POLISHED]], SCREEN_ITERATIONS)
    # the finals: the best screened pose of each of the first SEARCH_FINALS distinct basins (a
    # basin's neighbours screen alike and would crowd out a rival)
    starts: list[tuple[float, int, np.ndarray, np.ndarray]] = []
    for pose in screened:
        if len(starts) == SEARCH_FINALS:
            break
        if not any(same_basin(pose, s, widen=3.0) for s in starts):
            starts.append(pose)
    finals = polish([(rms, R, C) for rms, _, R, C in starts], FINAL_ITERATIONS)
    if not finals:
        return None
    best = finals[0]
    rival = min((other[0] for other in finals[1:] if not same_basin(other, best)), default=float("inf"))
    return best[0], best[1], best[2], best[3], rival


def _add_view(rec: pycolmap.Reconstruction, name: str, K: np.ndarray, shape: tuple[int, ...], R: np.ndarray, C: np.ndarray) -> None:
    """Register view ``name`` in ``rec`` at (R, C): its unregistered image if ``rec`` holds one, else a new
    PINHOLE camera and image without keypoints."""
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R), -R @ C)
    for image in rec.images.values():
        if image.name == name:
            rec.frames[image.frame_id].rig_from_world = pose
            rec.register_frame(image.frame_id)
            return
    new_id = max([*rec.cameras.keys(), *rec.images.keys(), *rec.frames.keys(), *rec.rigs.keys(), 0]) + 1
    camera = pycolmap.Camera(
        model="PINHOLE", width=int(shape[1]), height=int(shape[0]),
        params=[K[0, 0], K[1, 1], K[0, 2], K[1, 2]], camera_id=new_id,
    )
    rec.add_camera_with_trivial_rig(camera)
    image = pycolmap.Image(name=name, keypoints=np.zeros((0, 2)), camera_id=new_id, image_id=new_id)
    rec.add_image_with_trivial_frame(image, pose)
