"""capture.json inferred from a folder of frames (pmvir.io.inference) and opened as a capture.

Each bad input has its own test naming the error type and checking that the message names the file.
"""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest
import tifffile
from PIL import Image

from pmvir.capture import open_capture, validate_capture, zip_capture
from pmvir.errors import ConfigError, FrameError, ManifestError
from pmvir.io.exif import exif_focal_px
from pmvir.io.frames import pack_mono12p, write_frame
from pmvir.io.inference import InferOptions, infer_manifest, parse_frame_size

H, W = 24, 32


def _samples(seed: int, top: int = 4000, size: tuple[int, int] = (H, W)) -> np.ndarray:
    rng = np.random.default_rng(seed)
    s = rng.integers(0, top, size=size, dtype=np.uint16)
    s[0, 0] = top  # the largest sample, known exactly
    return s


def _folder(root: Path, n: int = 3, *, suffix: str = ".png", bit_depth: int = 12, top: int = 4000) -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        write_frame(root / f"img{i}{suffix}", _samples(i, top), bit_depth=bit_depth)
    return root


def test_twelve_bit_data_in_sixteen_bit_pngs_is_twelve_bit_with_the_default_layout(tmp_path):
    inferred = infer_manifest(_folder(tmp_path / "f"))
    m = inferred.manifest
    assert m.sensor.layout == "IMX250MYR" and m.sensor.bit_depth == 12 and m.sensor.white == 4095
    assert m.sensor.black_level == 0 and m.intrinsics is None and m.raw is None
    assert [f.file for f in m.frames] == ["frames/img0.png", "frames/img1.png", "frames/img2.png"]
    assert all(f.cam_from_world is None and f.mask is None for f in m.frames)
    assert inferred.frames_dir == tmp_path / "f"
    assert any("bit depth 12" in n and "4000" in n for n in inferred.notes)
    assert any("layout IMX250MYR" in n for n in inferred.notes)


def test_frames_that_never_go_near_zero_point_at_a_black_level_without_setting_one(tmp_path):
    dark = [n for n in infer_manifest(_folder(tmp_path / "dark")).notes if n.startswith("black level")]
    assert dark == ["black level 0: none given (--black-level), the files hold none"]
    root = tmp_path / "pedestal"
    root.mkdir()
    for i in range(2):  # a 64 DN pedestal under every sample, as pmvir synth's sensor and many cameras add
        samples = 64 + _samples(i, 3000)
        samples[1, 1] = 64
        write_frame(root / f"img{i}.png", samples, bit_depth=12)
    inferred = infer_manifest(root)
    assert inferred.manifest.sensor.black_level == 0  # a hint only: the level stays the user's to give
    (note,) = [n for n in inferred.notes if n.startswith("black level")]
    assert "no frame goes below 64" in note and "--black-level" in note


def test_sixteen_bit_data_and_eight_bit_files(tmp_path):
    assert infer_manifest(_folder(tmp_path / "a", bit_depth=16, top=60000)).manifest.sensor.bit_depth == 16
    assert infer_manifest(_folder(tmp_path / "b", bit_depth=14, top=9000)).manifest.sensor.bit_depth == 14
    assert infer_manifest(_folder(tmp_path / "c", bit_depth=8, top=200)).manifest.sensor.bit_depth == 8


def test_options_choose_the_layout_and_black_level(tmp_path):
    m = infer_manifest(_folder(tmp_path / "f"), InferOptions(layout="IMX250MZR", black_level=64)).manifest
    assert m.sensor.layout == "IMX250MZR" and m.sensor.black_level == 64


