"""Accuracy, completeness, albedo and illumination metrics against ground truth (spec section 5).

* Distances are in units of the ground-truth mesh's bounding-box diagonal.
* Accuracy: mean exact point-to-triangle distance from each estimated vertex to
  the true surface (Open3D's RaycastingScene, Embree).
* Completeness: mean distance from each of ``n_samples`` (default 1,000,000)
  points sampled uniformly by area on the true surface to its nearest estimated
  *vertex* (so it also measures how densely the estimate samples the surface).
* Albedo RMSE: over estimated vertices and the three channels, between the
  estimated linear albedo times one least-squares scale per channel and the true
  albedo interpolated (barycentric) at the closest true surface point.
* Normal error: the angle (degrees) between each estimated vertex's area-weighted
  normal and the true face normal at its closest true surface point; mean and median.
  Vertices without a face (no normal) are left out.
* Alignment (results from SfM poses): a similarity fitted from the estimated camera
  centres to the true ones, optionally refined by ICP against the true surface
  (:func:`refine_alignment`, Tanks and Temples' protocol), which measures the surface
  apart from the camera fit's error.
* Illumination error: per frame (matched by file name), the RMSE over 10,000
  Fibonacci directions N and the three channels between the estimated shading
  ``S(N) * rgb_scale`` divided by the albedo scale and the true shading, divided
  by the RMS of the true shading; the mean over frames is reported.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from pmvir.errors import ConfigError, MeshError, PmvirError, ShapeError
from pmvir.geometry.mesh_ops import face_normals, raycasting_scene, vertex_normals
from pmvir.geometry.sfm.align import (
    CameraAlignment,
    align_by_cameras,
    estimated_camera_centres,
    match_names,
    true_camera_centres,
    umeyama,
)
from pmvir.io.illumination import Illumination, read_illumination
from pmvir.io.ply import Mesh, read_mesh
from pmvir.sh import fibonacci_sphere, sh9_shading

#: Ground-truth surface samples for completeness (spec section 5: at least 1,000,000).
N_GT_SAMPLES = 1_000_000
#: ICP of refine_alignment: pairs farther apart than this (GT diagonals) are left out.
ICP_REACH = 0.01
#: ICP of refine_alignment: estimated vertices used at most, and true surface samples.
ICP_POINTS = 200_000
ICP_SAMPLES = 500_000
#: Directions for the illumination error (spec section 5).
N_LIGHT_DIRECTIONS = 10_000
_EPS = 1e-12


@dataclass(frozen=True)
class EvaluationResult:
    """Metrics of one estimate against ground truth. Distances in GT bounding-box diagonals.

    Attributes:
        accuracy, accuracy_median, accuracy_p90: mean / median / 90th percentile distance
            from estimated vertices to the true surface.
        completeness, completeness_median, completeness_p90: the same from true surface
            samples to their nearest estimated vertex.
        albedo_rmse: scale-corrected albedo RMSE (linear units), None without albedo on both meshes.
        illumination_error: mean relative shading RMSE over matched frames, None when not computable.
        n_vertices: estimated vertices. n_gt_samples: true surface samples.
        gt_diagonal: the GT bounding-box diagonal, in world units.
        albedo_scale: the per-channel least-squares scale applied to the estimated albedo.
        illumination_per_frame: true frame file -> relative shading RMSE.
        aligned: whether a camera-based similarity was applied to the estimate first.
        alignment_rmse: camera-centre RMSE after the camera fit, in GT diagonals (None unless aligned).
        alignment_refine_shift: with the alignment refined on the true surface, the largest distance
            by which that moved an estimated vertex, GT diagonals; else None.
        alignment: the applied similarity as a dict (scale, R, t), None unless aligned.
        notes: why a metric is None, which frames did not match, etc.
        normal_error, normal_error_median: mean / median angle in degrees between the estimated
            vertices' area-weighted normals and the true face normal at their closest true point
            (None when no estimated vertex has a face).
        signed_offset, signed_offset_median: mean / median signed distance from the estimated
            vertices to the true surface along the normal of the closest true face (the face's
            winding: outward on a consistently oriented closed mesh), so negative means inside.
            Not a spec metric: a diagnostic that tells a shrunk or swollen surface (a bias every
            vertex shares) from a noisy one.
    """

    accuracy: float
    accuracy_median: float
    accuracy_p90: float
    completeness: float
    completeness_median: float
    completeness_p90: float
    albedo_rmse: float | None
    illumination_error: float | None
    n_vertices: int
    n_gt_samples: int
    gt_diagonal: float
    albedo_scale: tuple[float, float, float] | None = None
    illumination_per_frame: dict[str, float] = field(default_factory=dict)
    aligned: bool = False
    alignment_rmse: float | None = None
    alignment: dict | None = None
    alignment_refine_shift: float | None = None
    notes: tuple[str, ...] = ()
    signed_offset: float | None = None
    signed_offset_median: float | None = None
    normal_error: float | None = None
    normal_error_median: float | None = None

    def to_dict(self) -> dict:
        """The JSON object ``pmvir evaluate`` prints: flat metrics plus a ``details`` object."""
        out: dict[str, Any] = {
            "accuracy": self.accuracy,
            "completeness": self.completeness,
            "normal_error": self.normal_error,
            "normal_error_median": self.normal_error_median,
            "albedo_rmse": self.albedo_rmse,
            "illumination_error": self.illumination_error,
            "accuracy_median": self.accuracy_median,
            "accuracy_p90": self.accuracy_p90,
            "completeness_median": self.completeness_median,
            "completeness_p90": self.completeness_p90,
            "signed_offset": self.signed_offset,
            "signed_offset_median": self.signed_offset_median,
            "n_vertices": self.n_vertices,
            "n_gt_samples": self.n_gt_samples,
            "aligned": self.aligned,
        }
        if self.aligned:
            out["alignment_rmse"] = self.alignment_rmse
            out["alignment_refine_shift"] = self.alignment_refine_shift
        out["details"] = {
            "gt_diagonal": self.gt_diagonal,
            "albedo_scale": None if self.albedo_scale is None else list(self.albedo_scale),
            "illumination_per_frame": dict(self.illumination_per_frame),
            "alignment": self.alignment,
            "notes": list(self.notes),
        }
        return out


def _check_mesh(mesh: Mesh, what: str) -> None:
    if len(mesh.vertices) == 0:
        raise MeshError(f"{what} mesh has no vertices")
    if len(mesh.faces) == 0:
        raise MeshError(f"{what} mesh has no faces; expected a triangle mesh")
    if not np.isfinite(mesh.vertices).all():
        raise MeshError(f"{what} mesh has NaN or infinite vertex coordinates")


def bbox_diagonal(vertices: np.ndarray) -> float:
    """Length of the axis-aligned bounding-box diagonal of (N, 3) points.

    Example:
        >>> bbox_diagonal(np.array([[0.0, 0.0, 0.0], [1.0, 2.0, 2.0]]))
        3.0
    """
    v = np.asarray(vertices, dtype=np.float64)
    return float(np.linalg.norm(v.max(0) - v.min(0)))


def sample_surface(
    vertices: np.ndarray, faces: np.ndarray, n: int, *, seed: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Points uniformly distributed by area on a triangle mesh.

    Args:
        vertices: (V, 3) positions. faces: (F, 3) indices.
        n: number of samples, >= 1.
        seed: seed of the NumPy generator (same seed, same samples).

    Returns:
        points (n, 3) float64; face_ids (n,) int64; barycentric weights (n, 3) float64
        of the face's three vertices.

    Raises:
        MeshError: the mesh has zero total area.
    """
    if n < 1:
        raise ConfigError(f"need at least one surface sample, got {n}")
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    areas = 0.5 * np.linalg.norm(np.cross(b - a, c - a), axis=1)
    cdf = np.cumsum(areas)
    if not cdf[-1] > 0:
        raise MeshError("mesh has zero surface area; cannot sample it")
    rng = np.random.default_rng(seed)
    face_ids = np.searchsorted(cdf, rng.random(n) * cdf[-1], side="right")
    face_ids = np.minimum(face_ids, len(f) - 1)
    r1, r2 = rng.random(n), rng.random(n)
    s = np.sqrt(r1)  # uniform on the triangle (Osada et al. 2002)
    bary = np.stack([1.0 - s, s * (1.0 - r2), s * r2], axis=1)
    points = bary[:, :1] * a[face_ids] + bary[:, 1:2] * b[face_ids] + bary[:, 2:] * c[face_ids]
    return points, face_ids, bary


