"""Captures (pmvir.capture): manifest model, folder and zip reading, normalization, validation.

Each bad input has its own test naming the error type and checking that the message names the file.
"""

from __future__ import annotations

import json
import os
import stat
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pmvir.camera import look_at
from pmvir.capture import (
    CamFromWorld,
    Capture,
    CaptureManifest,
    FrameEntry,
    Intrinsics,
    RawSpec,
    SensorSpec,
    open_capture,
    parse_manifest,
    validate_capture,
    write_capture_manifest,
    zip_capture,
)
from pmvir.errors import CaptureError, FrameError, ManifestError
from pmvir.io.frames import write_frame

H, W = 8, 12


def make_capture(
    root: Path,
    *,
    n: int = 3,
    size: tuple[int, int] = (H, W),
    layout: str = "IMX250MYR",
    suffix: str = ".png",
    bit_depth: int = 12,
    black: float = 0.0,
    white: float | None = None,
    exposures: list[float] | None = None,
    poses: bool = True,
    intrinsics: bool = True,
    masks: bool = False,
    raw_dtype: str | None = None,
    seed: int = 0,
) -> tuple[CaptureManifest, list[np.ndarray]]:
    """Write a small valid capture under root; returns its manifest and the samples written."""
    rng = np.random.default_rng(seed)
    (root / "frames").mkdir(parents=True, exist_ok=True)
    h, w = size
    entries, all_samples = [], []
    for i in range(n):
        s = rng.integers(0, 1 << bit_depth, size=(h, w)).astype(np.uint16)
        file = f"frames/{i:03d}{suffix}"
        write_frame(root / file, s, bit_depth=bit_depth, raw_dtype=raw_dtype)
        all_samples.append(s)
        mask = None
        if masks:
            (root / "masks").mkdir(exist_ok=True)
            mask = f"masks/{i:03d}.png"
            write_frame(root / mask, (rng.random((h, w)) > 0.5).astype(np.uint8) * 255, bit_depth=8)
        pose = None
        if poses:
            angle = 2 * np.pi * i / n
            R, t = look_at(np.array([3 * np.cos(angle), 3 * np.sin(angle), 1.0]), np.zeros(3))
            pose = CamFromWorld.from_arrays(R, t)
        entries.append(
            FrameEntry(file=file, mask=mask, cam_from_world=pose,
                       exposure=1.0 if exposures is None else exposures[i])
        )
    manifest = CaptureManifest(
        sensor=SensorSpec(layout=layout, bit_depth=bit_depth, black_level=black, white_level=white),
        intrinsics=Intrinsics(width=w, height=h, fx=20.0, fy=20.0, cx=w / 2, cy=h / 2) if intrinsics else None,
        raw=RawSpec(width=w, height=h, dtype=raw_dtype) if raw_dtype else None,
        frames=entries,
    )
    write_capture_manifest(root, manifest)
    return manifest, all_samples


def edit_manifest(root: Path, edit) -> None:
    doc = json.loads((root / "capture.json").read_text())
    edit(doc)
    (root / "capture.json").write_text(json.dumps(doc))


# ----------------------------------------------------------------------------- reading


def test_folder_capture_normalizes_samples(tmp_path):
    _, samples = make_capture(tmp_path, black=64, white=4000, exposures=[1.0, 2.0, 0.5])
    with open_capture(tmp_path) as cap:
        assert len(cap) == 3
        assert [f.name for f in cap.frames] == ["000", "001", "002"]
        assert cap.frames[1].file == "frames/001.png"
        for i, exposure in enumerate([1.0, 2.0, 0.5]):
            rf = cap.read_raw(i)
            np.testing.assert_array_equal(rf.samples, samples[i])
            expected = (samples[i].astype(np.float64) - 64) / (4000 - 64) / exposure
            assert rf.mosaic.dtype == np.float32 and rf.mosaic.shape == (H, W)
            np.testing.assert_allclose(rf.mosaic, expected, rtol=1e-6, atol=1e-7)
            np.testing.assert_array_equal(rf.saturated, samples[i] >= 4000)
            assert rf.exposure == exposure
        assert cap.validate() == []