def test_frames_sort_naturally_and_masks_are_picked_up(tmp_path):
    root = tmp_path / "cap"
    (root / "frames").mkdir(parents=True)
    (root / "masks").mkdir()
    for name in ("v10", "v2", "v1"):
        write_frame(root / "frames" / f"{name}.tif", _samples(1), bit_depth=12)
    write_frame(root / "masks" / "v2.png", np.full((H, W), 255, np.uint8), bit_depth=8)
    (root / "frames" / ".hidden.png").write_bytes(b"junk")
    m = infer_manifest(root).manifest
    assert [f.file for f in m.frames] == ["frames/v1.tif", "frames/v2.tif", "frames/v10.tif"]
    assert [f.mask for f in m.frames] == [None, "masks/v2.png", None]
    with open_capture(root) as cap:
        assert cap.inferred is not None and cap.read_mask(1).all() and cap.read_mask(0) is None


def test_a_bare_folder_opens_as_a_capture_whose_samples_are_the_files(tmp_path):
    root = _folder(tmp_path / "f")
    with open_capture(root, infer=InferOptions(black_level=100)) as cap:
        assert len(cap) == 3 and cap.validate() == []
        raw = cap.read_raw(2)
        assert np.array_equal(raw.samples, _samples(2))
        assert np.allclose(raw.mosaic, (_samples(2) - 100.0) / (4095 - 100.0))
    assert validate_capture(root) == []


def test_a_zip_of_bare_frames_opens_as_a_capture(tmp_path):
    root = _folder(tmp_path / "f")
    zip_capture(root, tmp_path / "frames.zip", top_folder="mine")
    with open_capture(tmp_path / "frames.zip", workdir=tmp_path) as cap:
        assert len(cap) == 3 and cap.inferred is not None and cap.validate() == []


def test_headerless_frames_need_their_size_and_give_their_encoding(tmp_path):
    root = tmp_path / "raw"
    root.mkdir()
    s = _samples(0)
    (root / "a.raw").write_bytes(pack_mono12p(s))
    (root / "b.raw").write_bytes(pack_mono12p(_samples(1)))
    with pytest.raises(FrameError, match=r"a\.raw: a headerless frame: give its size"):
        infer_manifest(root)
    m = infer_manifest(root, InferOptions(frame_size=(W, H))).manifest
    assert m.raw is not None and m.raw.dtype == "mono12p" and m.sensor.bit_depth == 12
    with open_capture(root, infer=InferOptions(frame_size=(W, H))) as cap:
        assert np.array_equal(cap.read_samples(0), s)
    be = tmp_path / "be"
    be.mkdir()
    (be / "a.bin").write_bytes(s.astype(">u2").tobytes())
    assert infer_manifest(be, InferOptions(frame_size=(W, H))).manifest.raw.dtype == "uint16be"  # type: ignore[union-attr]
    with pytest.raises(FrameError, match=r"a\.bin: 1536 bytes fits no encoding of 16x24"):
        infer_manifest(be, InferOptions(frame_size=(16, 24)))


def test_dng_black_and_white_levels_come_from_the_file(tmp_path):
    root = tmp_path / "dng"
    root.mkdir()
    for i in range(2):
        write_frame(root / f"{i}.dng", _samples(i), bit_depth=12)
    inferred = infer_manifest(root)
    assert inferred.manifest.sensor.bit_depth == 12 and inferred.manifest.sensor.white == 4095
    assert inferred.manifest.sensor.black_level == 0
    assert any("white level 4095: from 0.dng" in n for n in inferred.notes)
    assert infer_manifest(root, InferOptions(black_level=32)).manifest.sensor.black_level == 32