class SurfaceQuery:
    """Exact closest points on a triangle mesh (Open3D RaycastingScene).

    Coordinates are shifted to the mesh's bounding-box centre before Open3D's
    float32 conversion, so precision is relative to the mesh size, not its position.
    """

    def __init__(self, vertices: np.ndarray, faces: np.ndarray):
        import open3d as o3d

        self._o3d = o3d
        v = np.asarray(vertices, dtype=np.float64)
        self.origin = 0.5 * (v.min(0) + v.max(0))
        self._scene = raycasting_scene(v, faces, origin=self.origin).scene

    def closest(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Closest surface points of (N, 3) query points.

        Returns:
            closest (N, 3) float64 world points; face_ids (N,) int64; barycentric
            weights (N, 3) float64 of the face's vertices 0, 1, 2.
        """
        q = np.ascontiguousarray(np.asarray(points, dtype=np.float64) - self.origin, dtype=np.float32)
        ans = self._scene.compute_closest_points(self._o3d.core.Tensor(q))
        closest = ans["points"].numpy().astype(np.float64) + self.origin
        face_ids = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy().astype(np.float64)  # p = (1-u-v) v0 + u v1 + v v2
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        return closest, face_ids, bary


def albedo_scale_rmse(est_albedo: np.ndarray, true_albedo: np.ndarray) -> tuple[np.ndarray, float]:
    """One least-squares scale per channel, then the RMSE.

    Args:
        est_albedo, true_albedo: (N, 3) linear albedo at corresponding points.

    Returns:
        scale (3,) float64 minimising ``|scale_c * est_c - true_c|^2`` per channel
        (0 where the estimate's channel is all zero), and the RMSE over all N x 3 values.

    Example:
        An estimate that is the truth up to a per-channel scale has zero error:

        >>> true = np.array([[0.2, 0.4, 0.6], [0.1, 0.3, 0.5]])
        >>> scale, rmse = albedo_scale_rmse(true / np.array([2.0, 4.0, 1.0]), true)
        >>> scale, round(rmse, 12)
        (array([2., 4., 1.]), 0.0)
    """
    est = np.asarray(est_albedo, dtype=np.float64)
    true = np.asarray(true_albedo, dtype=np.float64)
    if est.shape != true.shape or est.ndim != 2 or est.shape[1] != 3:
        raise ShapeError(f"expected two (N, 3) albedo arrays, got {est.shape} and {true.shape}")
    scale = (est * true).sum(0) / np.maximum((est * est).sum(0), _EPS)
    return scale, float(np.sqrt(np.mean((est * scale - true) ** 2)))


def shading_error(
    est_sh: ArrayLike,
    est_rgb: ArrayLike,
    true_sh: ArrayLike,
    true_rgb: ArrayLike,
    albedo_scale: ArrayLike,
    *,
    est_from_true: ArrayLike | None = None,
    n_directions: int = N_LIGHT_DIRECTIONS,
) -> float:
    """Relative RMSE between estimated and true shading ``S(N) * rgb_scale`` on the sphere.

    Args:
        est_sh, true_sh: (9,) pmvir-sh9 coefficients. est_rgb, true_rgb: (3,) colour scales.
        albedo_scale: (3,) the scale that maps the estimated albedo onto the true one;
            the estimated shading is divided by it (albedo and rgb_scale share that ambiguity).
        est_from_true: optional (3, 3) rotation taking true-world directions to the
            estimate's world (the inverse rotation of an alignment); identity when None.
        n_directions: Fibonacci directions.

    Returns:
        RMSE over directions and channels divided by the RMS of the true shading.

    Example:
        Twice the light on an albedo estimated at half the truth is the same shading:

        >>> sh = np.array([1.0, 0.2, 0.5, 0.1, 0, 0, 0, 0, 0])
        >>> round(shading_error(2 * sh, [1, 1, 1], sh, [1, 1, 1], [2, 2, 2]), 12)
        0.0
    """
    dirs = fibonacci_sphere(n_directions)
    est_dirs = dirs if est_from_true is None else dirs @ np.asarray(est_from_true, dtype=np.float64).T
    true = sh9_shading(dirs, np.asarray(true_sh, np.float64))[:, None] * np.asarray(true_rgb, np.float64)
    est = sh9_shading(est_dirs, np.asarray(est_sh, np.float64))[:, None] * np.asarray(est_rgb, np.float64)
    est = est / np.asarray(albedo_scale, dtype=np.float64)
    rms_true = float(np.sqrt(np.mean(true**2)))
    return float(np.sqrt(np.mean((est - true) ** 2))) / max(rms_true, _EPS)


def refine_alignment(
    alignment: CameraAlignment, est_vertices: np.ndarray, gt_mesh: Mesh, *, iterations: int = 50, seed: int = 0
) -> CameraAlignment:
    """The camera fit refined by ICP against the true surface (similarity, point to point).

    From ``alignment``, each round pairs the estimated vertices (``ICP_POINTS`` of them at most)
    with their nearest of ``ICP_SAMPLES`` points on the true surface, leaves out pairs farther
    apart than ``ICP_REACH`` of its diagonal, and composes the Umeyama similarity of the rest,
    until a round moves no vertex by more than 1e-7 of the diagonal. What it measures is then
    the surface apart from the camera fit's error (Tanks and Temples' protocol); it cannot
    remove a shape error, only a rigid motion and a scale.

    Returns:
        The refined alignment: its transform, the camera fit's ``rmse`` and ``pairs``, and
        ``surface_shift``, the largest distance the refinement moved a used vertex.
    """
    from scipy.spatial import cKDTree

    diag = bbox_diagonal(gt_mesh.vertices)
    samples, _, _ = sample_surface(gt_mesh.vertices, gt_mesh.faces, ICP_SAMPLES, seed=seed)
    tree = cKDTree(samples)
    src = np.asarray(est_vertices, np.float64)
    if len(src) > ICP_POINTS:
        src = src[np.random.default_rng(seed).choice(len(src), ICP_POINTS, replace=False)]
    start = alignment.transform.apply(src)
    total, moved = alignment.transform, start
    for _ in range(iterations):
        dist, idx = tree.query(moved, workers=-1)
        near = dist < ICP_REACH * diag
        if near.sum() < 3:
            break
        total = umeyama(moved[near], samples[idx[near]]).after(total)
        before, moved = moved, total.apply(src)
        if np.abs(moved - before).max() < 1e-7 * diag:
            break
    shift = float(np.linalg.norm(moved - start, axis=1).max()) if len(src) else 0.0
    return CameraAlignment(total, alignment.rmse, alignment.pairs, surface_shift=shift)


def _summary(d: np.ndarray) -> tuple[float, float, float]:
    return float(d.mean()), float(np.median(d)), float(np.percentile(d, 90))


def evaluate(
    est_mesh: Mesh,
    gt_mesh: Mesh,
    *,
    est_illum: Illumination | None = None,
    gt_illum: Illumination | None = None,
    n_samples: int = N_GT_SAMPLES,
    seed: int = 0,
    alignment: CameraAlignment | None = None,
) -> EvaluationResult:
    """All metrics of spec section 5 for an estimated mesh (and lighting) against ground truth.

    Args:
        est_mesh: the estimate; its albedo (if any) is linear.
        gt_mesh: the true surface; its albedo (if any) is the true linear albedo.
        est_illum, gt_illum: per-frame SH lighting; the illumination error needs both
            and the albedo scale (so albedo on both meshes).
        n_samples: true surface samples for completeness (spec: >= 1,000,000).
        seed: sampling seed.
        alignment: a similarity from the estimate's frame to the true one; applied to
            the estimated vertices (and the lighting's directions) before measuring.

    Raises:
        MeshError: a mesh is empty, has no faces, non-finite vertices or zero extent.
    """
    _check_mesh(est_mesh, "estimated")
    _check_mesh(gt_mesh, "ground-truth")
    diag = bbox_diagonal(gt_mesh.vertices)
    if not diag > 0:
        raise MeshError("ground-truth mesh has a zero-size bounding box")
    notes: list[str] = []

    est_v = est_mesh.vertices if alignment is None else alignment.transform.apply(est_mesh.vertices)
    query = SurfaceQuery(gt_mesh.vertices, gt_mesh.faces)
    closest, face_ids, bary = query.closest(est_v)
    offsets = est_v - closest
    acc = np.linalg.norm(offsets, axis=1) / diag
    signed = acc * outward_sign(offsets, gt_mesh.vertices, gt_mesh.faces[face_ids])
    angles = normal_angles(est_v, est_mesh.faces, gt_mesh.vertices, gt_mesh.faces[face_ids])
    angles = angles[np.isfinite(angles)]
    if len(angles) < len(est_v):
        notes.append(f"normal_error: {len(est_v) - len(angles)} estimated vertices without a face left out")

    from scipy.spatial import cKDTree

    samples, _, _ = sample_surface(gt_mesh.vertices, gt_mesh.faces, n_samples, seed=seed)
    comp, _ = cKDTree(est_v).query(samples, k=1, workers=-1)
    comp = comp / diag

    albedo_rmse = scale = None
    if est_mesh.albedo is None or gt_mesh.albedo is None:
        notes.append(
            "albedo_rmse: "
            + ("estimated" if est_mesh.albedo is None else "ground-truth")
            + " mesh has no albedo"
        )
    else:
        tri = gt_mesh.faces[face_ids]
        true_albedo = np.einsum("nk,nkc->nc", bary, gt_mesh.albedo.astype(np.float64)[tri])
        scale, albedo_rmse = albedo_scale_rmse(est_mesh.albedo, true_albedo)

    illum_error, per_frame = _illumination(est_illum, gt_illum, scale, alignment, notes)
    return EvaluationResult(
        *_summary(acc),
        *_summary(comp),
        albedo_rmse=albedo_rmse,
        illumination_error=illum_error,
        n_vertices=len(est_v),
        n_gt_samples=int(n_samples),
        gt_diagonal=diag,
        albedo_scale=None if scale is None else (float(scale[0]), float(scale[1]), float(scale[2])),
        illumination_per_frame=per_frame,
        aligned=alignment is not None,
        alignment_rmse=None if alignment is None else alignment.rmse / diag,
        alignment_refine_shift=None if alignment is None or alignment.surface_shift is None
        else alignment.surface_shift / diag,
        alignment=None if alignment is None else alignment.transform.to_dict(),
        notes=tuple(notes),
        signed_offset=float(signed.mean()),
        signed_offset_median=float(np.median(signed)),
        normal_error=float(angles.mean()) if len(angles) else None,
        normal_error_median=float(np.median(angles)) if len(angles) else None,
    )


def normal_angles(
    vertices: np.ndarray, faces: np.ndarray, true_vertices: np.ndarray, true_faces: np.ndarray
) -> np.ndarray:
    """Angle between each vertex's area-weighted normal and the true face normal it is matched to.

    Args:
        vertices: (N, 3) estimated vertices (already in the true frame). faces: (F, 3) their faces.
        true_vertices: (V, 3) the true surface's vertices.
        true_faces: (N, 3) the true face holding each estimated vertex's closest point.

    Returns:
        (N,) float64 angles in degrees, in [0, 180]; NaN for a vertex without a face or matched
        to a degenerate true face.

    Example:
        A triangle against itself, then against itself flipped:

        >>> v = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]); f = np.array([[0, 1, 2]])
        >>> normal_angles(v, f, v, f[[0, 0, 0]]).round(6).tolist()
        [0.0, 0.0, 0.0]
        >>> normal_angles(v, f[:, ::-1], v, f[[0, 0, 0]]).round(6).tolist()
        [180.0, 180.0, 180.0]
    """
    n_est = vertex_normals(vertices, faces)
    t = np.asarray(true_vertices, dtype=np.float64)
    tf = np.asarray(true_faces, dtype=np.int64)
    n_true = face_normals(t, tf, normalize=False)
    len_true = np.linalg.norm(n_true, axis=1)
    n_true = n_true / np.maximum(len_true, 1e-300)[:, None]
    cos = np.clip(np.einsum("ij,ij->i", n_est, n_true), -1.0, 1.0)
    angles = np.degrees(np.arccos(cos))
    has_normal = np.linalg.norm(n_est, axis=1) > 0.5
    return np.where(has_normal & (len_true > 0), angles, np.nan)


def outward_sign(offsets: np.ndarray, vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Which side of the surface each query point lies on.

    Args:
        offsets: (N, 3) query point minus its closest point on the surface.
        vertices: (V, 3) the surface's vertices.
        faces: (N, 3) the face holding each closest point.

    Returns:
        (N,) float64 sign of ``offset . n``, n by the face's winding (counter-clockwise seen from
        its front): +1 in front, -1 behind, 0 on the surface.
    """
    n = face_normals(vertices, faces, normalize=False)
    return np.sign(np.einsum("ij,ij->i", np.asarray(offsets, dtype=np.float64), n))