def test_saturated_mask_and_level_edges(tmp_path):
    make_capture(tmp_path, n=1, black=100, white=3000)
    s = np.full((H, W), 1000, np.uint16)
    s[0, 0], s[0, 1], s[0, 2], s[0, 3] = 2999, 3000, 4095, 50
    write_frame(tmp_path / "frames/000.png", s, bit_depth=12)
    with open_capture(tmp_path) as cap:
        rf = cap.read_raw(0)
    assert rf.saturated[0, :4].tolist() == [False, True, True, False]
    assert rf.saturated.sum() == 2
    assert rf.mosaic[0, 1] == pytest.approx(1.0)
    assert rf.mosaic[0, 3] == pytest.approx(-50 / 2900)  # below black: not clipped
    assert rf.mosaic[1, 1] == pytest.approx(900 / 2900)


def test_white_level_defaults_to_full_scale(tmp_path):
    make_capture(tmp_path, n=1, bit_depth=10)
    with open_capture(tmp_path) as cap:
        assert cap.sensor.white_level == 1023
        assert cap.sensor.black_level == 0


def test_open_capture_json_path(tmp_path):
    make_capture(tmp_path, n=1)
    with open_capture(tmp_path / "capture.json") as cap:
        assert cap.root == tmp_path


def test_cameras_and_known_pose_mode(tmp_path):
    make_capture(tmp_path)
    with open_capture(tmp_path) as cap:
        assert cap.has_all_poses
        cam = cap.frames[0].camera
        assert cam is not None and (cam.width, cam.height) == (W, H)
        np.testing.assert_allclose(cam.K, [[20, 0, W / 2], [0, 20, H / 2], [0, 0, 1]])
        R, _ = look_at(np.array([3.0, 0.0, 1.0]), np.zeros(3))
        np.testing.assert_allclose(cam.R, R, atol=1e-12)
        np.testing.assert_allclose(cam.center, [3.0, 0.0, 1.0], atol=1e-12)
        assert cap.index("002") == 2


def test_one_missing_pose_leaves_known_pose_mode(tmp_path):
    make_capture(tmp_path)
    edit_manifest(tmp_path, lambda d: d["frames"][1].pop("cam_from_world"))
    with open_capture(tmp_path) as cap:
        assert not cap.has_all_poses
        assert cap.frames[1].camera is None and cap.frames[0].camera is not None


def test_no_intrinsics_no_known_pose_mode(tmp_path):
    make_capture(tmp_path, intrinsics=False)
    with open_capture(tmp_path) as cap:
        assert not cap.has_all_poses
        assert cap.frames[0].cam_from_world is not None and cap.frames[0].intrinsics is None
        assert cap.validate() == []


def test_per_frame_intrinsics_win_and_set_the_size(tmp_path):
    make_capture(tmp_path)
    write_frame(tmp_path / "frames/001.png", np.zeros((12, 16), np.uint16), bit_depth=12)
    own = {"model": "PINHOLE", "width": 16, "height": 12, "fx": 30.0, "fy": 31.0, "cx": 8.0, "cy": 6.0}
    edit_manifest(tmp_path, lambda d: d["frames"][1].update(intrinsics=own))
    with open_capture(tmp_path) as cap:
        assert cap.frames[1].intrinsics.fx == 30.0 and cap.frames[0].intrinsics.fx == 20.0
        assert cap.frames[1].camera.K[1, 1] == 31.0
        assert cap.validate() == []
        assert cap.read_raw(1).mosaic.shape == (12, 16)


