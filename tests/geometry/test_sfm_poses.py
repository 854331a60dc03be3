"""Poses: SfM and known-pose triangulation (pmvir.geometry.sfm.poses) against synthetic ground truth.

Captures: the session fixtures of ``conftest.py``: ``blob_capture`` (pmvir synth's textured
``blob``, 36 views of 432 x 360, focal length 1.2 x the larger side) with ``blob_views`` (its
decoded frames), ``textureless_capture`` and ``unrelated_capture``. For SfM the blob's frames
are cropped to 344 x 320 around the principal point: the focal length stays 518.4 px while
COLMAP's initial guess (1.2 x the larger side) becomes 412.8 px, 20 % off, so the focal length
is really estimated.

Thresholds, set from measurement (2026-11, pycolmap 4.2, CPU, 2 cores):

* SfM camera centres after a Umeyama similarity: largest error within 0.5 % of the scene size
  (the bounding-box diagonal of the true camera centres, 3.4 object units here; measured
  0.30 %), mean error within 0.25 % of it (measured 0.10 %).
* SfM focal length within 1 % of the truth (measured -0.3 %).
* Given intrinsics come back exactly; centres within 0.5 % (measured 0.20 %, 24 views).
* Known poses: cameras returned bit for bit; sparse points within 0.3e-2 of the true surface
  at the median (measured 0.06e-2) and 1.0e-2 at the 90th percentile (measured 0.25e-2),
  in units of the object's bounding-box diagonal.
"""

from __future__ import annotations

import itertools
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from pmvir.camera import Camera
from pmvir.capture import open_capture
from pmvir.config import SfmOptions
from pmvir.decode import decode_frame
from pmvir.errors import ReconstructionError, ShapeError
from pmvir.evaluate import SurfaceQuery
from pmvir.geometry.sfm import colmap, inputs, poses
from pmvir.geometry.sfm.align import umeyama
from pmvir.geometry.sfm.inputs import sift_image
from pmvir.geometry.sfm.matching import fundamental_matrix, sampson_error
from pmvir.geometry.sfm.poses import SparseModel, estimate_poses, write_poses_text
from pmvir.io.colmap_text import camera_from_colmap, read_colmap_text_model
from pmvir.io.ply import read_mesh
from pmvir.polarization.stokes import PolarizationImages

#: The SfM crop of the blob's 432 x 360 frames: x0, y0, width, height (centred on the principal point).
CROP = (44, 20, 344, 320)
#: Known poses need few features: the stage's tests use the same (faster) setting.
KNOWN_POSE_OPTIONS = SfmOptions(sift_affine_shape=False)


def _load(path: Path, views: list[PolarizationImages] | None = None) -> dict:
    """Names, decoded I_int, masks and true cameras of a capture (decoded here unless given)."""
    with open_capture(path) as cap:
        images, masks = [], []
        for i in range(len(cap)):
            mask = cap.read_mask(i)
            if views is None:
                raw = cap.read_raw(i)
                images.append(decode_frame(raw.mosaic, cap.layout, saturated=raw.saturated, mask=mask).i_int)
            else:
                images.append(views[i].i_int)
            masks.append(mask)
        return {
            "names": [f.name for f in cap.frames],
            "images": images,
            "masks": masks,
            "cameras": [f.camera for f in cap.frames],
        }


@pytest.fixture(scope="module")
def blob_data(blob_capture: Path, blob_views: list[PolarizationImages]) -> dict:
    return _load(blob_capture, blob_views)


@pytest.fixture(scope="module")
def sfm_views(blob_data: dict) -> dict:
    """The blob's views cropped to CROP, with the true cameras of the crop."""
    x0, y0, w, h = CROP
    cameras = []
    for c in blob_data["cameras"]:
        K = c.K.copy()
        K[0, 2] -= x0
        K[1, 2] -= y0
        cameras.append(Camera(K=K, R=c.R, t=c.t, width=w, height=h))
    return {
        "names": blob_data["names"],
        "images": [np.ascontiguousarray(a[y0:y0 + h, x0:x0 + w]) for a in blob_data["images"]],
        "masks": [np.ascontiguousarray(a[y0:y0 + h, x0:x0 + w]) for a in blob_data["masks"]],
        "cameras": cameras,
    }


@pytest.fixture(scope="module")
def known_pose_run(blob_data: dict, tmp_path_factory: pytest.TempPathFactory) -> tuple[dict, SparseModel, list]:
    calls: list[tuple[float, str]] = []
    model = estimate_poses(
        blob_data["images"], blob_data["names"], cameras=blob_data["cameras"], masks=blob_data["masks"],
        options=KNOWN_POSE_OPTIONS, workdir=tmp_path_factory.mktemp("sfm-known"),
        progress=lambda f, s: calls.append((f, s)),
    )
    return blob_data, model, calls


def _centre_errors(model: SparseModel, true: list[Camera]) -> tuple[np.ndarray, float]:
    """Per registered view, |aligned estimated centre - true centre|; and the scene size."""
    reg = [i for i, c in enumerate(model.cameras) if c is not None]
    est = np.stack([model.cameras[i].center for i in reg])
    tru = np.stack([true[i].center for i in reg])
    sim = umeyama(est, tru)
    scene = float(np.linalg.norm(tru.max(0) - tru.min(0)))
    return np.linalg.norm(sim.apply(est) - tru, axis=1), scene


