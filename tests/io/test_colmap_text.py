"""COLMAP text models (pmvir.io.colmap_text): round trips, COLMAP's own examples, pycolmap interop."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from pmvir.camera import Camera, look_at
from pmvir.io.colmap_text import (
    ColmapCamera,
    ColmapFormatError,
    ColmapImage,
    camera_from_colmap,
    image_from_camera,
    pinhole_from_camera,
    qvec_from_rotmat,
    read_cameras_text,
    read_colmap_text_model,
    read_images_text,
    rotmat_from_qvec,
    write_colmap_text_model,
)


def sample_model():
    rng = np.random.default_rng(0)
    cameras = [
        ColmapCamera(1, "PINHOLE", 2448, 2048, (2900.123456789012, 2901.5, 1224.25, 1023.75)),
        ColmapCamera(3, "SIMPLE_RADIAL", 640, 480, (500.0, 320.0, 240.0, -0.0218531)),
    ]
    images = []
    for i in range(4):
        q = Rotation.random(random_state=i).as_quat()  # x y z w
        qvec = np.array([q[3], *q[:3]])
        n = 0 if i == 2 else 3 + i  # image 2 has no keypoints: an empty POINTS2D line
        ids = rng.integers(-1, 50, n)
        images.append(
            ColmapImage(
                10 + i,
                qvec,
                rng.normal(0, 2, 3),
                1 if i % 2 else 3,
                f"frames/{i:03d}.png",
                rng.uniform(0, 600, (n, 2)),
                ids,
            )
        )
    return cameras, images


def test_round_trip_is_lossless(tmp_path):
    cameras, images = sample_model()
    write_colmap_text_model(tmp_path, cameras, images)
    cams, imgs = read_colmap_text_model(tmp_path)
    assert sorted(cams) == [1, 3] and sorted(imgs) == [10, 11, 12, 13]
    for c in cameras:
        assert cams[c.camera_id] == c
    for m in images:
        r = imgs[m.image_id]
        assert r.name == m.name and r.camera_id == m.camera_id
        sign = np.sign(r.qvec[0] * m.qvec[0]) or 1.0
        np.testing.assert_array_equal(r.qvec * sign, m.qvec / np.linalg.norm(m.qvec))
        np.testing.assert_array_equal(r.tvec, m.tvec)
        np.testing.assert_array_equal(r.points2d, m.points2d)
        np.testing.assert_array_equal(r.point3d_ids, m.point3d_ids)
    assert (tmp_path / "points3D.txt").is_file()
    lines = (tmp_path / "images.txt").read_text().splitlines()
    assert lines[0] == "# Image list with two lines of data per image:"
    assert lines[4 + 2 * 2 + 1] == ""  # the POINTS2D line of the third image is present and empty


def test_reads_colmap_documentation_examples(tmp_path):
    # Verbatim from colmap.github.io/format.html (cameras.txt and images.txt sections).
    (tmp_path / "cameras.txt").write_text(
        "# Camera list with one line of data per camera:\n"
        "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]\n"
        "# Number of cameras: 3\n"
        "1 SIMPLE_PINHOLE 3072 2304 2559.81 1536 1152\n"
        "2 PINHOLE 3072 2304 2560.56 2560.56 1536 1152\n"
        "3 SIMPLE_RADIAL 3072 2304 2559.69 1536 1152 -0.0218531\n"
    )
    (tmp_path / "images.txt").write_text(
        "# Image list with two lines of data per image:\n"
        "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME\n"
        "#   POINTS2D[] as (X, Y, POINT3D_ID)\n"
        "# Number of images: 2, mean observations per image: 2\n"
        "1 0.851773 0.0165051 0.503764 -0.142941 -0.737434 1.02973 3.74354 1 P1180141.JPG\n"
        "2362.39 248.498 58396 1784.7 268.254 59027 1784.7 268.254 -1\n"
        "2 0.851773 0.0165051 0.503764 -0.142941 -0.737434 1.02973 3.74354 1 P1180142.JPG\n"
        "1190.83 663.957 23056 1258.77 640.354 59070\n"
    )
    cams = read_cameras_text(tmp_path / "cameras.txt")
    assert cams[1].model == "SIMPLE_PINHOLE" and cams[1].params == (2559.81, 1536.0, 1152.0)
    np.testing.assert_allclose(cams[2].K(), [[2560.56, 0, 1536], [0, 2560.56, 1152], [0, 0, 1]])
    assert cams[3].params[-1] == -0.0218531
    imgs = read_images_text(tmp_path / "images.txt")
    assert imgs[1].name == "P1180141.JPG" and imgs[2].name == "P1180142.JPG"
    np.testing.assert_array_equal(imgs[1].point3d_ids, [58396, 59027, -1])
    np.testing.assert_allclose(imgs[2].points2d, [[1190.83, 663.957], [1258.77, 640.354]])
    # The documented centre -R^T t.
    R = rotmat_from_qvec([0.851773, 0.0165051, 0.503764, -0.142941])
    np.testing.assert_allclose(imgs[1].center, -R.T @ np.array([-0.737434, 1.02973, 3.74354]))


def test_pycolmap_reads_what_we_write_and_we_read_what_it_writes(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    cameras, images = sample_model()
    images = [
        ColmapImage(m.image_id, m.qvec, m.tvec, m.camera_id, m.name, m.points2d, np.full(len(m.points2d), -1))
        for m in images
    ]  # no 3D points in the model
    write_colmap_text_model(tmp_path / "ours", cameras, images)
    rec = pycolmap.Reconstruction()
    rec.read_text(str(tmp_path / "ours"))
    assert rec.num_images() == 4 and rec.num_cameras() == 2
    for m in images:
        im = rec.image(m.image_id)
        assert im.name == m.name and im.camera_id == m.camera_id and im.num_points2D() == len(m.points2d)
        np.testing.assert_allclose(im.cam_from_world().rotation.matrix(), m.R, atol=1e-12)
        np.testing.assert_allclose(im.cam_from_world().translation, m.tvec, atol=1e-12)
        np.testing.assert_allclose(im.projection_center(), m.center, atol=1e-9)
    np.testing.assert_allclose(rec.camera(1).params, cameras[0].params)
    (tmp_path / "theirs").mkdir()
    rec.write_text(str(tmp_path / "theirs"))
    cams, imgs = read_colmap_text_model(tmp_path / "theirs")
    assert cams[3] == cameras[1]
    for m in images:
        np.testing.assert_allclose(imgs[m.image_id].R, m.R, atol=1e-12)
        np.testing.assert_allclose(imgs[m.image_id].points2d, m.points2d, atol=1e-9)


def test_quaternion_conversions():
    for seed in range(50):
        R = Rotation.random(random_state=seed).as_matrix()
        q = qvec_from_rotmat(R)
        assert q[0] >= 0 and np.linalg.norm(q) == pytest.approx(1.0)
        np.testing.assert_allclose(rotmat_from_qvec(q), R, atol=1e-12)
    # Half turns (w = 0) and the identity.
    for R in (np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1]), np.eye(3)):
        np.testing.assert_allclose(rotmat_from_qvec(qvec_from_rotmat(R)), R, atol=1e-12)
    # Hamilton convention: a +90 degree turn about z is (cos 45, 0, 0, sin 45).
    np.testing.assert_allclose(
        rotmat_from_qvec([np.sqrt(0.5), 0, 0, np.sqrt(0.5)]), [[0, -1, 0], [1, 0, 0], [0, 0, 1]], atol=1e-12
    )


def test_pmvir_camera_round_trip():
    R, t = look_at(np.array([1.0, -3.0, 2.0]), np.zeros(3))
    cam = Camera.from_intrinsics(900.0, 910.0, 320.5, 240.5, 640, 480, R, t)
    back = camera_from_colmap(pinhole_from_camera(1, cam), image_from_camera(1, 1, "frames/000.png", cam))
    np.testing.assert_allclose(back.K, cam.K)
    np.testing.assert_allclose(back.R, cam.R, atol=1e-12)
    np.testing.assert_allclose(back.center, cam.center, atol=1e-12)


def test_wrong_parameter_count_raises(tmp_path):
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 10 10 5 5 5\n")
    with pytest.raises(ColmapFormatError, match=r"cameras.txt:1: .*PINHOLE takes 4 parameters, got 3"):
        read_cameras_text(tmp_path / "cameras.txt")


def test_unknown_camera_model_raises(tmp_path):
    (tmp_path / "cameras.txt").write_text("# c\n1 MYSTERY 10 10 5\n")
    with pytest.raises(ColmapFormatError, match=r"cameras.txt:2: .*unknown COLMAP camera model"):
        read_cameras_text(tmp_path / "cameras.txt")


def test_short_image_line_raises_with_line_number(tmp_path):
    (tmp_path / "images.txt").write_text("# x\n1 1 0 0 0 0 0 0 1\n\n")
    with pytest.raises(ColmapFormatError, match=r"images.txt:2: .*10 fields"):
        read_images_text(tmp_path / "images.txt")


def test_bad_points2d_line_raises(tmp_path):
    (tmp_path / "images.txt").write_text("1 1 0 0 0 0 0 0 1 a.png\n1.0 2.0\n")
    with pytest.raises(ColmapFormatError, match="multiple of 3"):
        read_images_text(tmp_path / "images.txt")


def test_name_with_whitespace_cannot_be_written():
    with pytest.raises(ColmapFormatError, match="whitespace"):
        ColmapImage(1, [1, 0, 0, 0], [0, 0, 0], 1, "my frame.png")


def test_missing_file_raises(tmp_path):
    with pytest.raises(ColmapFormatError, match="no such file"):
        read_images_text(tmp_path / "images.txt")


def test_image_with_unknown_camera_raises(tmp_path):
    cams, imgs = sample_model()
    with pytest.raises(ColmapFormatError, match="unknown CAMERA_ID"):
        write_colmap_text_model(tmp_path, cams[:1], imgs)
    write_colmap_text_model(tmp_path, cams, imgs)
    (tmp_path / "cameras.txt").write_text("1 PINHOLE 10 10 5 5 5 5\n")
    with pytest.raises(ColmapFormatError, match="unknown CAMERA_ID 3"):
        read_colmap_text_model(tmp_path)