def test_layout_defaults():
    m = SensorSpec(layout="IMX250MYR", bit_depth=12)
    assert m.layout_value().polarizer_block == ((90, 45), (135, 0)) and m.layout_value().bayer == "RGGB"
    assert SensorSpec(layout="IMX250MZR", bit_depth=12).layout_value().bayer is None


def test_layout_overrides(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["sensor"].update(polarizer_block=[[0, 45], [135, 90]], bayer="BGGR"))
    with open_capture(tmp_path) as cap:
        assert cap.layout.polarizer_block == ((0, 45), (135, 90))
        assert cap.layout.bayer == "BGGR"


def test_aop_reference_cw_is_mapped_to_ccw(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["sensor"].update(aop_reference="cw"))
    with open_capture(tmp_path) as cap:
        # a label a in the cw sense is the angle -a mod 180 in the ccw sense
        assert cap.layout.polarizer_block == ((90, 135), (45, 0))


def test_headerless_mono12p_capture(tmp_path):
    _, samples = make_capture(tmp_path, suffix=".raw", raw_dtype="mono12p", layout="IMX250MZR", size=(6, 10))
    with open_capture(tmp_path) as cap:
        assert cap.validate() == []
        np.testing.assert_array_equal(cap.read_raw(2).samples, samples[2])
        assert cap.frame_size(0) == (6, 10)


@pytest.mark.parametrize("suffix", [".tif", ".dng"])
def test_tiff_and_dng_captures(tmp_path, suffix):
    _, samples = make_capture(tmp_path, n=2, suffix=suffix, size=(24, 24))
    with open_capture(tmp_path) as cap:
        assert cap.validate() == []
        np.testing.assert_array_equal(cap.read_raw(1).samples, samples[1])


def test_masks(tmp_path):
    make_capture(tmp_path, masks=True)
    with open_capture(tmp_path) as cap:
        m = cap.read_mask(0)
        assert m.dtype == bool and m.shape == (H, W) and 0 < m.sum() < H * W
    make_capture(tmp_path / "nomask", n=1)
    with open_capture(tmp_path / "nomask") as cap:
        assert cap.read_mask(0) is None


def test_manifest_written_by_model_round_trips(tmp_path):
    manifest, _ = make_capture(tmp_path, masks=True, black=10)
    again = parse_manifest((tmp_path / "capture.json").read_bytes())
    assert again == manifest
    assert json.loads((tmp_path / "capture.json").read_text())["format"] == "pmvir-capture/1"


def test_validate_with_headers_only(tmp_path):
    make_capture(tmp_path, masks=True)
    with open_capture(tmp_path) as cap:
        assert cap.validate(decode_frames=False) == []


# ----------------------------------------------------------------------------- zip


def _same_capture(a: Capture, b: Capture) -> None:
    assert a.manifest == b.manifest
    assert a.layout == b.layout
    for i in range(len(a)):
        ra, rb = a.read_raw(i), b.read_raw(i)
        np.testing.assert_array_equal(ra.samples, rb.samples)
        np.testing.assert_array_equal(ra.mosaic, rb.mosaic)
        np.testing.assert_array_equal(a.read_mask(i), b.read_mask(i))


@pytest.mark.parametrize("top_folder", [None, "my capture"])
def test_zip_reads_like_the_folder(tmp_path, top_folder):
    make_capture(tmp_path / "cap", masks=True, black=32)
    zip_capture(tmp_path / "cap", tmp_path / "cap.zip", top_folder=top_folder)
    work = tmp_path / "work"
    work.mkdir()
    with open_capture(tmp_path / "cap") as folder, open_capture(tmp_path / "cap.zip", workdir=work) as zipped:
        assert zipped.root != folder.root and zipped.root.is_relative_to(work)
        _same_capture(folder, zipped)
        assert zipped.validate() == []
    assert list(work.iterdir()) == []  # temporary extraction removed on exit


