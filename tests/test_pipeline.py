"""The pipeline driver and `pmvir reconstruct`: stages, progress, cancellation, report, options."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from pmvir.capture import CaptureManifest, FrameEntry, SensorSpec, open_capture, write_capture_manifest
from pmvir.cli import main
from pmvir.config import DecodeOptions, PipelineConfig, RefineOptions
from pmvir.decode import decode_frame
from pmvir.errors import CanceledError, ConfigError, ShapeError
from pmvir.geometry.silhouette.hull_fit import RimFit
from pmvir.io.frames import write_frame
from pmvir.pipeline import (
    DRAWN_HULL_MIN_GAIN,
    SPECULAR_MEDIAN_DOP,
    decode_views,
    mask_margin_warning,
    refinement_observations,
    refinement_options,
    run,
    specular_warning,
    unregistered_warning,
    within_mask,
)
from pmvir.polarization.layout import ANGLES_DEG, IMX250MYR, mosaic
from pmvir.polarization.noise import closure_noise
from pmvir.progress import Progress


def _write_capture(
    root: Path, n_frames: int = 3, size: tuple[int, int] = (48, 64), *, rho: float = 0.3, masks: bool = False
) -> Path:
    """A small capture whose frames hold a known, uniform polarization field (DoP ``rho``), and with
    ``masks`` a mask per frame covering its left half."""
    h, w = size
    rng = np.random.default_rng(0)
    (root / "frames").mkdir(parents=True)
    if masks:
        (root / "masks").mkdir()
    entries = []
    for k in range(n_frames):
        s0, phi = 0.5 + 0.1 * k, np.deg2rad(30.0 + 20 * k)
        theta = np.deg2rad(np.array(ANGLES_DEG, dtype=np.float64))
        per_angle = s0 / 2 * (1 + rho * np.cos(2 * (theta - phi)))
        colour = np.array([1.0, 0.8, 0.6])
        inten = np.broadcast_to(per_angle[:, None] * colour, (h, w, 4, 3))
        raw = np.clip(np.round(mosaic(np.ascontiguousarray(inten), IMX250MYR) * 4095 + rng.normal(0, 1, (h, w))), 0, 4095)
        write_frame(root / f"frames/{k:03d}.png", raw.astype(np.uint16), bit_depth=12)
        mask = None
        if masks:
            mask = f"masks/{k:03d}.png"
            m = np.zeros((h, w), np.uint8)
            m[:, : w // 2] = 255
            cv2.imwrite(str(root / mask), m)
        entries.append(FrameEntry(file=f"frames/{k:03d}.png", mask=mask))
    write_capture_manifest(root, CaptureManifest(sensor=SensorSpec(layout="IMX250MYR", bit_depth=12), frames=entries))
    return root


@pytest.fixture()
def capture(tmp_path: Path) -> Path:
    return _write_capture(tmp_path / "cap")


def test_decode_stage_writes_decoded_frames_and_report(capture: Path, tmp_path: Path) -> None:
    events: list[tuple[str, float, str]] = []
    result = run(
        PipelineConfig(stop_after="decode"), capture, tmp_path / "out", progress=Progress(lambda *e: events.append(e))
    )
    assert result.stages_run == ["decode"]
    data = np.load(tmp_path / "out/decoded/001.npz")
    valid = data["valid"]
    assert valid.mean() > 0.8
    # frame 1 holds AoP 50 degrees and DoP 0.3 everywhere
    assert abs(np.rad2deg(np.median(data["aop"][valid])) - 50.0) < 1.0
    assert abs(np.median(data["dop"][valid]) - 0.3) < 0.02
    report = json.loads((tmp_path / "out/report.json").read_text())
    assert report["stages"] == ["decode"] and report["counts"]["frames"] == 3
    assert report["parameters"]["decode"]["noise_floor"] == PipelineConfig().decode.noise_floor
    fractions = [f for _, f, _ in events]
    assert fractions == sorted(fractions) and fractions[-1] == 1.0


def test_a_specular_dominated_object_is_warned_about(tmp_path: Path, capsys) -> None:
    """Median DoP inside the masks above SPECULAR_MEDIAN_DOP (0.2): report.json's warnings, the run's
    result and `pmvir reconstruct` say so; a diffuse-looking object (DoP 0.05) and a capture without
    masks (its background would dilute the DoP) get no warning."""
    runs = {}
    for label, rho, masks in (("metal", 0.3, True), ("plastic", 0.05, True), ("unmasked", 0.3, False)):
        cap = _write_capture(tmp_path / label, rho=rho, masks=masks)
        result = run(PipelineConfig(stop_after="decode"), cap, tmp_path / f"out-{label}")
        report = json.loads((tmp_path / f"out-{label}/report.json").read_text())
        assert report["warnings"] == result.warnings
        runs[label] = (report["decode"]["median_dop_in_masks"], result.warnings)
    assert runs["metal"][0] == pytest.approx(0.3, abs=0.02)
    assert len(runs["metal"][1]) == 1 and "specular-dominated" in runs["metal"][1][0]
    assert "the offset scan is off" in runs["metal"][1][0]
    assert runs["plastic"][0] == pytest.approx(0.05, abs=0.02) and runs["plastic"][1] == []
    assert runs["unmasked"] == (None, [])
    args = ["reconstruct", str(tmp_path / "metal"), "--out", str(tmp_path / "cli"), "--stop-after", "decode", "--quiet"]
    assert main(args) == 0
    assert "pmvir: warning: the object looks specular-dominated" in capsys.readouterr().err


def test_specular_captures_are_refined_without_the_offset_scan() -> None:
    """refinement_options: above SPECULAR_MEDIAN_DOP the offset scan is turned off, unless
    refine.offset_scan.specular is 'same'; below it, or without masks (None), the options stay."""
    default = RefineOptions()
    assert default.offset_scan.mode != "off"
    assert refinement_options(default, SPECULAR_MEDIAN_DOP + 0.05).offset_scan.mode == "off"
    assert refinement_options(default, SPECULAR_MEDIAN_DOP - 0.05) is default
    assert refinement_options(default, None) is default
    keep = RefineOptions(offset_scan={"specular": "same"})
    assert refinement_options(keep, 0.35).offset_scan.mode == default.offset_scan.mode
    assert "runs as set" in (specular_warning(0.35, keep) or "")
    assert specular_warning(0.1, default) is None


def test_views_sfm_left_out_are_named_in_a_warning() -> None:
    assert unregistered_warning([], 3) is None
    warning = unregistered_warning(["001", "003"], 4) or ""
    assert warning.startswith("SfM registered 2 of 4 views; 001, 003 are left out")
    many = unregistered_warning([f"{i:03d}" for i in range(20, 40)], 40) or ""
    assert "019" not in many and "020" in many and "031" in many and "032" not in many and "8 more" in many


def test_masks_the_isolation_drew_get_a_looser_hull_fit_no_rim_fit_and_a_wider_margin() -> None:
    """refinement_options with drawn_masks: the hull fit takes drawn_hull_tolerance_px and two views at
    least and stops where a step gains less than DRAWN_HULL_MIN_GAIN (unless hull_min_gain is set),
    the rim fit is off and the silhouette margin grows by drawn_mask_margin_px (the rest as set,
    the specular rule too); given masks keep them."""
    default = RefineOptions()
    reach = default.views.drawn_mask_margin_px
    assert default.surface.hull_tolerance_px is not None and default.surface.rim_fit_gain > 0 and reach > 0
    assert default.surface.hull_views == 1
    drawn = refinement_options(default, 0.05, drawn_masks=True)
    assert drawn.surface.hull_tolerance_px == default.surface.drawn_hull_tolerance_px is not None
    assert drawn.surface.hull_views == 2 and drawn.surface.rim_fit_gain == 0.0
    assert default.surface.hull_min_gain is None and drawn.surface.hull_min_gain == DRAWN_HULL_MIN_GAIN > 0
    kept = RefineOptions.model_validate({"surface": {"hull_min_gain": 0.0}})
    assert refinement_options(kept, 0.05, drawn_masks=True).surface.hull_min_gain == 0.0
    three = RefineOptions.model_validate({"surface": {"hull_views": 3, "drawn_hull_tolerance_px": None}})
    off = refinement_options(three, 0.05, drawn_masks=True).surface
    assert off.hull_tolerance_px is None and off.hull_views == 3
    assert drawn.views.silhouette_margin_px == default.views.silhouette_margin_px + reach
    assert drawn.surface.fair_iterations == default.surface.fair_iterations and drawn.pol == default.pol
    assert drawn.views.min_cos == default.views.min_cos
    assert refinement_options(default, SPECULAR_MEDIAN_DOP + 0.05, drawn_masks=True).offset_scan.mode == "off"
    assert refinement_options(default, 0.05, drawn_masks=False) is default
    wide = RefineOptions.model_validate({"views": {"silhouette_margin_px": 5, "drawn_mask_margin_px": 3}})
    assert refinement_options(wide, 0.05, drawn_masks=True).views.silhouette_margin_px == 8
    none = RefineOptions.model_validate({"views": {"drawn_mask_margin_px": 0}})
    assert refinement_options(none, 0.05, drawn_masks=True).views.silhouette_margin_px == default.views.silhouette_margin_px


def test_a_drawn_mask_limits_the_observations_as_a_given_one(tmp_path: Path) -> None:
    """Masks handed to refinement_observations for a capture decoded without masks give the
    observations the same capture decodes to with its masks given: the pixels outside invalid, the
    polarization noise measured inside only, the rest as decoded; a mask of another size is refused."""
    masked = _write_capture(tmp_path / "masked", masks=True)
    bare = _write_capture(tmp_path / "bare")
    config = PipelineConfig()
    assert config.refine.pol.aop_noise == "closure"
    with open_capture(masked) as cap_m, open_capture(bare) as cap_b:
        given = refinement_observations(cap_m, decode_views(cap_m, config), [0, 1], config.decode, config.refine)
        masks = [cap_m.read_mask(k) for k in (0, 1)]
        views_b = decode_views(cap_b, config)
        bare_obs = refinement_observations(cap_b, views_b, [0, 1], config.decode, config.refine)
        drawn = refinement_observations(cap_b, views_b, [0, 1], config.decode, config.refine, masks=masks)
        for k, mask in enumerate(masks):
            assert mask is not None and 0 < mask.mean() < 1 and bare_obs[k].valid[~mask].any()
            np.testing.assert_array_equal(drawn[k].valid, given[k].valid)
            np.testing.assert_array_equal(drawn[k].aop_noise, given[k].aop_noise)
            np.testing.assert_array_equal(drawn[k].intensity, bare_obs[k].intensity)
        assert within_mask(bare_obs[0], None) is bare_obs[0]
        with pytest.raises(ShapeError, match="mask"):
            within_mask(bare_obs[0], np.ones((4, 4), bool))


def test_masks_past_every_rim_are_warned_about() -> None:
    """An estimated mask margin of 0.5 px or more (the rim fit found the masks past every rim) is warned
    about, saying whether the fit discounted it; a small estimate, one a set margin accounts for, or no fit
    is not."""
    def fit(estimate: float, used: float | None) -> RimFit:
        margin = estimate if used is None else used
        return RimFit(np.zeros((1, 3)), 10, 5, 0.1, 0.2, 0.5, 0.25, margin, used is None, estimate)

    warning = mask_margin_warning(fit(1.0, None)) or ""
    assert "about 1.00 px" in warning and "dilated" in warning and "discounted that margin" in warning
    trusted = mask_margin_warning(fit(1.25, 0.0)) or ""  # a margin set (or the scans off): said so
    assert "about 1.25 px" in trusted and "discounted 0.00 px as set" in trusted and "pushed" in trusted
    # a small estimate, a set margin the estimate matches (1.0 set, 1.25 found), or no fit: quiet
    for quiet in (fit(0.25, None), fit(0.25, 0.0), fit(1.25, 1.0), None):
        assert mask_margin_warning(quiet) is None
    assert "about 1.75 px" in (mask_margin_warning(fit(1.75, 1.0)) or "")  # 0.75 px beyond the set margin


def test_cancel_stops_at_a_boundary(capture: Path, tmp_path: Path) -> None:
    calls = {"n": 0}

    def should_cancel() -> bool:
        calls["n"] += 1
        return calls["n"] > 2

    with pytest.raises(CanceledError):
        run(
            PipelineConfig(stop_after="decode"),
            capture,
            tmp_path / "out",
            progress=Progress(should_cancel=should_cancel),
        )
    assert not (tmp_path / "out/report.json").exists()


def test_reconstruct_cli_maps_flags_onto_the_config_tree(capture: Path, tmp_path: Path, capsys) -> None:
    import argparse

    from pmvir.commands.options import build_config
    from pmvir.commands.reconstruct import add_parser

    parser = argparse.ArgumentParser()
    add_parser(parser.add_subparsers())
    args = parser.parse_args(
        ["reconstruct", str(capture), "--out", "x", "--set", "decode.noise_floor=0.02", "--stop-after", "decode"]
    )
    config = build_config(args)
    assert config.decode.noise_floor == 0.02 and config.stop_after == "decode"
    bad = parser.parse_args(["reconstruct", str(capture), "--out", "x", "--set", "decode.noise_floor=2"])
    with pytest.raises(ConfigError, match=r"decode\.noise_floor"):
        build_config(bad)
    unknown = parser.parse_args(["reconstruct", str(capture), "--out", "x", "--set", "decode.nosuch=1"])
    with pytest.raises(ConfigError, match=r"decode\.nosuch"):
        build_config(unknown)


def test_reconstruct_cli_runs_and_reports_errors_in_one_line(capture: Path, tmp_path: Path, capsys) -> None:
    assert main(["reconstruct", str(capture), "--out", str(tmp_path / "o"), "--stop-after", "decode", "--quiet"]) == 0
    assert (tmp_path / "o/report.json").is_file()
    (capture / "capture.json").write_text("{not json")
    assert main(["reconstruct", str(capture), "--out", str(tmp_path / "o2"), "--stop-after", "decode", "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "capture.json" in err and "Traceback" not in err


def test_refinement_images_can_come_from_another_demosaicing(capture: Path) -> None:
    """refine.demosaic decodes the frames once more for the refinement; 'same' reuses the decode stage's."""
    config = PipelineConfig(decode={"demosaic": "guided", "noise_floor": 0.24})
    with open_capture(capture) as cap:
        views = decode_views(cap, config)
        indices = [2, 0]
        same = refinement_observations(
            cap, views, indices, config.decode, config.refine.model_copy(update={"demosaic": "same"})
        )
        also_same = refinement_observations(
            cap, views, indices, config.decode, config.refine.model_copy(update={"demosaic": "guided"})
        )
        eari = refinement_observations(
            cap, views, indices, config.decode, config.refine.model_copy(update={"demosaic": "eari"})
        )
        for k, i in enumerate(indices):
            assert same[k].aop is views[i].images.aop and also_same[k].aop is views[i].images.aop
            raw = cap.read_raw(i)
            expected = decode_frame(
                raw.mosaic, cap.layout, saturated=raw.saturated, options=DecodeOptions(demosaic="eari", noise_floor=0.24)
            )
            np.testing.assert_array_equal(eari[k].aop, expected.aop)
            np.testing.assert_array_equal(eari[k].intensity, expected.i_min)  # refine.pho.intensity 'min'
            np.testing.assert_array_equal(eari[k].valid, expected.valid)  # the decode stage's noise floor
            # the sensor noise of the frames makes the two methods' estimates differ pixel by pixel
            assert np.abs(eari[k].dop - views[i].images.dop).max() > 1e-3
    # frame 0's mean I_int (0.2) sits under the noise floor 0.24, frame 2's (0.28) above it
    assert not eari[1].valid.any() and eari[0].valid.mean() > 0.8


def test_refinement_images_carry_their_frames_polarization_noise(capture: Path) -> None:
    """refine.pol.aop_noise 'closure' measures each frame's closure noise over the refinement images'
    valid pixels; 'uniform' and the MVIR baseline (no E_pol) measure none."""
    config = PipelineConfig()
    with open_capture(capture) as cap:
        views = decode_views(cap, config)
        for refine in (config.refine, config.refine.model_copy(update={"demosaic": "same"})):
            obs = refinement_observations(cap, views, [2], config.decode, refine)[0]
            raw = cap.read_raw(2)
            expected = closure_noise(raw.mosaic, cap.layout, valid=obs.valid, sigma_px=refine.pol.aop_noise_px)
            np.testing.assert_array_equal(obs.aop_noise, expected)
            measured = obs.aop_noise[obs.valid]
            assert np.isfinite(measured).all() and measured.min() > 0.0
        for update in ({"pol": {"aop_noise": "uniform"}}, {"pol": {"enabled": False}}):
            refine = RefineOptions.model_validate(update)
            assert refinement_observations(cap, views, [2], config.decode, refine)[0].aop_noise is None