def test_exif_focal_length_gives_estimated_intrinsics(tmp_path):
    """FocalLength 8 mm on the IMX250's 3.45 um pixels in PNG EXIF; 35 mm equivalent in a TIFF."""
    root = tmp_path / "exif"
    root.mkdir()
    exif = Image.Exif()
    exif[37386] = 8.0  # FocalLength, mm
    for i in range(2):
        Image.fromarray(_samples(i)).save(root / f"{i}.png", exif=exif)
    m = infer_manifest(root).manifest
    assert m.intrinsics is not None and m.intrinsics.estimated
    assert m.intrinsics.fx == pytest.approx(8.0 / 0.00345) and m.intrinsics.fy == pytest.approx(8.0 / 0.00345)
    assert (m.intrinsics.cx, m.intrinsics.cy, m.intrinsics.width, m.intrinsics.height) == (W / 2, H / 2, W, H)
    tif = tmp_path / "f.tif"
    tifffile.imwrite(tif, _samples(0), photometric="minisblack", extratags=[(41989, 3, 1, 43, True)])
    focal = exif_focal_px(tif, W, H)
    assert focal is not None and focal.fx == pytest.approx(43 * np.hypot(W, H) / np.hypot(36, 24))
    plane = tmp_path / "g.tif"
    tifffile.imwrite(
        plane, _samples(0), photometric="minisblack",
        extratags=[(37386, 5, 1, (12, 1), True), (41486, 5, 1, (290, 1), True), (41488, 3, 1, 4, True)],
    )
    focal = exif_focal_px(plane, W, H)
    assert focal is not None and focal.fx == pytest.approx(12 * 290) and focal.fy == pytest.approx(12 * 290)


def test_frames_of_different_sizes_are_an_error_naming_the_file(tmp_path):
    root = _folder(tmp_path / "f", n=2)
    write_frame(root / "img9.png", _samples(3, size=(H, W + 4)), bit_depth=12)
    with pytest.raises(FrameError, match=r"img9\.png: size 36x24 differs from img0\.png's 32x24"):
        infer_manifest(root)
    cap = tmp_path / "cap"  # frames in frames/: named as they lie there
    (cap / "frames").mkdir(parents=True)
    for p in root.iterdir():
        p.rename(cap / "frames" / p.name)
    with pytest.raises(FrameError, match=r"frames/img9\.png: size 36x24 differs from frames/img0\.png's"):
        open_capture(cap)


def test_an_unreadable_frame_is_an_error_naming_the_file(tmp_path):
    root = _folder(tmp_path / "f", n=2)
    (root / "img5.png").write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    with pytest.raises(FrameError, match=r"img5\.png: truncated PNG"):
        infer_manifest(root)


def test_a_size_the_mosaic_cannot_tile_is_an_error_naming_the_file(tmp_path):
    root = tmp_path / "odd"
    root.mkdir()
    write_frame(root / "a.png", _samples(0, size=(H, 30)), bit_depth=12)
    with pytest.raises(FrameError, match=r"a\.png: size 30x24: width and height must be multiples of 4"):
        infer_manifest(root)
    assert infer_manifest(root, InferOptions(layout="IMX250MZR")).manifest.sensor.layout == "IMX250MZR"


def test_no_frames_at_all_is_an_error_naming_the_folder(tmp_path):
    (tmp_path / "empty").mkdir()
    (tmp_path / "empty" / "photo.jpg").write_bytes(b"jpeg")
    with pytest.raises(ManifestError, match=r"capture\.json: not found in .*empty, and no frame files.*photo\.jpg"):
        open_capture(tmp_path / "empty")
    z = tmp_path / "none.zip"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("readme.txt", "no frames")
    with pytest.raises(ManifestError, match=r"none\.zip: no capture\.json, and no frame files"):
        open_capture(z, workdir=tmp_path)


def test_frames_of_one_name_in_two_formats_are_an_error(tmp_path):
    root = _folder(tmp_path / "f", n=1)
    write_frame(root / "img0.tif", _samples(0), bit_depth=12)
    with pytest.raises(FrameError, match=r"img0\.(png|tif): has the same name as"):
        infer_manifest(root)


def test_bad_options_are_config_errors():
    with pytest.raises(ConfigError, match="frame size '2448'"):
        parse_frame_size("2448")
    assert parse_frame_size("2448x2048") == (2448, 2048)
    with pytest.raises(ConfigError, match="layout must be one of"):
        InferOptions(layout="X")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="black level must be >= 0"):
        InferOptions(black_level=-1)