def test_zip_extraction_removed_on_close_without_with(tmp_path):
    make_capture(tmp_path / "cap", n=1)
    zip_capture(tmp_path / "cap", tmp_path / "cap.zip")
    cap = open_capture(tmp_path / "cap.zip", workdir=tmp_path)
    root = cap.root
    assert (root / "capture.json").is_file()
    cap.close()
    assert not root.exists()


def _zip_with(tmp_path: Path, extra: list[tuple[zipfile.ZipInfo | str, bytes]]) -> Path:
    """A valid capture zipped, plus extra members."""
    make_capture(tmp_path / "cap", n=1)
    z = tmp_path / "cap.zip"
    zip_capture(tmp_path / "cap", z)
    with zipfile.ZipFile(z, "a", compression=zipfile.ZIP_DEFLATED) as zf:
        for info, data in extra:
            zf.writestr(info, data)
    return z


def test_zip_traversal_member(tmp_path):
    z = _zip_with(tmp_path, [("frames/../../evil.txt", b"x")])
    with pytest.raises(CaptureError, match=r"cap\.zip.*'frames/\.\./\.\./evil\.txt'.*traversal"):
        open_capture(z, workdir=tmp_path)
    assert not (tmp_path / "evil.txt").exists()


def test_zip_absolute_member(tmp_path):
    info = zipfile.ZipInfo("frames/x")
    info.filename = "/tmp/evil.txt"  # ZipInfo() strips a leading '/', a hostile zip does not
    z = _zip_with(tmp_path, [(info, b"x")])
    with pytest.raises(CaptureError, match=r"'/tmp/evil\.txt': is an absolute path"):
        open_capture(z, workdir=tmp_path)


def test_zip_backslash_member(tmp_path):
    z = _zip_with(tmp_path, [("frames\\..\\..\\evil.txt", b"x")])
    with pytest.raises(CaptureError, match="backslash"):
        open_capture(z, workdir=tmp_path)


def test_zip_symlink_member(tmp_path):
    info = zipfile.ZipInfo("frames/link.png")
    info.create_system = 3
    info.external_attr = (stat.S_IFLNK | 0o777) << 16
    z = _zip_with(tmp_path, [(info, b"/etc/passwd")])
    with pytest.raises(CaptureError, match=r"'frames/link\.png' is a symbolic link"):
        open_capture(z, workdir=tmp_path)


def test_zip_bomb_ratio(tmp_path):
    z = _zip_with(tmp_path, [("gt/zeros.bin", b"\0" * (4 << 20))])  # 4 MiB -> ~4 KiB
    with pytest.raises(CaptureError, match=r"'gt/zeros\.bin' expands .*zip bomb"):
        open_capture(z, workdir=tmp_path)
    # the same zip passes with a laxer ratio limit
    with open_capture(z, workdir=tmp_path, max_ratio=1e6) as cap:
        assert (cap.root / "gt/zeros.bin").stat().st_size == 4 << 20


def test_zip_huge_declared_size(tmp_path):
    z = _zip_with(tmp_path, [("gt/small.bin", os.urandom(1000))])
    data = bytearray(z.read_bytes())
    # patch the member's uncompressed size in the central directory to 4 GiB - 2
    cd = data.rindex(b"PK\x01\x02", 0, data.index(b"PK\x05\x06"))
    assert data[cd + 46 : cd + 46 + 12] == b"gt/small.bin"
    struct.pack_into("<I", data, cd + 24, 0xFFFFFFFE)
    z.write_bytes(bytes(data))
    with pytest.raises(CaptureError, match=r"'gt/small\.bin' expands"):
        open_capture(z, workdir=tmp_path)
    with pytest.raises(CaptureError, match="uncompressed size exceeds the limit of 1000000 bytes"):
        open_capture(z, workdir=tmp_path, max_total_bytes=1_000_000)