def test_sfm_recovers_camera_centres_and_focal_length(sfm_views: dict, tmp_path: Path) -> None:
    model = estimate_poses(
        sfm_views["images"], sfm_views["names"], masks=sfm_views["masks"], options=SfmOptions(),
        workdir=tmp_path,
    )
    true = sfm_views["cameras"]
    assert not model.known_poses
    assert model.registered == [True] * 36
    err, scene = _centre_errors(model, true)
    assert err.max() <= 0.005 * scene, f"largest centre error {err.max():.4f} of scene size {scene:.3f}"
    assert err.mean() <= 0.0025 * scene, f"mean centre error {err.mean():.4f} of scene size {scene:.3f}"
    focal = np.array([c.K[0, 0] for c in model.cameras])
    assert np.allclose(focal, focal[0])  # one shared camera
    # 1.06% off on this capture since synthetic captures are perspective-exact (their AoP field
    # reaches I_int through demosaicing, and the features with it); 0.3% on the orthographic ones
    assert abs(focal[0] / true[0].K[0, 0] - 1.0) <= 0.015, f"focal {focal[0]:.2f}, true {true[0].K[0, 0]:.2f}"
    assert np.array_equal(model.cameras[0].K[:2, 2], true[0].K[:2, 2])  # principal point at the centre
    assert 0.0 < model.mean_reprojection_error < 1.0
    assert len(model.points) >= 500 and model.point_views is not None and len(model.point_views) == len(model.points)
    assert {"images", "features", "matching", "mapping", "refinement", "total"} <= set(model.timings)
    # SfM on denoised, not equalized images without upsampling placed every view: no other run was made
    assert model.extras[0] == {"step": "denoised_first", "seconds": model.extras[0]["seconds"], "kept": True,
                               "registered": 36}
    assert not (tmp_path / "without-upsampling").exists() and not (tmp_path / "database.db").exists()


def test_sfm_holds_given_intrinsics_fixed(sfm_views: dict, tmp_path: Path) -> None:
    """The level and upper rings' 24 views, intrinsics given: they come back exactly; poses are estimated."""
    ring = list(range(12, 36))
    true = [sfm_views["cameras"][i] for i in ring]
    K = true[0].K.copy()
    model = estimate_poses(
        [sfm_views["images"][i] for i in ring], [sfm_views["names"][i] for i in ring],
        intrinsics=[K] * len(ring), masks=[sfm_views["masks"][i] for i in ring], options=SfmOptions(),
        workdir=tmp_path,
    )
    assert model.num_registered == len(ring)
    for cam in model.cameras:
        assert np.array_equal(cam.K, K)
    err, scene = _centre_errors(model, true)
    assert err.max() <= 0.005 * scene


def test_known_poses_are_returned_bit_exact(known_pose_run: tuple, blob_capture: Path) -> None:
    data, model, _ = known_pose_run
    assert model.known_poses and model.registered == [True] * len(data["names"])
    with open_capture(blob_capture) as cap:
        fresh = [f.camera for f in cap.frames]  # independent copies read again from capture.json
    for got, given, again in zip(model.cameras, data["cameras"], fresh, strict=True):
        assert got is given
        for name in ("K", "R", "t"):
            assert np.array_equal(getattr(got, name), getattr(again, name))
    assert "triangulation" in model.timings


def test_known_pose_points_lie_on_the_true_surface(known_pose_run: tuple, blob_capture: Path) -> None:
    data, model, _ = known_pose_run
    mesh = read_mesh(blob_capture / "gt" / "mesh.ply")
    closest, _, _ = SurfaceQuery(mesh.vertices, mesh.faces).closest(model.points)
    d = np.linalg.norm(closest - model.points, axis=1)
    assert len(d) >= 500
    assert np.median(d) <= 0.3e-2 and np.percentile(d, 90) <= 1.0e-2, (np.median(d), np.percentile(d, 90))
    assert model.mean_reprojection_error < 1.0
    # Every point is seen in 3 or more views and lies in the mask of each of them.
    inside = []
    for p, views in zip(model.points, model.point_views, strict=True):
        assert len(views) >= 3 and views.min() >= 0 and views.max() < len(data["names"])
        for v in views:
            (u, vv), = model.cameras[v].project(p[None])[0]
            inside.append(bool(data["masks"][v][int(vv), int(u)]))
    assert np.mean(inside) > 0.98
    assert model.point_colors is not None and model.point_colors.shape == (len(model.points), 3)


def test_progress_goes_from_zero_to_one(known_pose_run: tuple) -> None:
    _, _, calls = known_pose_run
    fractions = [f for f, _ in calls]
    assert fractions[0] == 0.0 and fractions[-1] == 1.0
    assert all(b >= a for a, b in itertools.pairwise(fractions))
    assert all(isinstance(s, str) and s for _, s in calls)


def test_poses_written_as_colmap_text_read_back(known_pose_run: tuple, tmp_path: Path) -> None:
    _, model, _ = known_pose_run
    write_poses_text(model, tmp_path / "poses")
    cameras, images = read_colmap_text_model(tmp_path / "poses")
    assert sorted(m.name for m in images.values()) == sorted(model.names)
    for m in images.values():
        back = camera_from_colmap(cameras[m.camera_id], m)
        given = model.cameras[model.names.index(m.name)]
        assert np.array_equal(back.K, given.K) and np.array_equal(back.t, given.t)
        assert np.allclose(back.R, given.R, atol=1e-14)


def test_fundamental_matrix_and_sampson_error(blob_data: dict) -> None:
    c1, c2 = blob_data["cameras"][0], blob_data["cameras"][1]
    pts = np.random.default_rng(1).normal(scale=0.2, size=(50, 3))
    x1, x2 = c1.project(pts)[0], c2.project(pts)[0]
    F = fundamental_matrix(c1, c2)
    assert sampson_error(x1, x2, F).max() < 1e-12
    shifted = x2 + np.array([0.0, 3.0])
    assert np.median(sampson_error(x1, shifted, F)) > 0.5


