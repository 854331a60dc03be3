"""``synthesize`` end to end: the capture follows the spec, decodes to the rendered truth, and is seeded."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import scipy.ndimage as ndi

from pmvir.capture import open_capture, validate_capture
from pmvir.config import DecodeOptions
from pmvir.decode import decode_capture
from pmvir.io.illumination import read_illumination
from pmvir.io.ply import read_mesh
from pmvir.sh import sh9_shading
from pmvir.synth.generate import AUTO_EXPOSURE_PERCENTILE, AUTO_EXPOSURE_TARGET, synthesize
from pmvir.synth.shapes import builtin_shape
from pmvir.synth.texture import procedural_albedo

SIZE = (128, 96)


@pytest.fixture(scope="module")
def plastic_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return synthesize(tmp_path_factory.mktemp("synth") / "plastic", shape="blob", views=6, size=SIZE, seed=5)


@pytest.fixture(scope="module")
def clean_sphere(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Noise-free, uniform-albedo plastic sphere (demosaicing is exact only where the image is smooth)."""
    return synthesize(
        tmp_path_factory.mktemp("synth") / "sphere",
        shape="sphere",
        views=3,
        size=(160, 128),
        noise=0.0,
        full_well=0.0,
        texture="uniform",
    )


def test_capture_follows_the_spec(plastic_capture: Path) -> None:
    assert validate_capture(plastic_capture) == []
    doc = json.loads((plastic_capture / "capture.json").read_text())
    assert doc["format"] == "pmvir-capture/1"
    assert doc["sensor"]["layout"] == "IMX250MYR" and doc["sensor"]["bit_depth"] == 12
    assert doc["sensor"]["aop_reference"] == "ccw"
    assert doc["intrinsics"]["width"] == SIZE[0] and doc["intrinsics"]["height"] == SIZE[1]
    assert doc["intrinsics"]["cx"] == SIZE[0] / 2 and doc["intrinsics"]["cy"] == SIZE[1] / 2
    with open_capture(plastic_capture) as cap:
        assert len(cap) == 6 and cap.has_all_poses
        for i, f in enumerate(cap.frames):
            assert f.file == f"frames/{i:03d}.png" and f.mask == f"masks/{i:03d}.png"
            samples = cap.read_samples(i)
            assert samples.dtype == np.uint16 and samples.shape == (SIZE[1], SIZE[0])
            assert samples.max() <= 4095
            cam = f.camera
            # The object (at the origin) is in front of every camera, near the image centre.
            uv, depth = cam.project(np.zeros((1, 3)))
            assert depth[0] > 0 and np.allclose(uv[0], [SIZE[0] / 2, SIZE[1] / 2], atol=1e-6)
            gt = np.load(plastic_capture / "gt" / "views" / f"{i:03d}.npz")
            assert np.array_equal(cap.read_mask(i), gt["mask"])


def test_ground_truth_files_parse(plastic_capture: Path) -> None:
    mesh = read_mesh(plastic_capture / "gt" / "mesh.ply")
    expect = builtin_shape("blob")
    np.testing.assert_allclose(mesh.vertices, expect.vertices, atol=1e-6)  # float32 in the PLY
    assert np.array_equal(mesh.faces, expect.faces)
    assert mesh.albedo is not None
    assert np.array_equal(mesh.albedo, procedural_albedo(expect.vertices, seed=5))
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    assert np.linalg.norm(hi - lo) == pytest.approx(1.0, abs=1e-5)
    illum = read_illumination(plastic_capture / "gt" / "illumination.json")
    assert [f.file for f in illum.frames] == [f"frames/{i:03d}.png" for i in range(6)]
    assert np.all(illum.scale_array() > 0)
    assert len({tuple(f.sh) for f in illum.frames}) == 6  # per-view lighting
    for i in range(6):
        gt = np.load(plastic_capture / "gt" / "views" / f"{i:03d}.npz")
        h, w = SIZE[1], SIZE[0]
        shapes = {
            "depth": (h, w),
            "normal_cam": (h, w, 3),
            "aop": (h, w),
            "dop": (h, w),
            "i_int": (h, w, 3),
            "mask": (h, w),
        }
        assert {k: gt[k].shape for k in shapes} == shapes
        assert gt["mask"].dtype == bool and all(gt[k].dtype == np.float32 for k in shapes if k != "mask")
        m = gt["mask"]
        assert np.all(gt["depth"][m] > 0) and np.all(gt["depth"][~m] == 0)
        np.testing.assert_allclose(np.linalg.norm(gt["normal_cam"][m], axis=-1), 1.0, atol=1e-5)
        assert np.all(gt["normal_cam"][m][:, 2] < 0)  # normals face the camera (-z in OpenCV axes)
        assert np.all((gt["aop"] >= 0) & (gt["aop"] < np.pi)) and np.all((gt["dop"] >= 0) & (gt["dop"] <= 1))
    info = json.loads((plastic_capture / "gt" / "synth.json").read_text())
    assert info["source"] == {"shape": "blob"} and info["options"]["seed"] == 5


