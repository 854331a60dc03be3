"""Decoding frames and whole captures (pmvir.decode, `pmvir decode`), on captures written here."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from pmvir.cli import main
from pmvir.config import DecodeOptions
from pmvir.decode import (
    NPZ_KEYS,
    PREVIEW_SUFFIXES,
    decode_capture,
    decode_frame,
    read_decoded,
    write_decoded,
)
from pmvir.errors import CaptureError, ConfigError
from pmvir.polarization.demosaic import support_radius
from pmvir.polarization.layout import IMX250MYR, IMX250MZR, layout_from_sensor, mosaic
from pmvir.polarization.stokes import intensities_from_polarization
from pmvir.progress import Progress

H, W = 48, 64
AOP_DEG, DOP = 30.0, 0.4
WHITE = 4095


def _raw_samples(layout, *, aop_deg: float = AOP_DEG, level: float = 0.5) -> np.ndarray:
    """12-bit samples of a smooth field with a constant AoP/DoP."""
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    base = level * (1.0 + 0.2 * np.sin(x / 17) * np.cos(y / 13))
    s0 = np.stack([0.9 * base, base, 0.7 * base], -1) if layout.is_colour else base[..., None]
    ints = intensities_from_polarization(
        s0.astype(np.float32),
        np.full((H, W), np.deg2rad(aop_deg), np.float32),
        np.full((H, W), DOP, np.float32),
    )
    return np.clip(np.rint(mosaic(ints, layout) * WHITE), 0, WHITE).astype(np.uint16)


def _write_capture(root: Path, frames: dict[str, np.ndarray], *, layout_name: str = "IMX250MYR",
                   masks: dict[str, np.ndarray] | None = None, aop_reference: str = "ccw") -> Path:
    """A capture folder per the spec: 16-bit PNG frames, optional 8-bit masks, capture.json."""
    (root / "frames").mkdir(parents=True)
    entries = []
    for name, samples in frames.items():
        assert cv2.imwrite(str(root / "frames" / f"{name}.png"), samples)
        entry = {"file": f"frames/{name}.png"}
        if masks and name in masks:
            (root / "masks").mkdir(exist_ok=True)
            assert cv2.imwrite(str(root / "masks" / f"{name}.png"), masks[name].astype(np.uint8) * 255)
            entry["mask"] = f"masks/{name}.png"
        entries.append(entry)
    manifest = {
        "format": "pmvir-capture/1",
        "sensor": {"layout": layout_name, "bit_depth": 12, "black_level": 0, "white_level": WHITE,
                   "aop_reference": aop_reference},
        "frames": entries,
    }
    (root / "capture.json").write_text(json.dumps(manifest, indent=2))
    return root


def _aop_err_deg(a: np.ndarray, deg: float) -> np.ndarray:
    return np.degrees(np.abs(np.angle(np.exp(2j * (a.astype(np.float64) - np.deg2rad(deg)))))) / 2


def test_decode_capture_writes_the_spec_files(tmp_path: Path) -> None:
    sat = _raw_samples(IMX250MYR)
    sat[20, 30] = WHITE  # one saturated sample
    mask = np.ones((H, W), dtype=bool)
    mask[:, :10] = False
    cap = _write_capture(tmp_path / "cap", {"000": _raw_samples(IMX250MYR), "001": sat},
                         masks={"001": mask})
    calls: list[tuple[float, str]] = []
    out = tmp_path / "out"
    written = decode_capture(cap, out, progress=Progress(lambda _, f, m: calls.append((f, m))))
    assert written == [out / "000.npz", out / "001.npz"]
    assert calls == [(0.5, "decoded frames/000.png"), (1.0, "decoded frames/001.png")]
    for stem in ("000", "001"):
        with np.load(out / f"{stem}.npz") as z:
            assert sorted(z.files) == sorted(NPZ_KEYS)
            assert z["i_int"].shape == z["i_min"].shape == (H, W, 3)
            assert z["aop"].shape == z["dop"].shape == z["valid"].shape == (H, W)
            assert z["i_int"].dtype == z["i_min"].dtype == z["aop"].dtype == z["dop"].dtype == np.float32
            assert z["valid"].dtype == np.bool_
        for suffix in PREVIEW_SUFFIXES:
            png = cv2.imread(str(out / f"{stem}{suffix}"), cv2.IMREAD_UNCHANGED)
            assert png is not None and png.shape[:2] == (H, W) and png.dtype == np.uint8
    d0, d1 = read_decoded(out / "000.npz"), read_decoded(out / "001.npz")
    inner = (slice(8, -8), slice(8, -8))
    assert d0.valid[inner].all()
    assert _aop_err_deg(d0.aop, AOP_DEG)[inner].max() < 1.0
    assert np.abs(d0.dop - DOP)[inner].max() < 0.01
    # I_int in normalized units: the mean of the 4 angles, here s0 / 2
    np.testing.assert_allclose(d0.i_min[inner], ((1 - d0.dop)[..., None] * d0.i_int)[inner], rtol=1e-5)
    # frame 001: masked-out columns and the saturated sample's footprint are invalid, nothing else
    r = support_radius(IMX250MYR, DecodeOptions().demosaic)
    expected = np.ones((H, W), bool)
    expected[:, :10] = False
    expected[20 - r : 20 + r + 1, 30 - r : 30 + r + 1] = False
    np.testing.assert_array_equal(d1.valid, expected)


def test_decode_capture_selects_frames_by_stem_or_index(tmp_path: Path) -> None:
    frames = {name: _raw_samples(IMX250MYR) for name in ("a", "b", "c")}
    cap = _write_capture(tmp_path / "cap", frames)
    out = tmp_path / "out"
    assert decode_capture(cap, out, frames=["c", 0], previews=False) == [out / "c.npz", out / "a.npz"]
    assert decode_capture(cap, out, frames=["1"], previews=False) == [out / "b.npz"]
    assert not list(out.glob("*.png"))


def test_unknown_frame_name_raises_config_error(tmp_path: Path) -> None:
    cap = _write_capture(tmp_path / "cap", {"000": _raw_samples(IMX250MYR)})
    with pytest.raises(ConfigError, match="no frame named 'zzz'"):
        decode_capture(cap, tmp_path / "out", frames=["zzz"])


def test_frame_index_out_of_range_raises_config_error(tmp_path: Path) -> None:
    cap = _write_capture(tmp_path / "cap", {"000": _raw_samples(IMX250MYR)})
    with pytest.raises(ConfigError, match="out of range"):
        decode_capture(cap, tmp_path / "out", frames=[3])


def test_missing_capture_raises_capture_error(tmp_path: Path) -> None:
    with pytest.raises(CaptureError):
        decode_capture(tmp_path / "nowhere", tmp_path / "out")


def test_monochrome_capture_gives_grey_rgb(tmp_path: Path) -> None:
    cap = _write_capture(tmp_path / "cap", {"m": _raw_samples(IMX250MZR)}, layout_name="IMX250MZR")
    (path,) = decode_capture(cap, tmp_path / "out", previews=False)
    d = read_decoded(path)
    assert d.i_int.shape == (H, W, 3)
    np.testing.assert_array_equal(d.i_int[..., 0], d.i_int[..., 2])
    assert _aop_err_deg(d.aop, AOP_DEG)[4:-4, 4:-4].max() < 1.0


def test_cw_capture_decodes_to_the_mirrored_angle(tmp_path: Path) -> None:
    cap = _write_capture(tmp_path / "cap", {"0": _raw_samples(IMX250MYR)}, aop_reference="cw")
    (path,) = decode_capture(cap, tmp_path / "out", previews=False)
    assert _aop_err_deg(read_decoded(path).aop, 180.0 - AOP_DEG)[8:-8, 8:-8].max() < 1.0


def test_decode_frame_noise_floor_and_mask() -> None:
    raw = _raw_samples(IMX250MYR, level=0.5).astype(np.float32) / WHITE
    raw[:, W // 2 :] *= 0.01  # right half: mean intensity about 0.0025, below a 0.005 floor
    mask = np.ones((H, W), bool)
    mask[:8] = False
    d = decode_frame(raw, IMX250MYR, mask=mask, options=DecodeOptions(noise_floor=0.005))
    assert not d.valid[:8].any()
    assert d.valid[8:, : W // 2 - 4].all()
    assert not d.valid[:, W // 2 + 4 :].any()


def test_decode_frame_with_mismatched_mask_raises_value_error() -> None:
    raw = np.zeros((H, W), np.float32)
    with pytest.raises(ValueError, match="mask"):
        decode_frame(raw, IMX250MYR, mask=np.ones((H, W + 4), bool))


def test_read_decoded_rejects_a_file_with_missing_arrays(tmp_path: Path) -> None:
    bad = tmp_path / "bad.npz"
    np.savez(bad, aop=np.zeros((4, 4), np.float32))
    with pytest.raises(CaptureError, match="expected arrays"):
        read_decoded(bad)


def test_write_then_read_decoded_round_trips(tmp_path: Path) -> None:
    raw = _raw_samples(IMX250MYR).astype(np.float32) / WHITE
    d = decode_frame(raw, layout_from_sensor("IMX250MYR"))
    path = write_decoded(tmp_path / "f.npz", d, compress=True)
    back = read_decoded(path)
    for key in NPZ_KEYS:
        np.testing.assert_array_equal(getattr(back, key), getattr(d, key))


def test_cli_decode_writes_files_and_reports(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cap = _write_capture(tmp_path / "cap", {"000": _raw_samples(IMX250MYR), "001": _raw_samples(IMX250MYR)})
    out = tmp_path / "out"
    code = main(["decode", str(cap), "--out", str(out), "--frames", "001", "--demosaic", "edge-aware"])
    assert code == 0
    assert (out / "001.npz").is_file() and not (out / "000.npz").exists()
    assert all((out / f"001{s}").is_file() for s in PREVIEW_SUFFIXES)
    captured = capsys.readouterr()
    assert "decoded 1 frame(s)" in captured.out
    assert "decode" in captured.err  # the tqdm bar goes to stderr


def test_cli_decode_bad_noise_floor_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cap = _write_capture(tmp_path / "cap", {"000": _raw_samples(IMX250MYR)})
    assert main(["decode", str(cap), "--out", str(tmp_path / "o"), "--noise-floor", "2"]) == 2
    assert "noise_floor" in capsys.readouterr().err


def test_cli_decode_missing_capture_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["decode", str(tmp_path / "nope"), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "pmvir decode: error:" in capsys.readouterr().err