def test_zip_member_larger_than_declared(tmp_path):
    z = _zip_with(tmp_path, [("gt/small.bin", os.urandom(1000))])
    data = bytearray(z.read_bytes())
    cd = data.rindex(b"PK\x01\x02", 0, data.index(b"PK\x05\x06"))
    struct.pack_into("<I", data, cd + 24, 10)  # claims 10 bytes
    z.write_bytes(bytes(data))
    with pytest.raises(CaptureError, match=r"gt/small\.bin"):
        open_capture(z, workdir=tmp_path)
    assert list(tmp_path.glob("pmvir-capture-*")) == []  # cleaned up after the failure


def test_zip_total_size_limit(tmp_path):
    make_capture(tmp_path / "cap")
    zip_capture(tmp_path / "cap", tmp_path / "cap.zip")
    with pytest.raises(CaptureError, match=r"cap\.zip.*exceeds the limit of 100 bytes"):
        open_capture(tmp_path / "cap.zip", workdir=tmp_path, max_total_bytes=100)


def test_zip_too_many_members(tmp_path):
    make_capture(tmp_path / "cap", n=3)  # capture.json + 3 frames
    zip_capture(tmp_path / "cap", tmp_path / "cap.zip")
    with pytest.raises(CaptureError, match=r"cap\.zip.*4 members, more than the limit of 3"):
        open_capture(tmp_path / "cap.zip", workdir=tmp_path, max_members=3)


def test_zip_without_manifest(tmp_path):
    z = tmp_path / "x.zip"
    with zipfile.ZipFile(z, "w") as zf:
        zf.writestr("a/capture.json", "{}")
        zf.writestr("b/frames/000.png", b"")
    with pytest.raises(ManifestError, match=r"x\.zip.*no capture\.json"):
        open_capture(z, workdir=tmp_path)


def test_not_a_zip(tmp_path):
    p = tmp_path / "cap.zip"
    p.write_bytes(b"not a zip at all")
    with pytest.raises(CaptureError, match=r"cap\.zip.*not a readable zip"):
        open_capture(p, workdir=tmp_path)


def test_missing_capture_path(tmp_path):
    with pytest.raises(CaptureError, match="no such capture"):
        open_capture(tmp_path / "nowhere")


# ----------------------------------------------------------------------------- bad manifests


def _manifest_error(tmp_path: Path) -> str:
    with pytest.raises(ManifestError) as info:
        open_capture(tmp_path)
    assert info.value.path == "capture.json"
    return info.value.problem


def test_manifest_not_json(tmp_path):
    make_capture(tmp_path, n=1)
    (tmp_path / "capture.json").write_text('{"format": "pmvir-capture/1", ')
    assert "not valid JSON" in _manifest_error(tmp_path)


def test_manifest_missing_and_no_frames_to_infer_it_from(tmp_path):
    (tmp_path / "frames").mkdir()
    (tmp_path / "frames" / "notes.txt").write_text("not a frame")
    problem = _manifest_error(tmp_path)
    assert "not found" in problem and "no frame files" in problem and "notes.txt" in problem


def test_manifest_missing_sensor(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d.pop("sensor"))
    assert "sensor: Field required" in _manifest_error(tmp_path)


def test_manifest_missing_bit_depth(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["sensor"].pop("bit_depth"))
    assert "sensor.bit_depth: Field required" in _manifest_error(tmp_path)


def test_manifest_missing_frames(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d.pop("frames"))
    assert "frames: Field required" in _manifest_error(tmp_path)


def test_manifest_missing_format(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d.pop("format"))
    assert "format: missing" in _manifest_error(tmp_path)


def test_manifest_wrong_format(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d.update(format="pmvir-capture/2"))
    assert "format: Input should be 'pmvir-capture/1'" in _manifest_error(tmp_path)


def test_manifest_unknown_field(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0].update(cam_form_world={}))
    assert "frames[0].cam_form_world: Extra inputs are not permitted" in _manifest_error(tmp_path)


def test_manifest_unknown_layout(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["sensor"].update(layout="IMX999"))
    assert "sensor.layout" in _manifest_error(tmp_path)