def _dense_guided_matches(x1, x2, d1, d2, F, band=2.0, ratio=0.8, max_dist=0.7):
    """The epipolar-guided matching written on the whole (N1, N2) arrays: the reference."""
    h1, h2 = np.c_[x1, np.ones(len(x1))], np.c_[x2, np.ones(len(x2))]
    l2, l1 = h1 @ F.T, h2 @ F
    l2 /= np.hypot(l2[:, :1], l2[:, 1:2])
    l1 /= np.hypot(l1[:, :1], l1[:, 1:2])
    inside = (np.abs(l2 @ h2.T) < band) & (np.abs(h1 @ l1.T) < band)
    full = d1 @ d2.T
    cos = np.where(inside, full, -2.0)
    matches = set()
    for i in range(len(x1)):
        cand = np.flatnonzero(inside[i])
        if not len(cand):
            continue
        j = int(cand[np.argmax(cos[i, cand])])
        second = np.sort(cos[i, cand])[-2] if len(cand) > 1 else np.delete(full[i], j).max()
        dist = np.sqrt(np.maximum(2 - 2 * np.array([cos[i, j], second]), 0))
        if dist[0] < max_dist and dist[0] < ratio * dist[1] and int(np.argmax(cos[:, j])) == i:
            matches.add((i, j))
    return matches


@pytest.mark.parametrize("motion", ["orbit", "forward", "sideways"])
def test_guided_matches_equal_the_whole_array_reference(motion: str) -> None:
    """The band's pairs are found by sorting the features about the epipole (far away in an orbit,
    inside the image moving forward, at infinity moving sideways): the same matches as the search
    over every pair of features."""
    from pmvir.geometry.sfm.matching import _guided_matches

    rng = np.random.default_rng(3)
    pts = rng.uniform([-1, -1, 4], [1, 1, 6], (800, 3))
    centre2 = {"orbit": [2.0, 0.3, 0.5], "forward": [0.05, 0.02, 1.0], "sideways": [1.0, 0.0, 0.0]}[motion]
    c1 = Camera.from_intrinsics(300.0, 300.0, 320.0, 240.0, 640, 480, np.eye(3), np.zeros(3))
    R2 = np.eye(3)
    if motion == "orbit":
        a = np.radians(-20.0)
        R2 = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    c2 = Camera.from_intrinsics(300.0, 300.0, 320.0, 240.0, 640, 480, R2, -R2 @ np.asarray(centre2))
    x1, x2 = c1.project(pts)[0], c2.project(pts)[0]
    x2 = x2 + rng.normal(0, 0.7, x2.shape)
    x2 = np.concatenate([x2, rng.uniform([0, 0], [640, 480], (600, 2))])  # clutter
    desc = rng.normal(size=(len(pts), 128)).astype(np.float32)
    d1 = desc + 0.3 * rng.normal(size=desc.shape).astype(np.float32)
    d2 = np.concatenate([desc + 0.3 * rng.normal(size=desc.shape), rng.normal(size=(600, 128))]).astype(np.float32)
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    F = fundamental_matrix(c1, c2)
    got = {tuple(int(v) for v in m) for m in _guided_matches(x1, x2, d1, d2, F)}
    assert got == _dense_guided_matches(x1, x2, d1, d2, F)
    assert len(got) > 300 and sum(i == j for i, j in got) > 0.95 * len(got)


def test_sift_image_is_exposure_invariant_8bit() -> None:
    rng = np.random.default_rng(0)
    image = rng.uniform(0.0, 0.2, size=(64, 80, 3)).astype(np.float32)
    mask = np.zeros((64, 80), bool)
    mask[8:56, 10:70] = True
    a = sift_image(image, mask, equalize=False)
    assert a.dtype == np.uint8 and a.shape == (64, 80)
    assert np.array_equal(a, sift_image(image * 7.0, mask, equalize=False))
    assert np.percentile(a[mask], 99.5) >= 250
    assert sift_image(image, mask).shape == (64, 80)
    # not equalized, a pedestal (a black level left in the intensities) is taken off: shadows stay dark
    lifted = sift_image(image + 0.02, mask, equalize=False)
    assert np.abs(lifted.astype(int) - a).max() <= 1


def test_sift_image_denoising_flattens_noise_and_keeps_edges() -> None:
    """sift_denoise: non-local means on the 8-bit image; 0 leaves the image as it was."""
    rng = np.random.default_rng(1)
    image = np.zeros((96, 96), np.float32)  # black, grey, light grey bands
    image[:, 16:] = 0.3
    image[:, 48:] = 0.6
    noisy = np.clip(image + rng.normal(0.0, 0.01, image.shape), 0.0, None).astype(np.float32)
    plain, clean = sift_image(noisy, equalize=False), sift_image(noisy, equalize=False, denoise=10.0)
    assert np.array_equal(plain, sift_image(noisy, equalize=False, denoise=0.0))
    flat = (slice(8, 88), slice(22, 42))
    assert clean[flat].std() < 0.3 * plain[flat].std(), (clean[flat].std(), plain[flat].std())
    step = clean[:, 52].astype(float).mean() - clean[:, 44].astype(float).mean()
    assert step > 0.9 * (plain[:, 52].astype(float).mean() - plain[:, 44].astype(float).mean())


