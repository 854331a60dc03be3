"""Umeyama similarity and camera-based alignment (pmvir.geometry.sfm.align)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pmvir.camera import look_at
from pmvir.errors import ManifestError, ReconstructionError
from pmvir.geometry.sfm.align import (
    Similarity,
    align_by_cameras,
    estimated_camera_centres,
    match_names,
    true_camera_centres,
    umeyama,
)
from pmvir.io.colmap_text import ColmapCamera, ColmapImage, qvec_from_rotmat, write_colmap_text_model


def known_similarity(seed: int) -> Similarity:
    rng = np.random.default_rng(seed)
    return Similarity(
        float(rng.uniform(0.2, 5.0)), Rotation.random(random_state=seed).as_matrix(), rng.normal(0, 3, 3)
    )


@pytest.mark.parametrize("seed", range(5))
def test_umeyama_recovers_a_known_similarity_exactly(seed):
    truth = known_similarity(seed)
    src = np.random.default_rng(100 + seed).normal(0, 1, (12, 3))
    est = umeyama(src, truth.apply(src))
    assert est.scale == pytest.approx(truth.scale, rel=1e-12)
    np.testing.assert_allclose(est.R, truth.R, atol=1e-12)
    np.testing.assert_allclose(est.t, truth.t, atol=1e-10)
    assert np.linalg.det(est.R) == pytest.approx(1.0)


def test_umeyama_minimal_three_points():
    truth = known_similarity(7)
    src = np.array([[0.0, 0, 0], [1, 0, 0], [0, 2, 0]])
    est = umeyama(src, truth.apply(src))
    np.testing.assert_allclose(est.apply(src), truth.apply(src), atol=1e-12)
    np.testing.assert_allclose(est.R, truth.R, atol=1e-12)


def test_umeyama_rigid_keeps_scale_one():
    truth = known_similarity(3)
    rigid = Similarity(1.0, truth.R, truth.t)
    src = np.random.default_rng(1).normal(0, 1, (8, 3))
    est = umeyama(src, rigid.apply(src), with_scale=False)
    assert est.scale == 1.0
    np.testing.assert_allclose(est.R, truth.R, atol=1e-12)
    # Given scaled data, the rigid fit still has scale 1 (and a residual).
    assert umeyama(src, truth.apply(src), with_scale=False).scale == 1.0


def test_umeyama_never_returns_a_reflection():
    src = np.random.default_rng(2).normal(0, 1, (10, 3))
    mirrored = src * np.array([1.0, 1.0, -1.0])
    est = umeyama(src, mirrored)
    assert np.linalg.det(est.R) == pytest.approx(1.0)
    # The least-squares rotation of noisy data is close to the truth.
    truth = known_similarity(4)
    noisy = truth.apply(src) + np.random.default_rng(5).normal(0, 1e-3, src.shape)
    est = umeyama(src, noisy)
    assert np.linalg.det(est.R) == pytest.approx(1.0)
    assert np.degrees(Rotation.from_matrix(est.R.T @ truth.R).magnitude()) < 0.1


def test_similarity_inverse_round_trip():
    s = known_similarity(9)
    p = np.random.default_rng(0).normal(0, 1, (5, 3))
    np.testing.assert_allclose(s.inverse().apply(s.apply(p)), p, atol=1e-12)


def test_umeyama_collinear_points_raise_reconstruction_error():
    src = np.outer(np.arange(5.0), [1.0, 2.0, 3.0])
    with pytest.raises(ReconstructionError, match="collinear"):
        umeyama(src, src + 1.0)


def test_umeyama_too_few_points_raise_reconstruction_error():
    with pytest.raises(ReconstructionError, match="at least 3"):
        umeyama(np.eye(3)[:2], np.eye(3)[:2])


def test_umeyama_shape_mismatch_raises_value_error():
    with pytest.raises(ValueError, match="same shape"):
        umeyama(np.zeros((4, 3)), np.zeros((5, 3)))


def test_match_names_full_basename_stem():
    true = ["frames/000.png", "frames/001.png", "frames/002.png", "frames/003.png"]
    est = ["frames/000.png", "001.png", "002", "zzz.png"]
    assert match_names(est, true) == [
        ("frames/000.png", "frames/000.png"),
        ("001.png", "frames/001.png"),
        ("002", "frames/002.png"),
    ]


def test_match_names_skips_ambiguous_keys():
    true = ["a/000.png", "b/000.png", "a/001.png"]
    assert match_names(["000.png", "001.png"], true) == [("001.png", "a/001.png")]
    # A full path still matches exactly.
    assert match_names(["b/000.png"], true) == [("b/000.png", "b/000.png")]


def _write_poses(tmp_path, truth: Similarity, names: list[str]):
    frames, images = [], []
    est_from_true = truth.inverse()
    for i, name in enumerate(names):
        ang = 2 * np.pi * i / len(names)
        centre = np.array([3 * np.cos(ang), 3 * np.sin(ang), 0.5 * np.cos(3 * ang)])
        R, t = look_at(centre, np.zeros(3))
        frames.append({"file": f"frames/{name}", "cam_from_world": {"R": R.tolist(), "t": t.tolist()}})
        R_est = R @ truth.R
        c_est = est_from_true.apply(centre[None])[0]
        images.append(ColmapImage(i + 1, qvec_from_rotmat(R_est), -R_est @ c_est, 1, name))
    frames.append({"file": "frames/unposed.png"})  # frames without a pose are skipped
    (tmp_path / "capture.json").write_text(json.dumps({"frames": frames}))
    write_colmap_text_model(tmp_path / "poses", [ColmapCamera(1, "SIMPLE_PINHOLE", 8, 8, (9, 4, 4))], images)
    return frames


def test_align_by_cameras_from_files(tmp_path):
    truth = known_similarity(11)
    frames = _write_poses(tmp_path, truth, [f"{i:03d}.png" for i in range(5)])
    true_c = true_camera_centres(tmp_path / "capture.json")
    assert len(true_c) == 5 and "frames/unposed.png" not in true_c
    R0, t0 = np.array(frames[0]["cam_from_world"]["R"]), np.array(frames[0]["cam_from_world"]["t"])
    np.testing.assert_allclose(true_c["frames/000.png"], -R0.T @ t0)
    al = align_by_cameras(estimated_camera_centres(tmp_path / "poses" / "images.txt"), true_c)
    assert len(al.pairs) == 5 and al.rmse < 1e-9
    assert al.transform.scale == pytest.approx(truth.scale, rel=1e-9)
    np.testing.assert_allclose(al.transform.R, truth.R, atol=1e-9)


def test_align_by_cameras_needs_three_matches(tmp_path):
    truth = known_similarity(12)
    _write_poses(tmp_path, truth, ["a.png", "b.png", "c.png"])
    est = estimated_camera_centres(tmp_path / "poses" / "images.txt")
    true_c = true_camera_centres(tmp_path / "capture.json")
    del est["c.png"]
    with pytest.raises(ReconstructionError, match="at least 3 cameras matched"):
        align_by_cameras(est, true_c)


def test_true_camera_centres_missing_manifest_raises_manifest_error(tmp_path):
    with pytest.raises(ManifestError, match="no such file"):
        true_camera_centres(tmp_path / "capture.json")


def test_true_camera_centres_bad_pose_raises_manifest_error(tmp_path):
    (tmp_path / "capture.json").write_text(
        json.dumps({"frames": [{"file": "f.png", "cam_from_world": {"R": [1, 2]}}]})
    )
    with pytest.raises(ManifestError, match=r"frames\[0\].cam_from_world"):
        true_camera_centres(tmp_path / "capture.json")


def test_true_camera_centres_not_json_raises_manifest_error(tmp_path):
    (tmp_path / "capture.json").write_text("{not json")
    with pytest.raises(ManifestError, match="cannot read JSON"):
        true_camera_centres(tmp_path / "capture.json")
