"""Joining SfM models (pmvir.geometry.sfm.join): the similarity between two models' frames from common views."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pmvir.camera import Camera
from pmvir.geometry.sfm.join import similarity_from_shared, transform_camera

K = np.array([[500.0, 0.0, 160.0], [0.0, 500.0, 120.0], [0.0, 0.0, 1.0]])


def _ring(n: int = 6, radius: float = 3.0) -> dict[int, Camera]:
    """n cameras on a circle, looking at the origin."""
    cameras = {}
    for i in range(n):
        a = 2 * np.pi * i / n
        centre = radius * np.array([np.cos(a), 0.3, np.sin(a)])
        z = -centre / np.linalg.norm(centre)
        x = np.cross([0.0, 1.0, 0.0], z)
        x /= np.linalg.norm(x)
        R = np.stack([x, np.cross(z, x), z])
        cameras[i] = Camera(K=K, R=R, t=-R @ centre, width=320, height=240)
    return cameras


def _moved(cameras: dict[int, Camera], s: float, R: np.ndarray, t: np.ndarray) -> dict[int, Camera]:
    return {i: transform_camera(c, s, R, t) for i, c in cameras.items()}


def test_transform_camera_moves_the_centre_and_keeps_projections() -> None:
    cam = _ring()[1]
    s, R, t = 2.5, Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix(), np.array([1.0, -2.0, 0.5])
    moved = transform_camera(cam, s, R, t)
    assert np.allclose(moved.center, s * R @ cam.center + t)
    X = np.array([[0.1, 0.2, -0.1], [0.0, -0.3, 0.2]])
    uv, _ = cam.project(X)
    uv_moved, _ = moved.project(s * X @ R.T + t)
    assert np.allclose(uv, uv_moved)


def test_similarity_from_two_or_more_common_views_is_recovered() -> None:
    base = _ring()
    s, R, t = 0.4, Rotation.from_rotvec([-0.7, 0.1, 1.2]).as_matrix(), np.array([0.3, 2.0, -1.0])
    # other's frame: x_other = (R^T (x_base - t)) / s, so x_base = s R x_other + t
    R_inv = R.T
    other = _moved({i: base[i] for i in (2, 3, 4, 5)}, 1.0 / s, R_inv, -R_inv @ t / s)
    found = similarity_from_shared({i: base[i] for i in (0, 1, 2, 3)}, {i: other[i] for i in (2, 3, 4, 5)})
    assert found is not None
    s_found, R_found, t_found = found
    assert np.isclose(s_found, s) and np.allclose(R_found, R, atol=1e-9) and np.allclose(t_found, t)
    assert np.allclose(transform_camera(other[5], *found).center, base[5].center)


def test_one_common_view_or_disagreeing_views_do_not_join() -> None:
    base = _ring()
    assert similarity_from_shared({0: base[0], 1: base[1]}, {1: base[1], 2: base[2]}) is None
    # the common views' rotations disagree by 10 degrees (one pose wrong): no similarity
    wrong = base[3]
    tilted = Rotation.from_rotvec([0.0, np.radians(10.0), 0.0]).as_matrix() @ wrong.R
    bad = Camera(K=K, R=tilted, t=-tilted @ wrong.center, width=320, height=240)
    assert similarity_from_shared(base, {2: base[2], 3: bad}) is None
    # rotations agree but one centre is off by a fifth of the spread
    off = transform_camera(base[3], 1.0, np.eye(3), np.array([0.0, 1.2, 0.0]))
    assert similarity_from_shared(base, {2: base[2], 3: base[3], 4: off}) is None
    assert similarity_from_shared(base, {2: base[2], 3: base[3], 4: base[4]}) is not None


def _shared_model(name: str) -> Path:
    env = os.environ.get("PMVIR_SHARED")
    root = Path(env) if env else Path(__file__).resolve().parents[2] / ".." / "shared"
    return root / "data" / "models" / name


@pytest.mark.skipif(
    not _shared_model("dragon.ply").is_file(), reason="../shared/data/models/dragon.ply is absent"
)
def test_the_dragons_two_one_sided_models_are_joined(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """End to end: on the 36-view dragon the mapper builds one model per side (the end-on views
    verify with too few others; it failed with 14 views before the join); joining them through the
    views both register by absolute pose gives one model of at least 30 views, and the frontier
    adjustment takes the bend its tracks leave (1.1% of the rig) to within 0.5%.
    Models being joined are matched again once per pass whatever sfm.rematch_rounds says (default 2):
    a second round along their bent poses added to the bend (1.10 -> 1.34 % of the rig)."""
    from pmvir.capture import open_capture
    from pmvir.config import SfmOptions
    from pmvir.decode import decode_frame
    from pmvir.geometry.sfm import colmap as sfm_colmap
    from pmvir.geometry.sfm.align import umeyama
    from pmvir.geometry.sfm.poses import estimate_poses
    from pmvir.synth.generate import synthesize

    capture = synthesize(
        tmp_path / "dragon",
        mesh=_shared_model("dragon.ply"),
        views=36,
        size=(612, 512),
        material="plastic",
        focal_factor=1.2,
        mesh_up="y",
        seed=0,
    )
    with open_capture(capture) as cap:
        images, masks = [], []
        for i in range(len(cap)):
            raw, mask = cap.read_raw(i), cap.read_mask(i)
            images.append(decode_frame(raw.mosaic, cap.layout, saturated=raw.saturated, mask=mask).i_int)
            masks.append(mask)
        true = [f.camera for f in cap.frames]
        names = [f.name for f in cap.frames]
    rounds: list[int] = []
    rematch = sfm_colmap._rematch_and_refine

    def spy(rec, run, n, **kwargs):  # type: ignore[no-untyped-def]
        rounds.append(n)
        return rematch(rec, run, n, **kwargs)

    monkeypatch.setattr(sfm_colmap, "_rematch_and_refine", spy)
    model = estimate_poses(
        images,
        names,
        masks=masks,
        intrinsics=[c.K for c in true],
        options=SfmOptions(),
        workdir=tmp_path / "w",
    )
    assert "joining" in model.timings  # the mapper left views out: the join ran
    assert SfmOptions().rematch_rounds == 2 and rounds and set(rounds) == {1}, rounds
    reg = [i for i, c in enumerate(model.cameras) if c is not None]
    assert len(reg) >= 30
    assert {0, 5, 6, 7, 11, 17, 23, 29, 35} & set(reg)  # end-on views between the two sides
    left = {1, 2, 3, 4, 12, 13, 14, 15, 16, 24, 25, 26, 27, 28}
    right = {8, 9, 10, 18, 19, 20, 21, 22, 30, 31, 32, 33, 34}
    assert len(left & set(reg)) >= 12 and len(right & set(reg)) >= 12  # both sides, in one model
    est = np.stack([model.cameras[i].center for i in reg])
    tru = np.stack([true[i].center for i in reg])
    err = np.linalg.norm(umeyama(est, tru).apply(est) - tru, axis=1)
    rig = float(np.linalg.norm(tru.max(0) - tru.min(0)))
    # The frontier adjustment (sfm.frontier_weight) holds the joined poses to the masks: without it
    # the largest centre error is 1.10 % (the tracks' bend), with it 0.19 %.
    assert model.frontier is not None and model.frontier["accepted"], model.frontier
    # the report is the last adjustment's (after the silhouette registration): the masks fit the
    # poses within 0.5 px RMS (the SfM poses: 7.5 px; the true poses: 0.34 px)
    assert model.frontier["frontier_rms_after"] < 0.5, model.frontier
    # and the four end-on views SfM leaves out are registered from their masks
    # (sfm.silhouette_register_px): 36 of 36 views within 0.18 % of the rig
    assert len(model.silhouette_registered) >= 3 and len(reg) >= 35, (model.silhouette_registered, len(reg))
    assert err.max() <= 0.005 * rig, f"largest centre error {100 * err.max() / rig:.2f}% of the rig"