def test_denoised_images_that_place_most_views_skip_the_usual_runs(sfm_views: dict, tmp_path: Path) -> None:
    """Two views blanked: SfM on denoised, not equalized images without upsampling places the other 34
    (at least _DENOISED_LEAD of them), so the same images upsampled come next (workdir/denoised, each
    image denoised once), and as they place at least three quarters of the views, the usual runs are
    not made."""
    blank = (14, 20)
    images = [np.full_like(im, 0.3) if i in blank else im for i, im in enumerate(sfm_views["images"])]
    steps: list[tuple[float, str]] = []
    model = estimate_poses(images, sfm_views["names"], options=SfmOptions(), workdir=tmp_path,
                           progress=lambda f, s: steps.append((f, s)))
    assert model.num_registered == 34 and not model.registered[14] and not model.registered[20]
    first, kept, skipped = model.extras[0], model.extras[-2], model.extras[-1]
    assert first["step"] == "denoised_first" and not first["kept"] and 18 <= first["registered"] < 36
    assert kept["step"] == "denoised" and kept["kept"] and kept["registered"] == 34
    assert kept["registered_before"] == first["registered"]
    assert skipped["step"] == "usual_runs" and "at least 75%" in skipped["skipped"]
    # no usual run was made: neither the one without upsampling nor the one on the fallback images
    assert sorted(p.name for p in tmp_path.iterdir() if p.is_dir()) == ["denoised", "denoised-first"]
    assert model.timings["denoised_first"] == first["seconds"] > 0
    assert model.timings["total"] >= first["seconds"] + model.timings["mapping"]
    fractions = [f for f, _ in steps]
    assert fractions == sorted(fractions) and steps[-1] == (1.0, "poses done"), steps
    assert sum(s == "poses done" for _, s in steps) == 1, steps

    # the upsampled run placing too few to be kept alone: the usual runs follow, and the two are compared
    # (a tie keeps the usual model), the denoised run counted once, not made again
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(poses, "_DENOISED_KEEP", 1.01)
        both = estimate_poses(images, sfm_views["names"], options=SfmOptions(), workdir=tmp_path / "b")
    assert both.num_registered == 34
    last = both.extras[-1]
    assert last["step"] == "denoised" and not last["kept"] and last["registered_before"] == last["registered"] == 34
    assert both.timings["denoised"] == last["seconds"] > 0
    assert sum(e["step"] == "denoised" for e in both.extras) == 1
    assert (tmp_path / "b" / "without-upsampling").is_dir() and (tmp_path / "b" / "denoised").is_dir()


def test_denoised_runs_where_views_are_left_out(sfm_views: dict, tmp_path: Path) -> None:
    """Two views blanked, and the denoised images let lead only where they place every view
    (_DENOISED_LEAD 1): SfM on denoised, not equalized images without upsampling leaves them out (34 of
    36 placed), so the usual runs follow, and where they leave them out too, SfM on denoised upsampled images
    (workdir/denoised, each image denoised once for both runs) once more: the usual model is kept (a
    tie), and the extras and timings say what the denoised runs cost and gave. With denoised_runs 0
    there are no such runs."""
    blank = (14, 20)
    images = [np.full_like(im, 0.3) if i in blank else im for i, im in enumerate(sfm_views["images"])]
    names = sfm_views["names"]
    options = SfmOptions()
    steps: list[tuple[float, str]] = []
    denoised_images: list[float] = []
    real_sift_image = inputs.sift_image

    def counting(*args: Any, **kwargs: Any) -> np.ndarray:
        if kwargs.get("denoise", 0.0) > 0:
            denoised_images.append(kwargs["denoise"])
        return real_sift_image(*args, **kwargs)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(inputs, "sift_image", counting)
        mp.setattr(poses, "_DENOISED_LEAD", 1.0)
        model = estimate_poses(images, names, options=options, workdir=tmp_path / "a",
                               progress=lambda f, s: steps.append((f, s)))
    assert model.num_registered == 34
    assert len(denoised_images) == len(images)  # the last run copies the first run's denoised images
    first, last = model.extras[0], model.extras[-1]
    assert first["step"] == "denoised_first" and not first["kept"] and first["registered"] < 36
    assert last["step"] == "denoised" and last["registered_before"] == last["registered"] == 34 and not last["kept"]
    assert model.timings["denoised"] == last["seconds"] > 0
    assert model.timings["denoised_first"] == first["seconds"] > 0
    assert model.timings["total"] >= first["seconds"] + last["seconds"] + model.timings["mapping"]
    written = tmp_path / "a" / "denoised" / "images" / "00000.png"
    expected = sift_image(images[0], equalize=False, denoise=options.denoised_runs)
    assert np.array_equal(cv2.imread(str(written), cv2.IMREAD_GRAYSCALE), expected)
    assert (tmp_path / "a" / "denoised-first" / "database.db").is_file()
    fractions = [f for f, _ in steps]
    assert fractions == sorted(fractions) and steps[-1] == (1.0, "poses done"), steps
    assert sum(s == "poses done" for _, s in steps) == 1, steps
    assert any(s.endswith("(denoised images)") for _, s in steps), steps

    off = estimate_poses(images, names, options=options.model_copy(update={"denoised_runs": 0.0}),
                         workdir=tmp_path / "b")
    # (the usual runs match without guidance by default; the denoised runs always with it)
    assert not options.guided_matching and poses._denoised_options(options).guided_matching
    assert off.num_registered == 34 and not list((tmp_path / "b").glob("denoised*"))
    assert all(not e["step"].startswith("denoised") for e in off.extras)


