"""``pmvir synth`` on the command line, bad inputs with their errors, and the optional Mitsuba renderer."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from pmvir.capture import validate_capture
from pmvir.cli import main
from pmvir.errors import ConfigError, MeshError
from pmvir.synth.generate import synthesize


def test_cli_writes_a_capture(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "cap"
    rc = main(
        [
            "synth",
            "--shape",
            "knot",
            "--out",
            str(out),
            "--views",
            "2",
            "--size",
            "64x48",
            "--material",
            "conductor",
            "--lighting",
            "envmap",
            "--noise",
            "0.002",
            "--seed",
            "3",
            "--quiet",
        ]
    )
    assert rc == 0
    assert f"wrote {out}" in capsys.readouterr().out
    assert validate_capture(out) == []
    assert (out / "gt" / "mesh.ply").is_file() and (out / "gt" / "illumination.json").is_file()
    assert sorted(p.name for p in (out / "gt" / "views").iterdir()) == ["000.npz", "001.npz"]


def test_cli_no_gt_views_and_force(tmp_path: Path) -> None:
    out = tmp_path / "cap"
    args = ["synth", "--shape", "sphere", "--out", str(out), "--views", "1", "--size", "32x32", "--quiet"]
    assert main(args + ["--no-gt-views"]) == 0
    assert not (out / "gt" / "views").exists()
    assert main(args) == 2  # not empty
    assert main(args + ["--force"]) == 0
    assert (out / "gt" / "views" / "000.npz").is_file()


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--shape", "teapot"], "unknown shape 'teapot'"),
        (["--mesh", "/nonexistent/bunny.ply"], "no such mesh file"),
        (["--shape", "blob", "--size", "62x48"], "multiples of 4"),
        (["--shape", "blob", "--size", "big"], "WIDTHxHEIGHT"),
        (["--shape", "blob", "--views", "0"], "views"),
        (["--shape", "blob", "--material", "plastic", "--ior", "0.9"], "plastic needs ior > 1"),
    ],
)
def test_cli_bad_inputs_exit_2_with_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], message: str
) -> None:
    rc = main(["synth", "--out", str(tmp_path / "x"), "--quiet", *argv])
    err = capsys.readouterr().err
    assert rc == 2 and message in err and err.startswith("pmvir synth: error:")
    assert len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x" / "capture.json").exists()


def test_unknown_shape_raises_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"unknown shape 'cube'.*sphere, blob, dented, knot"):
        synthesize(tmp_path / "x", shape="cube", views=1, size=(32, 32))


def test_missing_mesh_file_raises_mesh_error(tmp_path: Path) -> None:
    with pytest.raises(MeshError, match="no such mesh file"):
        synthesize(tmp_path / "x", mesh=tmp_path / "missing.obj", views=1, size=(32, 32))


def test_size_not_multiple_of_4_raises_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="size 34x32: width and height must be multiples of 4"):
        synthesize(tmp_path / "x", shape="sphere", views=1, size=(34, 32))


def test_mesh_and_shape_together_raise_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="exactly one of mesh"):
        synthesize(tmp_path / "x", mesh=tmp_path / "a.ply", shape="blob")
    with pytest.raises(ConfigError, match="exactly one of mesh"):
        synthesize(tmp_path / "x")


def test_unknown_option_raises_config_error(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="colour_temperature"):
        synthesize(tmp_path / "x", shape="sphere", colour_temperature=5000)


def test_non_empty_output_raises_config_error(tmp_path: Path) -> None:
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "notes.txt").write_text("keep me")
    with pytest.raises(ConfigError, match="not empty"):
        synthesize(tmp_path / "x", shape="sphere", views=1, size=(32, 32))
    assert (tmp_path / "x" / "notes.txt").read_text() == "keep me"


def test_unreadable_mesh_raises_mesh_error(tmp_path: Path) -> None:
    bad = tmp_path / "bad.ply"
    bad.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\n")
    with pytest.raises(MeshError):
        synthesize(tmp_path / "x", mesh=bad, views=1, size=(32, 32))


def test_mitsuba_missing_gives_a_clear_error(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(sys.modules, "mitsuba", None)  # as if the optional extra were not installed
    with pytest.raises(ConfigError, match=r"pip install 'pmvir\[mitsuba\]'"):
        synthesize(tmp_path / "x", shape="sphere", views=1, size=(32, 32), renderer="mitsuba")
    rc = main(
        ["synth", "--shape", "sphere", "--out", str(tmp_path / "y"), "--renderer", "mitsuba", "--quiet"]
    )
    assert rc == 2 and "pmvir[mitsuba]" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_mitsuba_renderer_agrees_with_builtin_on_a_mirror_sphere(tmp_path: Path) -> None:
    """Both renderers share the sensor step and conventions; a conductor sphere is nearly noise-free."""
    pytest.importorskip("mitsuba")
    import drjit as dr

    if not dr.has_backend(dr.JitBackend.LLVM):
        pytest.skip("Mitsuba's LLVM backend is unavailable")
    kw = dict(
        shape="sphere",
        views=1,
        size=(64, 48),
        material="conductor",
        noise=0.0,
        full_well=0.0,
        texture="uniform",
        exposure=1.0,
    )
    a = synthesize(tmp_path / "builtin", aop_frame="ray", **kw)
    b = synthesize(tmp_path / "mitsuba", renderer="mitsuba", spp=16, **kw)
    assert validate_capture(b) == []
    ga, gb = np.load(a / "gt/views/000.npz"), np.load(b / "gt/views/000.npz")
    assert np.array_equal(ga["mask"], gb["mask"])  # geometry comes from the same ray casting
    from scipy.ndimage import binary_erosion

    inner = binary_erosion(ga["mask"], iterations=2) & (ga["dop"] > 0.05)
    diff = np.degrees(
        np.abs(np.angle(np.exp(2j * (ga["aop"][inner] - gb["aop"][inner].astype(np.float64))))) / 2
    )
    assert inner.sum() > 200 and np.median(diff) < 1.5
    ratio = gb["i_int"][inner].mean() / ga["i_int"][inner].mean()
    assert 0.9 < ratio < 1.1


def test_mitsuba_max_depth_two_drops_the_interreflected_light(tmp_path: Path) -> None:
    """``--max-depth 2`` renders direct light only: a Lambert gear, whose teeth and bore face each
    other, is darker than with the default six bounces."""
    pytest.importorskip("mitsuba")
    import drjit as dr

    if not dr.has_backend(dr.JitBackend.LLVM):
        pytest.skip("Mitsuba's LLVM backend is unavailable")
    kw = dict(shape="gear", views=1, size=(96, 80), material="lambert", noise=0.0, full_well=0.0,
              texture="uniform", exposure=1.0, renderer="mitsuba", spp=64, lighting="envmap")
    direct = tmp_path / "direct"
    rc = main(["synth", "--shape", "gear", "--out", str(direct), "--renderer", "mitsuba", "--max-depth", "2",
               "--views", "1", "--size", "96x80", "--material", "lambert", "--noise", "0", "--full-well", "0",
               "--texture", "uniform", "--exposure", "1", "--spp", "64", "--lighting", "envmap", "--quiet"])
    assert rc == 0
    full = synthesize(tmp_path / "full", **kw)
    gd, gf = np.load(direct / "gt/views/000.npz"), np.load(full / "gt/views/000.npz")
    inside = gd["mask"] & gf["mask"]
    ratio = gd["i_int"][inside].sum() / gf["i_int"][inside].sum()
    # The bounced light is gone: 2.5% of the total on this gear at albedo 0.5 (Monte Carlo noise in
    # the sum over 1,000 pixels at 64 spp: about 0.3%).
    assert inside.sum() > 500 and 0.9 < ratio < 0.99
    with pytest.raises(ConfigError, match="max_depth"):
        synthesize(tmp_path / "bad", shape="sphere", views=1, size=(32, 32), renderer="mitsuba", max_depth=1)


def test_the_built_in_renderer_does_not_load_torch() -> None:
    """``make demo`` renders its capture while the service's processes start on the same cores: the
    renderer's imports stay light (torch alone took 2 s of them)."""
    import subprocess

    code = "import sys, pmvir.cli, pmvir.synth.generate; print('torch' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "False"
