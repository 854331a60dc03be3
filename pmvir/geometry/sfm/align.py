"""Aligning a reconstruction to ground truth through its cameras (Umeyama 1991).

A reconstruction from SfM lives in its own frame, known only up to a
similarity (rotation, translation and scale). ``umeyama`` finds the least-squares
similarity between two sets of corresponding points; ``align_by_cameras`` applies
it to the estimated camera centres (from a COLMAP ``images.txt``) and the true
ones (from ``capture.json``), matched by image name.

S. Umeyama, "Least-squares estimation of transformation parameters between two
point patterns", IEEE TPAMI 13(4), 1991.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

import numpy as np

from pmvir.errors import ManifestError, ReconstructionError, ShapeError
from pmvir.io.colmap_text import read_images_text


@dataclass(frozen=True)
class Similarity:
    """``y = scale * R @ x + t``.

    Attributes:
        scale: positive float.
        R: (3, 3) float64 proper rotation (det +1).
        t: (3,) float64 translation.
    """

    scale: float
    R: np.ndarray
    t: np.ndarray

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Transform (N, 3) points; returns (N, 3) float64."""
        return self.scale * (np.asarray(points, dtype=np.float64) @ self.R.T) + self.t

    def inverse(self) -> Similarity:
        """The similarity that undoes this one."""
        return Similarity(1.0 / self.scale, self.R.T, -(self.R.T @ self.t) / self.scale)

    def after(self, first: Similarity) -> Similarity:
        """The similarity that applies ``first``, then this one."""
        return Similarity(self.scale * first.scale, self.R @ first.R, self.scale * (self.R @ first.t) + self.t)

    def to_dict(self) -> dict:
        return {"scale": float(self.scale), "R": self.R.tolist(), "t": self.t.tolist()}