def test_manifest_path_outside_capture(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0].update(file="../x.png"))
    problem = _manifest_error(tmp_path)
    assert "frames[0].file" in problem and "'../x.png'" in problem and "inside the capture" in problem


def test_manifest_dotdot_inside_frames(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0].update(file="frames/../../x.png"))
    assert "'frames/../../x.png'" in _manifest_error(tmp_path)


def test_manifest_absolute_path(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0].update(file=str(tmp_path / "frames/000.png")))
    assert "is absolute" in _manifest_error(tmp_path)


def test_manifest_drive_letter_path(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0].update(file="C:/frames/000.png"))
    assert "'C:/frames/000.png' is absolute" in _manifest_error(tmp_path)


def test_manifest_backslash_path(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0].update(file="frames\\000.png"))
    assert "backslash" in _manifest_error(tmp_path)


def test_manifest_frame_outside_frames_folder(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0].update(file="capture.json"))
    assert "must be frames/<name><ext>" in _manifest_error(tmp_path)


def test_manifest_mask_outside_masks_folder(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0].update(mask="../masks/000.png"))
    assert "frames[0].mask" in _manifest_error(tmp_path)


def test_manifest_unknown_frame_suffix(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0].update(file="frames/000.jpg"))
    assert "must end in one of" in _manifest_error(tmp_path)


def test_manifest_duplicate_frame_names(tmp_path):
    make_capture(tmp_path, n=2)
    edit_manifest(tmp_path, lambda d: d["frames"][1].update(file="frames/000.tif"))
    assert "frame name '000' is used twice" in _manifest_error(tmp_path)


def test_manifest_rotation_not_orthonormal(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0]["cam_from_world"].update(R=[[2, 0, 0], [0, 1, 0], [0, 0, 1]]))
    problem = _manifest_error(tmp_path)
    assert "frames[0].cam_from_world.R" in problem and "not a rotation" in problem


def test_manifest_rotation_reflection(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0]["cam_from_world"].update(R=[[-1, 0, 0], [0, 1, 0], [0, 0, 1]]))
    assert "det = -1" in _manifest_error(tmp_path)


def test_manifest_rotation_wrong_shape(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0]["cam_from_world"].update(R=[[1, 0], [0, 1]]))
    assert "frames[0].cam_from_world.R" in _manifest_error(tmp_path)


def test_rotation_within_tolerance_is_made_exact():
    R, t = look_at(np.array([1.0, 2.0, 3.0]), np.zeros(3))
    pose = CamFromWorld(R=np.round(R, 6).tolist(), t=t.tolist())
    R2, _ = pose.arrays()
    np.testing.assert_allclose(R2.T @ R2, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R2, R, atol=1e-5)


def test_manifest_black_not_below_white(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["sensor"].update(black_level=4095, white_level=4095))
    assert "black_level < white_level" in _manifest_error(tmp_path)


def test_manifest_white_above_bit_depth(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["sensor"].update(white_level=4096))
    assert "2^bit_depth - 1 = 4095" in _manifest_error(tmp_path)


def test_manifest_bayer_override_on_monochrome(tmp_path):
    make_capture(tmp_path, n=1, layout="IMX250MZR")
    edit_manifest(tmp_path, lambda d: d["sensor"].update(bayer="RGGB"))
    assert "monochrome" in _manifest_error(tmp_path)


def test_manifest_bad_polarizer_block(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["sensor"].update(polarizer_block=[[0, 0], [45, 90]]))
    assert "polarizer_block must hold each of 0, 45, 90, 135 once" in _manifest_error(tmp_path)


def test_manifest_exposure_not_positive(tmp_path):
    make_capture(tmp_path, n=1)
    edit_manifest(tmp_path, lambda d: d["frames"][0].update(exposure=0))
    assert "frames[0].exposure" in _manifest_error(tmp_path)