def test_a_single_model_is_completed_once_with_the_mappers_threshold(monkeypatch: pytest.MonkeyPatch) -> None:
    """_join_models: several models are first grown with every absolute pose of PNP_MIN_INLIERS inliers
    (kept when two joined), then the largest alone with the mapper's register_min_inliers; a single model
    has no second one to confirm its poses, so only that last pass is made (the first would be thrown away)."""
    calls: list[tuple[int, int]] = []

    def grow(ranked: list, run: Any, *, min_inliers: int) -> tuple[Any, bool]:
        calls.append((len(ranked), min_inliers))
        return ranked[0], False

    monkeypatch.setattr(colmap, "_grow_and_join", grow)
    options = SfmOptions()
    run = colmap._Workspace(Path("db"), Path("images"), Path("sparse"), [], options, set(), [])
    assert colmap._join_models(["only"], run) == "only"  # type: ignore[list-item]
    assert calls == [(1, options.register_min_inliers)]
    calls.clear()
    assert colmap._join_models(["largest", "other"], run) == "largest"  # type: ignore[list-item]
    assert calls == [(2, colmap.PNP_MIN_INLIERS), (1, options.register_min_inliers)]


def _fake_model(registered: int, n: int = 6) -> SparseModel:
    cam = Camera(K=np.diag([100.0, 100.0, 1.0]), R=np.eye(3), t=np.zeros(3), width=64, height=64)
    return SparseModel(
        cameras=[cam if i < registered else None for i in range(n)], points=np.zeros((0, 3)), point_colors=None,
        point_views=None, mean_reprojection_error=0.5, registered=[i < registered for i in range(n)],
        known_poses=False, timings={"total": 1.0},
    )


def test_denoised_run_is_kept_only_with_more_views() -> None:
    """_denoised_retry keeps the model with more registered views (ties: the first), counts both runs'
    time, and fails only when both runs failed, with both reasons."""
    from pmvir.geometry.sfm.poses import _denoised_retry

    kept = _denoised_retry(_fake_model(3), None, 7.0, lambda: _fake_model(5))
    assert kept.num_registered == 5 and kept.extras[-1]["kept"] and kept.timings["without_denoising"] == 7.0
    assert kept.timings["total"] >= 7.0
    tie = _denoised_retry(_fake_model(4), None, 7.0, lambda: _fake_model(4))
    assert not tie.extras[-1]["kept"] and "denoised" in tie.timings and "without_denoising" not in tie.timings

    def fails() -> SparseModel:
        raise ReconstructionError("SfM registered 1 of 6 views")

    assert _denoised_retry(_fake_model(4), None, 7.0, fails).extras[-1]["registered"] == 0
    first = ReconstructionError("SfM registered 2 of 6 views")
    with pytest.raises(ReconstructionError, match="2 of 6 views; on denoised images: SfM registered 1 of 6"):
        _denoised_retry(None, first, 7.0, fails)
    assert _denoised_retry(None, first, 7.0, lambda: _fake_model(6)).num_registered == 6


# -- bad inputs: each a clear ReconstructionError (or ValueError for inconsistent arguments)


def test_too_few_views_is_an_error(sfm_views: dict, tmp_path: Path) -> None:
    """Said once, before any SfM run: not again for the second images."""
    images = sfm_views["images"][:2]
    with pytest.raises(ReconstructionError, match="too few views: 2 given") as info:
        estimate_poses(images, sfm_views["names"][:2], options=SfmOptions(), workdir=tmp_path,
                       fallback_images=images)
    assert str(info.value).count("too few views") == 1, str(info.value)
    assert not (tmp_path / "without-upsampling").exists()


def test_textureless_object_is_an_error_in_sfm(textureless_capture: Path, tmp_path: Path) -> None:
    data = _load(textureless_capture)
    with pytest.raises(ReconstructionError, match=r"registered 0 of 12 views.*textureless") as info:
        estimate_poses(data["images"], data["names"], masks=data["masks"], options=SfmOptions(), workdir=tmp_path)
    assert "000 (" in str(info.value)  # names the views that failed, with their feature counts


def test_textureless_object_with_known_poses_needs_no_sparse_points(textureless_capture: Path, tmp_path: Path) -> None:
    """Known poses never fail for want of sparse points: dense stereo bounds depths by the visual hull."""
    data = _load(textureless_capture)
    model = estimate_poses(
        data["images"], data["names"], cameras=data["cameras"], masks=data["masks"], options=SfmOptions(),
        workdir=tmp_path,
    )
    assert all(model.registered) and len(model.points) < SfmOptions().min_sparse_points
    assert model.cameras == data["cameras"]


def test_known_poses_upsample_sift_only_where_masks_bound_the_features(sfm_views: dict, tmp_path: Path) -> None:
    """sift_upsample 'auto' with known poses: without masks SIFT sees the views as they are (the features
    of sift_upsample false, fewer than upsampled), with masks upsampled (the features of true)."""
    images, masks, cameras = sfm_views["images"][:8], sfm_views["masks"][:8], sfm_views["cameras"][:8]
    names = sfm_views["names"][:8]

    def features(upsample: bool | str, with_masks: bool) -> list[int]:
        options = KNOWN_POSE_OPTIONS.model_copy(update={"sift_upsample": upsample})
        where = tmp_path / f"{upsample}-{with_masks}"
        model = estimate_poses(images, names, cameras=cameras, masks=masks if with_masks else None,
                               options=options, workdir=where)
        assert model.cameras == cameras
        return model.num_features

    unmasked = features("auto", False)
    assert unmasked == features(False, False)
    assert sum(unmasked) < 0.8 * sum(features(True, False))
    assert features("auto", True) == features(True, True)


def test_non_overlapping_frames_are_an_error_in_sfm(unrelated_capture: Path, tmp_path: Path) -> None:
    data = _load(unrelated_capture)
    with pytest.raises(ReconstructionError, match=r"registered 0 of 8 views.*overlap") as info:
        estimate_poses(data["images"], data["names"], masks=data["masks"], options=SfmOptions(), workdir=tmp_path)
    assert all(f"{name} (" in str(info.value) for name in data["names"])


