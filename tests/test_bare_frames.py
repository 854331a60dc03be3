"""A folder of frames without capture.json through the command line: ``pmvir init`` and
``pmvir reconstruct`` (subprocesses, as a user runs them).

The reconstruction test strips a 24-view 320x256 synthetic capture of an object on a textured table
to its frames (no manifest, no poses, no masks) and writes an EXIF focal length 10% too long into
them, so the manifest is inferred with estimated intrinsics and SfM estimates the poses and refines
the focal length from the EXIF one.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from pmvir.capture import parse_manifest
from pmvir.io.colmap_text import read_colmap_text_model
from pmvir.io.frames import read_frame, write_frame
from pmvir.io.inference import PIXEL_PITCH_MM
from pmvir.synth import synthesize

#: Black level of pmvir synth's sensor model (its capture.json says so; the bare frames do not).
SYNTH_BLACK = 64


def pmvir(*args: str | Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "pmvir.cli", *map(str, args)], check=False, capture_output=True, text=True,
        timeout=900,
    )


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory: pytest.TempPathFactory) -> Path:
    root = tmp_path_factory.mktemp("bare")
    return synthesize(
        root / "cap", shape="blob", scene="table", views=24, size=(320, 256), material="plastic", seed=4
    )


def bare_copy(capture: Path, dest: Path, *, focal_mm: float) -> Path:
    """The capture's frames alone, directly in ``dest``, each with the EXIF FocalLength ``focal_mm``."""
    dest.mkdir(parents=True)
    exif = Image.Exif()
    exif[37386] = focal_mm  # FocalLength
    for p in sorted((capture / "frames").iterdir()):
        Image.fromarray(read_frame(p)).save(dest / p.name, exif=exif)
    return dest


def test_init_writes_the_inferred_manifest_beside_the_frames_and_keeps_an_existing_one(tmp_path: Path) -> None:
    root = tmp_path / "shots"
    root.mkdir()
    rng = np.random.default_rng(0)
    for i in range(3):
        write_frame(root / f"{i:03d}.png", rng.integers(0, 3000, (16, 24)), bit_depth=12)
    run = pmvir("init", root, "--black-level", "32")
    assert run.returncode == 0, run.stderr
    assert "bit depth 12" in run.stderr and "black level 32" in run.stderr and "IMX250MYR" in run.stderr
    manifest = parse_manifest((root / "capture.json").read_bytes())
    assert manifest.sensor.bit_depth == 12 and manifest.sensor.black_level == 32
    assert [f.file for f in manifest.frames] == ["frames/000.png", "frames/001.png", "frames/002.png"]
    before = (root / "capture.json").read_bytes()
    again = pmvir("init", root, "--layout", "IMX250MZR")
    assert again.returncode == 2 and "exists; --force replaces it" in again.stderr
    assert (root / "capture.json").read_bytes() == before
    forced = pmvir("init", root, "--layout", "IMX250MZR", "--force")
    assert forced.returncode == 0, forced.stderr
    assert parse_manifest((root / "capture.json").read_bytes()).sensor.layout == "IMX250MZR"


def test_init_names_the_bad_frame_in_one_line(tmp_path: Path) -> None:
    root = tmp_path / "shots"
    root.mkdir()
    write_frame(root / "a.png", np.zeros((16, 24), np.uint16), bit_depth=12)
    write_frame(root / "b.png", np.zeros((16, 28), np.uint16), bit_depth=12)
    run = pmvir("init", root)
    assert run.returncode == 2 and not (root / "capture.json").exists()
    lines = run.stderr.strip().splitlines()
    assert len(lines) == 1 and "b.png: size 28x16 differs from a.png's 24x16" in lines[0], run.stderr
    raw = tmp_path / "raw"
    raw.mkdir()
    (raw / "a.raw").write_bytes(bytes(16 * 24 * 2))
    run = pmvir("reconstruct", raw, "--out", tmp_path / "out")
    assert run.returncode == 2 and "a.raw: a headerless frame: give its size (--frame-size WxH)" in run.stderr


def test_decode_reads_a_folder_of_frames_with_the_inferred_manifest(tmp_path: Path) -> None:
    root = tmp_path / "shots"
    root.mkdir()
    write_frame(root / "a.png", np.full((16, 24), 1032, np.uint16), bit_depth=12)
    run = pmvir("decode", root, "--black-level", "8", "--out", tmp_path / "dec", "--no-previews", "--quiet")
    assert run.returncode == 0, run.stderr
    decoded = np.load(tmp_path / "dec" / "a.npz")
    assert np.allclose(decoded["i_int"], (1032 - 8) / (4095 - 8), rtol=1e-5)  # a flat grey: (s - black) / range


def test_reconstruct_options_for_inference_refuse_a_capture_with_a_manifest(tmp_path: Path) -> None:
    root = tmp_path / "shots"
    root.mkdir()
    write_frame(root / "a.png", np.zeros((16, 24), np.uint16), bit_depth=12)
    assert pmvir("init", root).returncode == 0
    run = pmvir("reconstruct", root, "--out", tmp_path / "out", "--layout", "IMX250MZR")
    assert run.returncode == 2 and "apply to a folder of frames without capture.json" in run.stderr


@pytest.mark.slow
def test_a_bare_folder_of_frames_reconstructs_with_sfm(synthetic: Path, tmp_path: Path) -> None:
    truth = parse_manifest((synthetic / "capture.json").read_bytes())
    assert truth.intrinsics is not None
    exif_fx = 1.1 * truth.intrinsics.fx
    bare = bare_copy(synthetic, tmp_path / "frames-only", focal_mm=exif_fx * PIXEL_PITCH_MM["IMX250MYR"])
    out = tmp_path / "out"
    run = pmvir(
        "reconstruct", bare, "--out", out, "--black-level", SYNTH_BLACK, "--stop-after", "geometry", "--quiet"
    )
    assert run.returncode == 0, run.stderr
    assert "no capture.json; inferred:" in run.stderr
    used = parse_manifest((out / "capture.json").read_bytes())
    assert [f.file for f in used.frames] == [f.file for f in truth.frames]
    assert used.sensor == truth.sensor
    assert used.intrinsics is not None and used.intrinsics.estimated
    assert used.intrinsics.fx == pytest.approx(exif_fx, rel=1e-6)
    report = json.loads((out / "report.json").read_text())
    assert report["capture"]["manifest"] == "inferred"
    poses = report["geometry"]["poses"]
    assert poses["mode"] == "sfm" and poses["registered_views"] >= 22, poses
    left_out = [w for w in report["warnings"] if w.startswith("SfM registered")]  # named when any is
    assert len(left_out) == (poses["registered_views"] < len(truth.frames)), report["warnings"]
    assert all(name in left_out[0] for name in poses["unregistered"])
    cameras, _ = read_colmap_text_model(out / "poses")
    focal = np.array([c.params[0] for c in cameras.values()])
    # refined from the EXIF focal length (10% off) to within 3% of the truth
    assert np.all(np.abs(focal / truth.intrinsics.fx - 1.0) < 0.03), (focal, truth.intrinsics.fx)
    assert (out / "initial.ply").is_file()