def test_manifest_nan_refused(tmp_path):
    make_capture(tmp_path, n=1)
    text = (tmp_path / "capture.json").read_text().replace('"fx": 20.0', '"fx": NaN')
    (tmp_path / "capture.json").write_text(text)
    assert "intrinsics.fx" in _manifest_error(tmp_path)


def test_manifest_headerless_without_raw(tmp_path):
    make_capture(tmp_path, n=1, suffix=".raw", raw_dtype="uint16le")
    edit_manifest(tmp_path, lambda d: d.pop("raw"))
    assert "need \"raw\"" in _manifest_error(tmp_path)


def test_manifest_unknown_raw_dtype(tmp_path):
    make_capture(tmp_path, n=1, suffix=".raw", raw_dtype="uint16le")
    edit_manifest(tmp_path, lambda d: d["raw"].update(dtype="uint32"))
    assert "raw.dtype" in _manifest_error(tmp_path)


def test_validate_capture_reports_manifest_error(tmp_path):
    make_capture(tmp_path, n=1)
    (tmp_path / "capture.json").write_text("[]")
    problems = validate_capture(tmp_path)
    assert len(problems) == 1 and isinstance(problems[0], ManifestError)


# ----------------------------------------------------------------------------- bad frames


def _only_problem(cap: Capture, file: str, decode_frames: bool = True) -> FrameError:
    problems = cap.validate(decode_frames=decode_frames)
    assert [p.path for p in problems] == [file], problems
    assert isinstance(problems[0], FrameError)
    return problems[0]


def test_frame_size_differs_from_intrinsics(tmp_path):
    make_capture(tmp_path)
    write_frame(tmp_path / "frames/001.png", np.zeros((H, W + 4), np.uint16), bit_depth=12)
    with open_capture(tmp_path) as cap:
        err = _only_problem(cap, "frames/001.png")
        assert "size 16x8 does not match the intrinsics' 12x8" in err.problem
        _only_problem(cap, "frames/001.png", decode_frames=False)
        with pytest.raises(FrameError, match=r"frames/001\.png: size 16x8"):
            cap.read_raw(1)
        cap.read_raw(0)


def test_frame_sizes_inconsistent_without_intrinsics(tmp_path):
    make_capture(tmp_path, intrinsics=False)
    write_frame(tmp_path / "frames/002.png", np.zeros((H + 4, W), np.uint16), bit_depth=12)
    with open_capture(tmp_path) as cap:
        err = _only_problem(cap, "frames/002.png")
        assert "differs from frames/000.png's 12x8" in err.problem


def test_frame_width_not_multiple_of_4(tmp_path):
    make_capture(tmp_path, size=(8, 10), intrinsics=False)
    with open_capture(tmp_path) as cap:
        problems = cap.validate()
        assert [p.path for p in problems] == ["frames/000.png", "frames/001.png", "frames/002.png"]
        assert all("multiples of 4 for IMX250MYR" in p.problem for p in problems)
        with pytest.raises(FrameError, match=r"frames/000\.png.*multiples of 4"):
            cap.read_raw(0)


def test_frame_width_multiple_of_2_is_fine_for_mono(tmp_path):
    make_capture(tmp_path, size=(8, 10), layout="IMX250MZR")
    with open_capture(tmp_path) as cap:
        assert cap.validate() == []


def test_frame_odd_size_for_mono(tmp_path):
    make_capture(tmp_path, n=1, size=(8, 9), layout="IMX250MZR", intrinsics=False)
    with open_capture(tmp_path) as cap:
        assert "multiples of 2 for IMX250MZR" in _only_problem(cap, "frames/000.png").problem