def test_depth_and_normals_agree_with_the_poses(plastic_capture: Path) -> None:
    """Back-projected depth lands on the true surface; normals point away from it."""
    from scipy.spatial import cKDTree

    mesh = read_mesh(plastic_capture / "gt" / "mesh.ply")
    tree = cKDTree(mesh.vertices)
    with open_capture(plastic_capture) as cap:
        cam = cap.frames[2].camera
    gt = np.load(plastic_capture / "gt" / "views" / "002.npz")
    rows, cols = np.nonzero(gt["mask"])
    z = gt["depth"][rows, cols].astype(np.float64)
    x_cam = np.stack(
        [(cols + 0.5 - cam.K[0, 2]) / cam.K[0, 0] * z, (rows + 0.5 - cam.K[1, 2]) / cam.K[1, 1] * z, z], 1
    )
    x_world = (x_cam - cam.t) @ cam.R
    dist, idx = tree.query(x_world)
    assert np.percentile(dist, 99) < 0.01  # within about a vertex spacing of the surface
    n_world = gt["normal_cam"][rows, cols].astype(np.float64) @ cam.R
    assert np.mean(np.sum(n_world * (mesh.normals[idx]), axis=1) > 0.9) > 0.95


def test_exposure_keeps_highlights_below_full_scale(plastic_capture: Path) -> None:
    with open_capture(plastic_capture) as cap:
        raw = cap.read_raw(0)
        mask = cap.read_mask(0)
    level = float(np.median(raw.mosaic[mask]))
    assert 0.1 < level < 0.6
    assert raw.saturated[mask].mean() < 0.015
    gt = np.load(plastic_capture / "gt" / "views" / "000.npz")
    # the brightest polarizer sample I_int (1 + DoP) of the chosen percentile sits at the target
    brightest = (gt["i_int"] * (1.0 + gt["dop"][..., None]))[gt["mask"]].max(-1)
    assert np.percentile(brightest, AUTO_EXPOSURE_PERCENTILE) == pytest.approx(AUTO_EXPOSURE_TARGET, rel=0.02)