def _illumination(
    est: Illumination | None,
    gt: Illumination | None,
    scale: np.ndarray | None,
    alignment: CameraAlignment | None,
    notes: list[str],
) -> tuple[float | None, dict[str, float]]:
    if gt is None or est is None:
        notes.append(
            "illumination_error: no " + ("ground-truth" if gt is None else "estimated") + " SH illumination"
        )
        return None, {}
    if scale is None:
        notes.append("illumination_error: needs the albedo scale, which needs albedo on both meshes")
        return None, {}
    if np.any(scale <= _EPS):
        notes.append(f"illumination_error: albedo scale {scale.tolist()} is not positive in every channel")
        return None, {}
    est_by_file = {f.file: f for f in est.frames}
    pairs = match_names(list(est_by_file), [f.file for f in gt.frames])
    gt_by_file = {f.file: f for f in gt.frames}
    unmatched = sorted(set(gt_by_file) - {f for _, f in pairs})
    if unmatched:
        notes.append(
            f"illumination_error: {len(unmatched)} true frame(s) without an estimate: {unmatched[:10]}"
        )
    if not pairs:
        return None, {}
    rot = None if alignment is None else alignment.transform.R.T
    per_frame = {
        true_file: shading_error(
            est_by_file[name].sh,
            est_by_file[name].rgb_scale,
            gt_by_file[true_file].sh,
            gt_by_file[true_file].rgb_scale,
            scale,
            est_from_true=rot,
        )
        for name, true_file in pairs
    }
    return float(np.mean(list(per_frame.values()))), per_frame