def test_truncated_png_in_capture_and_all_errors_collected(tmp_path):
    make_capture(tmp_path, n=4)
    p = tmp_path / "frames/001.png"
    p.write_bytes(p.read_bytes()[:-20])
    (tmp_path / "frames/003.png").unlink()
    with open_capture(tmp_path) as cap:
        problems = cap.validate()
        assert [p.path for p in problems] == ["frames/001.png", "frames/003.png"]
        assert "truncated PNG" in problems[0].problem
        assert "not found" in problems[1].problem
        with pytest.raises(FrameError, match=r"frames/001\.png: truncated PNG"):
            cap.read_raw(1)


def test_dng_that_is_not_a_mosaic_in_capture(tmp_path):
    import tifffile

    make_capture(tmp_path, n=2, suffix=".dng", size=(24, 24))
    tifffile.imwrite(
        tmp_path / "frames/001.dng", np.zeros((24, 24, 3), np.uint16), photometric=34892, subfiletype=0,
        extratags=[(50706, 1, 4, (1, 4, 0, 0), True), (50708, 2, 0, "x", True)],
    )
    with open_capture(tmp_path) as cap:
        assert "single-plane CFA mosaic" in _only_problem(cap, "frames/001.dng").problem


def test_raw_shorter_than_declared_in_capture(tmp_path):
    make_capture(tmp_path, n=2, suffix=".bin", raw_dtype="uint16be")
    p = tmp_path / "frames/000.bin"
    p.write_bytes(p.read_bytes()[:-1])
    with open_capture(tmp_path) as cap:
        assert "shorter than declared" in _only_problem(cap, "frames/000.bin").problem
        assert "shorter than declared" in _only_problem(cap, "frames/000.bin", decode_frames=False).problem


def test_8bit_data_declared_12bit(tmp_path):
    make_capture(tmp_path, n=2)
    write_frame(tmp_path / "frames/000.png", np.full((H, W), 200, np.uint8), bit_depth=8)
    with open_capture(tmp_path) as cap:
        assert "8-bit data but sensor.bit_depth is 12" in _only_problem(cap, "frames/000.png").problem
        with pytest.raises(FrameError, match=r"frames/000\.png: 8-bit data"):
            cap.read_raw(0)


def test_16bit_values_above_bit_depth(tmp_path):
    make_capture(tmp_path, n=2)
    s = np.zeros((H, W), np.uint16)
    s[3, 3] = 4096
    write_frame(tmp_path / "frames/001.png", s, bit_depth=16)
    with open_capture(tmp_path) as cap:
        problem = _only_problem(cap, "frames/001.png").problem
        assert "sample value 4096 exceeds 2^bit_depth - 1 = 4095" in problem
        with pytest.raises(FrameError, match=r"frames/001\.png: sample value 4096"):
            cap.read_raw(1)


def test_mask_of_wrong_size(tmp_path):
    make_capture(tmp_path, masks=True)
    write_frame(tmp_path / "masks/002.png", np.zeros((H, W - 4), np.uint8), bit_depth=8)
    with open_capture(tmp_path) as cap:
        err = _only_problem(cap, "masks/002.png")
        assert "mask is 8x8 but frame frames/002.png is 12x8" in err.problem
        _only_problem(cap, "masks/002.png", decode_frames=False)
        with pytest.raises(FrameError, match=r"masks/002\.png: mask is 8x8"):
            cap.read_mask(2)


def test_mask_missing(tmp_path):
    make_capture(tmp_path, masks=True)
    (tmp_path / "masks/000.png").unlink()
    with open_capture(tmp_path) as cap:
        assert "not found" in _only_problem(cap, "masks/000.png").problem


def test_frame_symlink_outside_capture(tmp_path):
    make_capture(tmp_path / "cap", n=2)
    outside = tmp_path / "outside.png"
    write_frame(outside, np.zeros((H, W), np.uint16), bit_depth=12)
    (tmp_path / "cap/frames/001.png").unlink()
    (tmp_path / "cap/frames/001.png").symlink_to(outside)
    with open_capture(tmp_path / "cap") as cap:
        assert "outside the capture" in _only_problem(cap, "frames/001.png").problem