def umeyama(src: np.ndarray, dst: np.ndarray, *, with_scale: bool = True) -> Similarity:
    """Least-squares similarity mapping ``src`` onto ``dst`` (Umeyama 1991, eqs. 34-43).

    Minimises ``sum_i |dst_i - (c R src_i + t)|^2`` over rotations R (det +1),
    scales c > 0 (fixed to 1 when ``with_scale`` is False) and translations t.

    Args:
        src: (N, 3) points, N >= 3, not all on one line.
        dst: (N, 3) corresponding points.
        with_scale: estimate the scale (True) or keep it 1 (a rigid transform).

    Returns:
        The Similarity; exact for noise-free data.

    Raises:
        ShapeError: shapes differ or are not (N, 3).
        ReconstructionError: fewer than 3 points, or the points are (nearly) collinear
            so the rotation is not determined.
    """
    x = np.asarray(src, dtype=np.float64)
    y = np.asarray(dst, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or x.shape != y.shape:
        raise ShapeError(f"expected two (N, 3) arrays of the same shape, got {x.shape} and {y.shape}")
    if len(x) < 3:
        raise ReconstructionError(f"a similarity needs at least 3 corresponding points, got {len(x)}")
    if not (np.isfinite(x).all() and np.isfinite(y).all()):
        raise ReconstructionError("corresponding points hold NaN or infinite values")
    mu_x, mu_y = x.mean(0), y.mean(0)
    xc, yc = x - mu_x, y - mu_y
    var_x = float((xc * xc).sum(1).mean())
    sigma = yc.T @ xc / len(x)  # (3, 3) covariance of dst and src
    U, d, Vt = np.linalg.svd(sigma)
    # Rank test (Umeyama: rank >= m - 1 for a unique rotation); relative to the spread.
    spread = np.sqrt(var_x * float((yc * yc).sum(1).mean()))
    if spread <= 0.0 or d[1] <= 1e-6 * spread:
        raise ReconstructionError(
            "cannot determine a rotation: the corresponding points are (nearly) collinear or coincident"
        )
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1.0
    R = U @ S @ Vt
    scale = float((d * np.diag(S)).sum() / var_x) if with_scale else 1.0
    t = mu_y - scale * (R @ mu_x)
    return Similarity(scale, R, t)


def match_names(est_names: list[str], true_files: list[str]) -> list[tuple[str, str]]:
    """Pair estimated image names with true frame files.

    A name matches a frame when it equals the frame's file, else its basename, else
    its stem (file name without extension), tried in that order; a key shared by
    two frames (or two names) is ambiguous and not used at that level.

    Returns:
        (est_name, true_file) pairs, each name and each file at most once, in ``true_files`` order.
    """
    keyers = (
        lambda s: s,
        lambda s: PurePosixPath(s.replace("\\", "/")).name,
        lambda s: PurePosixPath(s.replace("\\", "/")).stem,
    )
    pairs: dict[str, str] = {}  # true_file -> est_name
    used: set[str] = set()
    for key in keyers:
        free_true = [f for f in true_files if f not in pairs]
        free_est = [n for n in est_names if n not in used]
        by_true: dict[str, list[str]] = {}
        for f in free_true:
            by_true.setdefault(key(f), []).append(f)
        by_est: dict[str, list[str]] = {}
        for n in free_est:
            by_est.setdefault(key(n), []).append(n)
        for k, files in by_true.items():
            names = by_est.get(k, [])
            if len(files) == 1 and len(names) == 1:
                pairs[files[0]] = names[0]
                used.add(names[0])
    return [(pairs[f], f) for f in true_files if f in pairs]


def true_camera_centres(manifest: str | Path) -> dict[str, np.ndarray]:
    """Camera centres ``-R^T t`` of the frames of a ``capture.json`` that carry ``cam_from_world``.

    Returns:
        frame file -> (3,) float64 centre.

    Raises:
        ManifestError: the file is missing, not JSON, or a pose is malformed.
    """
    manifest = Path(manifest)
    try:
        doc = json.loads(manifest.read_text(encoding="utf-8"))
    except FileNotFoundError as exc:
        raise ManifestError(manifest, "no such file (needed for the true camera poses)") from exc
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ManifestError(manifest, f"cannot read JSON ({exc})") from exc
    frames = doc.get("frames") if isinstance(doc, dict) else None
    if not isinstance(frames, list):
        raise ManifestError(manifest, "expected a 'frames' list")
    centres: dict[str, np.ndarray] = {}
    for i, frame in enumerate(frames):
        if not isinstance(frame, dict) or "file" not in frame:
            raise ManifestError(manifest, f"frames[{i}] has no 'file'")
        pose = frame.get("cam_from_world")
        if pose is None:
            continue
        try:
            R = np.asarray(pose["R"], dtype=np.float64).reshape(3, 3)
            t = np.asarray(pose["t"], dtype=np.float64).reshape(3)
        except (KeyError, TypeError, ValueError) as exc:
            raise ManifestError(
                manifest, f"frames[{i}].cam_from_world: expected R (3x3) and t (3) ({exc})"
            ) from exc
        if not (np.isfinite(R).all() and np.isfinite(t).all()):
            raise ManifestError(manifest, f"frames[{i}].cam_from_world holds non-finite values")
        centres[str(frame["file"])] = -R.T @ t
    return centres


def estimated_camera_centres(images_txt: str | Path) -> dict[str, np.ndarray]:
    """Camera centres ``-R^T t`` of a COLMAP text ``images.txt``: image name -> (3,) float64."""
    return {m.name: m.center for m in read_images_text(images_txt).values()}


@dataclass(frozen=True)
class CameraAlignment:
    """A similarity from the estimated frame to the true one, fitted on camera centres.

    Attributes:
        transform: maps estimated world points to true world points.
        rmse: root mean square distance between the camera fit's transformed estimated centres
            and the true ones, in the true world's units.
        pairs: the (est_name, true_file) pairs used.
        surface_shift: when the fit was refined on the true surface (:func:`pmvir.evaluate.refine_alignment`),
            the largest distance by which that moved an estimated point (true world units); else None.
    """

    transform: Similarity
    rmse: float
    pairs: list[tuple[str, str]]
    surface_shift: float | None = None


def align_by_cameras(
    est_centres: dict[str, np.ndarray], true_centres: dict[str, np.ndarray]
) -> CameraAlignment:
    """Fit the similarity (with scale) taking estimated camera centres onto the true ones.

    Raises:
        ReconstructionError: fewer than 3 cameras match by name, or their centres are collinear.
    """
    pairs = match_names(list(est_centres), list(true_centres))
    if len(pairs) < 3:
        raise ReconstructionError(
            f"alignment needs at least 3 cameras matched by name, got {len(pairs)} "
            f"(estimated: {sorted(est_centres)[:5]}..., true: {sorted(true_centres)[:5]}...)"
        )
    src = np.stack([est_centres[n] for n, _ in pairs])
    dst = np.stack([true_centres[f] for _, f in pairs])
    sim = umeyama(src, dst, with_scale=True)
    rmse = float(np.sqrt(((sim.apply(src) - dst) ** 2).sum(1).mean()))
    return CameraAlignment(sim, rmse, pairs)