def evaluate_paths(
    estimate: str | Path,
    gt_dir: str | Path,
    *,
    align: bool = False,
    icp: bool = False,
    n_samples: int = N_GT_SAMPLES,
    seed: int = 0,
) -> EvaluationResult:
    """Evaluate a result folder (``mesh.ply``, ``illumination.json``, ``poses/``) or a bare mesh file.

    Args:
        estimate: a RESULT_DIR or a .ply/.obj mesh file.
        gt_dir: a capture's ``gt/`` folder (``mesh.ply``, optional ``illumination.json``);
            with ``align`` its parent's ``capture.json`` gives the true camera poses.
        align: fit a similarity from the estimated camera centres (``poses/images.txt``)
            to the true ones and apply it first.
        icp: with ``align``, refine that similarity on the true surface (:func:`refine_alignment`).

    Raises:
        MeshError, ManifestError, ConfigError, PmvirError: missing or malformed inputs.
    """
    estimate, gt_dir = Path(estimate), Path(gt_dir)
    if not gt_dir.is_dir():
        raise PmvirError(f"{gt_dir}: no such ground-truth folder (expected CAPTURE/gt with mesh.ply)")
    if not (gt_dir / "mesh.ply").is_file():
        raise MeshError(f"{gt_dir / 'mesh.ply'}: no ground-truth mesh")
    gt_mesh = read_mesh(gt_dir / "mesh.ply")
    gt_illum = (
        read_illumination(gt_dir / "illumination.json") if (gt_dir / "illumination.json").is_file() else None
    )

    if estimate.is_dir():
        est_mesh = read_mesh(estimate / "mesh.ply")
        illum_path = estimate / "illumination.json"
        est_illum = read_illumination(illum_path) if illum_path.is_file() else None
        images_txt = estimate / "poses" / "images.txt"
    elif estimate.is_file():
        est_mesh, est_illum, images_txt = read_mesh(estimate), None, None
    else:
        raise PmvirError(f"{estimate}: no such result folder or mesh file")

    alignment = None
    if align:
        if images_txt is None:
            raise ConfigError(
                f"--align needs a result folder with poses/images.txt, got the mesh file {estimate}"
            )
        alignment = align_by_cameras(
            estimated_camera_centres(images_txt),
            true_camera_centres(gt_dir.resolve().parent / "capture.json"),
        )
        if icp:
            alignment = refine_alignment(alignment, est_mesh.vertices, gt_mesh, seed=seed)
    elif icp:
        raise ConfigError("--icp refines the camera alignment: it needs --align")
    return evaluate(
        est_mesh,
        gt_mesh,
        est_illum=est_illum,
        gt_illum=gt_illum,
        n_samples=n_samples,
        seed=seed,
        alignment=alignment,
    )