def _diff_mod_pi(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(np.angle(np.exp(2j * (a.astype(np.float64) - b)))) / 2


def test_decode_recovers_the_rendered_aop_and_dop(clean_sphere: Path, tmp_path: Path) -> None:
    # bilinear: exact wherever the noise-free image is smooth (the guided default trades a little
    # smoothing bias on this small sphere for robustness to texture and noise)
    decode_capture(clean_sphere, tmp_path, previews=False, options=DecodeOptions(demosaic="bilinear"))
    for i in range(3):
        gt = np.load(clean_sphere / "gt" / "views" / f"{i:03d}.npz")
        dec = np.load(tmp_path / f"{i:03d}.npz")
        inner = ndi.binary_erosion(gt["mask"], iterations=4) & dec["valid"]  # demosaicing footprint
        sel = inner & (gt["dop"] > 0.05)
        assert sel.sum() > 1000
        err = np.degrees(_diff_mod_pi(dec["aop"][sel], gt["aop"][sel]))
        assert np.median(err) < 0.5 and np.percentile(err, 95) < 3.0
        dop_err = np.abs(dec["dop"][inner] - gt["dop"][inner])
        assert np.median(dop_err) < 0.002 and np.percentile(dop_err, 95) < 0.02
        rel = np.abs(dec["i_int"][inner] / gt["i_int"][inner] - 1.0)
        assert np.median(rel) < 0.005


def test_decoded_lambert_intensity_is_albedo_times_gt_shading(tmp_path: Path) -> None:
    """The GT lighting predicts the decoded I_int in the spec's units: K * S(N) * rgb_scale."""
    cap_dir = synthesize(
        tmp_path / "lambert",
        shape="sphere",
        views=2,
        size=(160, 128),
        material="lambert",
        lighting="sh",
        noise=0.0,
        full_well=0.0,
        texture="uniform",
        supersample=1,
    )
    decode_capture(cap_dir, tmp_path / "dec", previews=False)
    illum = read_illumination(cap_dir / "gt" / "illumination.json")
    albedo = np.array([0.6, 0.5, 0.4])
    with open_capture(cap_dir) as cap:
        for i in range(2):
            R = cap.frames[i].camera.R
            gt = np.load(cap_dir / "gt" / "views" / f"{i:03d}.npz")
            dec = np.load(tmp_path / "dec" / f"{i:03d}.npz")
            inner = ndi.binary_erosion(gt["mask"], iterations=4) & dec["valid"]
            n_world = gt["normal_cam"][inner].astype(np.float64) @ R
            predict = albedo * sh9_shading(n_world, illum.sh_array()[i])[:, None] * illum.scale_array()[i]
            np.testing.assert_allclose(gt["i_int"][inner], predict, rtol=1e-4)  # noise-free truth: exact
            rel = np.abs(dec["i_int"][inner] / predict - 1.0)
            assert np.median(rel) < 0.003 and np.percentile(rel, 99) < 0.02  # quantization, demosaicing
            assert np.all(gt["dop"][gt["mask"]] == 0.0)


def test_same_seed_same_bytes_other_seed_other_data(tmp_path: Path) -> None:
    kw = dict(shape="sphere", views=2, size=(64, 48), lighting="envmap")
    a = synthesize(tmp_path / "a", seed=11, **kw)
    b = synthesize(tmp_path / "b", seed=11, **kw)
    c = synthesize(tmp_path / "c", seed=12, **kw)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert len(files) == 1 + 2 + 2 + 2 + 2 + 2  # capture.json, frames, masks, views, ply+illum, synth+envmap
    assert files == sorted(p.relative_to(b) for p in b.rglob("*") if p.is_file())
    for rel in files:
        assert (a / rel).read_bytes() == (b / rel).read_bytes(), rel
    assert (a / "frames/000.png").read_bytes() != (c / "frames/000.png").read_bytes()
    assert read_mesh(a / "gt/mesh.ply").albedo.tolist() != read_mesh(c / "gt/mesh.ply").albedo.tolist()


def test_loaded_mesh_is_normalized_and_rendered(tmp_path: Path) -> None:
    from pmvir.io.ply import Mesh, write_mesh_ply

    src = builtin_shape("dented")
    # A y-up, off-centre, scaled copy as a user's file would be.
    v = src.vertices[:, [0, 2, 1]] * np.array([1.0, 1.0, -1.0]) * 7.0 + np.array([3.0, -2.0, 5.0])
    write_mesh_ply(tmp_path / "in.ply", Mesh(v, src.faces[:, ::-1]))
    out = synthesize(tmp_path / "cap", mesh=tmp_path / "in.ply", views=2, size=(64, 48), mesh_up="y")
    gt = read_mesh(out / "gt" / "mesh.ply")
    np.testing.assert_allclose(gt.vertices, src.vertices, atol=1e-5)  # back to the built-in pose
    assert np.linalg.norm(gt.vertices.max(0) - gt.vertices.min(0)) == pytest.approx(1.0, abs=1e-5)
    with open_capture(out) as cap:
        assert cap.read_mask(0).mean() > 0.1


def test_save_stokes_stores_the_sensor_input(tmp_path: Path) -> None:
    """gt/views 'stokes' is the noise-free sensor input: the frame's samples are its mosaic, noise aside."""
    from pmvir.polarization.layout import IMX250MYR
    from pmvir.synth.sensor import noiseless_signal

    cap = synthesize(tmp_path / "s", shape="sphere", views=1, size=(64, 48), noise=0.0, full_well=0.0,
                     save_stokes=True)
    gt = np.load(cap / "gt" / "views" / "000.npz")
    stokes = gt["stokes"]
    assert stokes.shape == (48, 64, 3, 3) and stokes.dtype == np.float32
    np.testing.assert_allclose(stokes[..., 0] / 2, gt["i_int"], rtol=1e-5, atol=1e-7)
    with open_capture(cap) as c:
        mosaic = c.read_raw(0).mosaic
    np.testing.assert_allclose(mosaic, noiseless_signal(stokes, 1.0, IMX250MYR), atol=0.6 / 4031)
    default = synthesize(tmp_path / "d", shape="sphere", views=1, size=(64, 48))
    assert "stokes" not in np.load(default / "gt" / "views" / "000.npz")