def test_too_few_registered_views_is_an_error(sfm_views: dict, tmp_path: Path) -> None:
    """Requiring every view of a capture of two unrelated halves: the views that failed are named, with
    why the masks did not complete the model; the model is not held to the masks first (it fails anyway)."""
    front, back = [12, 13, 14, 15], [19, 20, 21, 22]  # level ring, 30 degrees apart; 120+ degrees between halves
    idx = front + back
    steps: list[str] = []
    with pytest.raises(ReconstructionError, match=r"SfM registered [0-4] of 8 views, at least 8 needed") as info:
        estimate_poses(
            [sfm_views["images"][i] for i in idx], [sfm_views["names"][i] for i in idx],
            masks=[sfm_views["masks"][i] for i in idx], options=SfmOptions(min_registered_fraction=1.0),
            workdir=tmp_path, progress=lambda f, s: steps.append(s),
        )
    text = str(info.value)
    assert sum(f"{sfm_views['names'][i]} (" in text for i in idx) >= 4
    assert "were not searched for by their masks" in text, text
    assert "holding the poses to the masks" not in steps, steps


def test_inconsistent_arguments_are_value_errors(sfm_views: dict, tmp_path: Path) -> None:
    images, names = sfm_views["images"][:3], sfm_views["names"][:3]
    with pytest.raises(ValueError, match="distinct names"):
        estimate_poses(images, names[:2], options=SfmOptions(), workdir=tmp_path)
    with pytest.raises(ValueError, match="mask"):
        estimate_poses(images, names, masks=[np.ones((4, 4), bool)] * 3, options=SfmOptions(), workdir=tmp_path)
    skewed = np.array([[500.0, 1.0, 172.0], [0.0, 500.0, 160.0], [0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="skew"):
        estimate_poses(images, names, intrinsics=[skewed] * 3, options=SfmOptions(), workdir=tmp_path)


def test_mask_erosion_option_shrinks_the_feature_masks(sfm_views: dict, tmp_path: Path) -> None:
    """sfm.mask_erosion_px reaches the masks COLMAP detects features in (0: the masks as given)."""
    import cv2

    from pmvir.geometry.sfm.inputs import write_inputs

    images, masks = sfm_views["images"][:2], sfm_views["masks"][:2]
    areas = {}
    for px in (0, 4):
        _, mask_dir, files = write_inputs(tmp_path / f"e{px}", images, masks, SfmOptions(mask_erosion_px=px))
        written = cv2.imread(str(mask_dir / f"{files[0]}.png"), cv2.IMREAD_GRAYSCALE) > 0
        areas[px] = int(written.sum())
        if px == 0:
            assert np.array_equal(written, masks[0].astype(bool))
    assert areas[4] < areas[0] - 100  # a 4 px band along the silhouette is gone


def test_sift_images_written_in_parallel_are_each_views_own(sfm_views: dict, tmp_path: Path) -> None:
    """write_inputs makes the views' SIFT images on several threads: each file is its own view's
    sift_image (denoised, with its mask), and a reused folder's files are copied, not made again."""
    import cv2

    from pmvir.geometry.sfm.inputs import sift_image, write_inputs

    images, masks = sfm_views["images"][:6], sfm_views["masks"][:6]
    opts = SfmOptions(sift_denoise=6.0)
    image_dir, _, files = write_inputs(tmp_path / "a", images, masks, opts)
    written = [cv2.imread(str(image_dir / name), cv2.IMREAD_GRAYSCALE) for name in files]
    for i, im in enumerate(written):
        assert np.array_equal(im, sift_image(images[i], masks[i], equalize=opts.sift_equalize, denoise=6.0))
    assert not np.array_equal(written[0], written[1])
    blank = [np.zeros_like(im) for im in images]  # reused: the blank images are never looked at
    again, _, _ = write_inputs(tmp_path / "b", blank, masks, opts, reuse=image_dir)
    for name, im in zip(files, written, strict=True):
        assert np.array_equal(cv2.imread(str(again / name), cv2.IMREAD_GRAYSCALE), im)


def test_features_of_masked_views_come_from_crops_at_the_full_views_positions(
    blob_data: dict, tmp_path: Path
) -> None:
    """With masks and ``crop`` (known poses), SIFT runs on each view's crop around its mask and the
    keypoints are shifted back: the same features at the same places in the full view as SIFT on the
    whole view (a few large ones near the crop's edge differ); a view whose mask is empty gets no
    features and no error."""
    import pycolmap

    from pmvir.geometry.sfm import matching
    from pmvir.geometry.sfm.inputs import write_inputs

    images = blob_data["images"][:3]
    masks = blob_data["masks"][:2] + [np.zeros_like(blob_data["masks"][2])]
    opts = SfmOptions(sift_affine_shape=False, sift_upsample=False)
    sizes = [im.shape[:2] for im in images]
    keypoints = {}
    for cropped in (True, False):
        root = tmp_path / str(cropped)
        image_dir, mask_dir, files = write_inputs(root, images, masks, opts)
        assert mask_dir is not None
        if cropped:
            boxes = matching._crop_boxes([matching._read_png(mask_dir / f"{name}.png") for name in files])
            assert boxes is not None and boxes[0][2] - boxes[0][0] < images[0].shape[1]
        matching.extract_features(
            root / "database.db", image_dir, mask_dir, files, sizes, [None] * 3, opts, crop=cropped
        )
        db = pycolmap.Database.open(str(root / "database.db"))
        keypoints[cropped] = {im.name: np.asarray(db.read_keypoints(im.image_id))[:, :2]
                              for im in db.read_all_images()}
        assert db.num_descriptors() == sum(len(k) for k in keypoints[cropped].values())
        db.close()
    for name in files[:2]:
        crop, full = keypoints[True][name], keypoints[False][name]
        assert len(full) > 100 and abs(len(crop) - len(full)) < 0.1 * len(full)
        nearest = np.linalg.norm(full[:, None, :] - crop[None, :, :], axis=2).min(axis=1)
        assert np.mean(nearest < 0.05) > 0.95
    assert len(keypoints[True][files[2]]) == len(keypoints[False][files[2]]) == 0


def test_match_ratio_option_reaches_colmap_matching(sfm_views: dict, tmp_path: Path) -> None:
    """A stricter ratio test (sfm.match_max_ratio) keeps fewer raw matches between neighbouring views."""
    import pycolmap

    from pmvir.geometry.sfm.inputs import write_inputs
    from pmvir.geometry.sfm.matching import extract_features, match_images

    images, masks = sfm_views["images"][:3], sfm_views["masks"][:3]
    counts = {}
    for ratio in (0.7, 0.95):
        opts = SfmOptions(match_max_ratio=ratio, sift_affine_shape=False, sift_upsample=False)
        image_dir, mask_dir, files = write_inputs(tmp_path / f"r{ratio}", images, masks, opts)
        database = tmp_path / f"r{ratio}" / "database.db"
        sizes = [im.shape[:2] for im in images]
        extract_features(database, image_dir, mask_dir, files, sizes, [None] * len(files), opts)
        match_images(database, len(files), opts)
        db = pycolmap.Database.open(str(database))
        counts[ratio] = db.num_matches()
        db.close()
    assert 0 < counts[0.7] < counts[0.95]


def test_views_are_numbered_in_order_and_known_pose_matches_repeat(sfm_views: dict, tmp_path: Path) -> None:
    """COLMAP numbers images as its extraction threads finish them; pmvir imports them first, so
    the image ids follow the views' order and two runs write the same known-pose matches (the
    matching visits pairs in image-id order and its ratio test is one-sided), the first matching its
    pairs on one thread, the second on two."""
    import pycolmap

    from pmvir.geometry.sfm.inputs import write_inputs
    from pmvir.geometry.sfm.matching import extract_features, match_known_poses

    images, masks, cameras = sfm_views["images"][:12], sfm_views["masks"][:12], sfm_views["cameras"][:12]
    opts = SfmOptions(sift_affine_shape=False, sift_upsample=False)
    runs = []
    for run in range(2):
        image_dir, mask_dir, files = write_inputs(tmp_path / f"run{run}", images, masks, opts)
        database = tmp_path / f"run{run}" / "database.db"
        sizes = [im.shape[:2] for im in images]
        extract_features(database, image_dir, mask_dir, files, sizes, [c.K for c in cameras], opts)
        with pytest.MonkeyPatch.context() as mp:
            mp.setenv("OMP_NUM_THREADS", str(run + 1))  # the pool's threads (pmvir.threads.usable_threads)
            match_known_poses(database, files, cameras)
        db = pycolmap.Database.open(str(database))
        try:
            name = {im.image_id: im.name for im in db.read_all_images()}
            assert [name[k] for k in sorted(name)] == files
            matches = {}
            for pair_id, m in zip(*db.read_all_matches(), strict=True):
                id1, id2 = pycolmap.pair_id_to_image_pair(pair_id)
                matches[name[id1], name[id2]] = np.asarray(m)
        finally:
            db.close()
        runs.append(matches)
    assert len(runs[0]) >= 10
    assert runs[0].keys() == runs[1].keys()
    assert all(np.array_equal(runs[0][k], runs[1][k]) for k in runs[0])


def test_rematch_rounds_lengthen_tracks_with_sfm_poses(sfm_views: dict, tmp_path: Path) -> None:
    """sfm.rematch_rounds: SfM's poses guide a second matching (as known poses do). The level and upper
    rings' 24 views, intrinsics given: more points seen in 3 or more views (measured 868 -> 1203), centres
    still within 0.5 % (measured 0.23 -> 0.30 %). The re-matching keeps no point seen in fewer than
    sfm.rematch_min_track (3) views: its two-view matches are checked by the estimated epipolar line
    alone; with rematch_min_track 2 they stay (measured: a quarter of the points). A second round (the
    default) keeps the centres within 0.5 % and adds no short track, or is skipped where the first moved
    the poses too little to change the matches; ``extras`` says what each round and the frontier
    adjustment cost and gave. With SIFT upsampling on, the features the numbers above were measured with."""
    ring = list(range(12, 36))
    true = [sfm_views["cameras"][i] for i in ring]
    results = {}
    extras = {}
    for rounds, min_track in ((0, 3), (1, 3), (1, 2), (2, 3)):
        model = estimate_poses(
            [sfm_views["images"][i] for i in ring], [sfm_views["names"][i] for i in ring],
            intrinsics=[true[0].K] * len(ring), masks=[sfm_views["masks"][i] for i in ring],
            options=SfmOptions(rematch_rounds=rounds, rematch_min_track=min_track, sift_upsample=True,
                               denoised_runs=0),
            workdir=tmp_path / f"r{rounds}-{min_track}",
        )
        assert model.num_registered == len(ring)
        assert model.point_views is not None
        err, scene = _centre_errors(model, true)
        lengths = np.array([len(v) for v in model.point_views])
        results[rounds, min_track] = (int((lengths >= 3).sum()), err.max() / scene, int((lengths < 3).sum()))
        extras[rounds, min_track] = model.extras
    assert results[1, 3][0] >= 1.2 * results[0, 3][0], results
    assert results[1, 3][1] <= 0.005, results
    assert results[1, 3][2] == 0, results
    assert results[1, 2][2] >= 0.1 * results[1, 2][0], results
    assert results[2, 3][1] <= 0.005 and results[2, 3][2] == 0, results
    assert [e["step"] for e in extras[0, 3]] == ["frontier", "silhouette_registration"], extras[0, 3]
    rounds = [e for e in extras[2, 3] if e["step"] == "rematch"]
    assert 1 <= len(rounds) <= 2 and all(e["seconds"] > 0 for e in rounds), rounds
    assert rounds[0]["after"]["observations_3plus"] > rounds[0]["before"]["observations_3plus"], rounds
    assert (len(rounds) == 2) != ("stopped" in rounds[0]), rounds  # a skipped round says why
    frontier = next(e for e in extras[2, 3] if e["step"] == "frontier")
    assert frontier["seconds"] > 0 and frontier["iterations"] < SfmOptions().frontier_iterations, frontier


def test_fallback_images_register_the_views_the_first_ones_leave_out(sfm_views: dict, tmp_path: Path) -> None:
    """estimate_poses(fallback_images=...): the lower ring's 12 views blanked in the first images (no
    features: they register in no model, 24 of 36 do) are registered from the second images, and the
    model says it came from them; only the kept model is held to the masks (the first images' 24-view model,
    discarded, is not: that was 5-23 s of wasted work on the benchmark models); first images that register
    every view are kept without a second run, and (sift_upsample 'auto') without an upsampled one (the
    runs on denoised images are off: test_denoised_runs_where_views_are_left_out)."""
    true = sfm_views["cameras"]
    blanked = [np.full_like(im, 0.3) if i < 12 else im for i, im in enumerate(sfm_views["images"])]
    steps: list[tuple[float, str]] = []
    model = estimate_poses(
        blanked, sfm_views["names"], intrinsics=[true[0].K] * 36, masks=sfm_views["masks"],
        options=SfmOptions(denoised_runs=0), workdir=tmp_path / "a", fallback_images=sfm_views["images"],
        progress=lambda f, s: steps.append((f, s)),
    )
    assert model.fallback and model.registered == [True] * 36
    assert sum(s.startswith("holding the poses to the masks") for _, s in steps) == 1, steps
    assert model.frontier is not None and model.timings["frontier"] > 0
    assert [f for f, _ in steps] == sorted(f for f, _ in steps), steps
    assert model.timings["first_images"] > 0 and model.timings["total"] > model.timings["first_images"]
    err, scene = _centre_errors(model, true)
    assert err.max() <= 0.005 * scene
    assert (tmp_path / "a" / "fallback" / "database.db").is_file()
    # sift_upsample 'auto': the run without upsampling left the blanked ring out, so it was not kept
    quick = model.extras[0]
    assert quick["step"] == "without_upsampling" and not quick["kept"] and quick["registered"] < 36, quick
    assert model.timings["without_upsampling"] > 0

    ring = list(range(12, 36))
    calls: list[tuple[float, str]] = []
    model = estimate_poses(
        [sfm_views["images"][i] for i in ring], [sfm_views["names"][i] for i in ring],
        intrinsics=[true[0].K] * len(ring), masks=[sfm_views["masks"][i] for i in ring],
        options=SfmOptions(denoised_runs=0),
        workdir=tmp_path / "b", fallback_images=[np.full_like(sfm_views["images"][i], 0.3) for i in ring],
        progress=lambda f, s: calls.append((f, s)),
    )
    assert not model.fallback and model.num_registered == len(ring)
    assert not (tmp_path / "b" / "fallback").exists()
    # every view registered without SIFT upsampling: that model is kept and no upsampled run is made
    assert model.extras[0] == {"step": "without_upsampling", "seconds": model.extras[0]["seconds"], "kept": True,
                               "registered": len(ring)}
    assert (tmp_path / "b" / "without-upsampling" / "database.db").is_file()
    assert not (tmp_path / "b" / "database.db").exists() and "without_upsampling" not in model.timings
    fractions = [f for f, _ in calls]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


def test_views_the_masks_register_spare_the_second_images(sfm_views: dict, tmp_path: Path) -> None:
    """Two views blanked in the first images: SfM leaves them out, their masks register them (the
    silhouette registration) and the second images are not run (on the armadillo a 25 s run that
    registered fewer views); ``extras`` says so."""
    true = sfm_views["cameras"]
    blank = (5, 22)
    model = estimate_poses(
        [np.full_like(im, 0.3) if i in blank else im for i, im in enumerate(sfm_views["images"])],
        sfm_views["names"], intrinsics=[true[0].K] * 36, masks=sfm_views["masks"],
        options=SfmOptions(sift_upsample=True), workdir=tmp_path, fallback_images=sfm_views["images"],
    )
    assert model.registered == [True] * 36 and not model.fallback
    assert sorted(model.silhouette_registered) == [sfm_views["names"][i] for i in blank]
    assert not (tmp_path / "fallback").exists() and "second_images" not in model.timings
    skipped = next(e for e in model.extras if e["step"] == "second_images")
    assert skipped["seconds"] == 0 and "2 view(s)" in skipped["skipped"], skipped
    err, scene = _centre_errors(model, true)
    assert err.max() <= 0.01 * scene


def test_fallback_images_must_match_the_views(sfm_views: dict, tmp_path: Path) -> None:
    with pytest.raises(ShapeError, match="fallback images"):
        estimate_poses(
            sfm_views["images"], sfm_views["names"], options=SfmOptions(), workdir=tmp_path,
            fallback_images=sfm_views["images"][:3],
        )
