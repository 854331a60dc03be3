"""Where the decoded AoP's error comes from: the sensor's read-out, the renderer's noise, the albedo texture.

For synthetic captures rendered with ``pmvir synth --save-stokes`` (gt/views/<stem>.npz holds each
view's noise-free Stokes image, true camera-frame normals and mask), three AoPs are compared with the
perspective-exact azimuth of the true normal (spec section 2), modulo 90 degrees as on the page
"Decoded AoP at fine relief" (a plastic's AoP is the azimuth where diffuse reflection dominates and
90 degrees off it where specular reflection does):

* the renderer's own AoP (gt/views ``aop``, from the Stokes at each pixel),
* the capture's frames decoded as the pipeline does (default decode options),
* the same Stokes read out by the sensor model without shot or read noise (``full_well`` 0,
  ``read_noise`` 0, 12-bit quantization kept) and decoded the same way.

The renderer's AoP has every angle of a pixel from the same light paths; the mosaic samples each
polarizer angle at a different pixel, so whatever varies from pixel to pixel in the intensity (a path
tracer's Monte Carlo noise, a fine albedo texture, shot noise) reaches the demosaiced Stokes as false
polarization, and at a DoP of a few percent it turns the AoP. Comparing captures of one shape rendered
at different sample counts and with a uniform albedo separates the renderer's noise and the texture
from the read-out: the noise-free read-out row has no sensor noise at all.

"Relief pixels" are as in bench/relief_aop.py: object pixels whose true normal turns by more than
--relief-deg from the normal map blurred over --relief-px.

Prints a table and writes bench/results/aop_error_sources.json (or --out).
Run: .venv/bin/python bench/aop_error_sources.py CAPTURE [CAPTURE ...] [--relief-px 4] [--relief-deg 5]
"""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
from _results import table, write_results
from relief_aop import err_mod_90, relief_arguments, relief_pixels

from pmvir.capture import open_capture
from pmvir.decode import decode_frame
from pmvir.polarization.azimuth import perspective_azimuth
from pmvir.polarization.layout import MosaicLayout
from pmvir.synth.sensor import SensorModel, capture_mosaic

ROOT = Path(__file__).resolve().parent
SOURCES = ("renderer", "decoded frames", "decoded, noise-free read-out")


def _noise_free_floats(stokes: np.ndarray, sensor: dict, layout: MosaicLayout) -> tuple[np.ndarray, np.ndarray]:
    """The saved Stokes (already times the capture's gain) read out without noise: normalized samples
    and the saturated ones."""
    model = SensorModel(layout=layout, full_well=0.0, read_noise=0.0, black_level=int(sensor["black_level"]))
    samples = capture_mosaic(stokes, gain=1.0, sensor=model, rng=np.random.default_rng(0))
    span = np.float32(model.white_level - model.black_level)
    return (samples.astype(np.float32) - np.float32(model.black_level)) / span, samples >= model.white_level


def measure(capture: Path, sigma_px: float, min_deg: float) -> dict:
    """Median and mean AoP errors (mod 90) of each source at relief and at all object pixels, and the
    renderer's median DoP there."""
    synth = json.loads((capture / "gt" / "synth.json").read_text())
    errors: dict[str, dict[str, list[np.ndarray]]] = {s: {"relief": [], "all": []} for s in SOURCES}
    dops: list[np.ndarray] = []
    with open_capture(capture) as cap:
        for i, frame in enumerate(cap.frames):
            with np.load(capture / "gt" / "views" / f"{Path(frame.file).stem}.npz") as z:
                if "stokes" not in z.files:
                    raise SystemExit(f"{capture}: gt/views has no Stokes images; render it with --save-stokes")
                normal, mask = z["normal_cam"].astype(np.float64), z["mask"]
                stokes, true_aop, true_dop = z["stokes"], z["aop"], z["dop"]
            cam = frame.camera
            _, d_world = cam.pixel_rays()
            alpha, defined = perspective_azimuth(normal, d_world @ cam.R.T)
            raw = cap.read_raw(i)
            decoded = decode_frame(raw.mosaic, cap.layout, saturated=raw.saturated, mask=cap.read_mask(i))
            floats, saturated = _noise_free_floats(stokes, synth["sensor"], cap.layout)
            clean = decode_frame(floats, cap.layout, saturated=saturated, mask=cap.read_mask(i))
            inside = cv2.erode(mask.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
            valid = defined & decoded.valid & clean.valid
            regions = {"relief": relief_pixels(normal.astype(np.float32), mask, sigma_px, min_deg) & valid,
                       "all": inside & valid}
            for source, aop in zip(SOURCES, (true_aop, decoded.aop, clean.aop), strict=True):
                err = err_mod_90(aop, alpha)
                for region, sel in regions.items():
                    errors[source][region].append(err[sel])
            dops.append(true_dop[regions["all"]].astype(np.float64))
    out: dict = {"texture": synth["options"]["texture"], "renderer": synth["options"]["renderer"],
                 "spp": synth["options"]["spp"] if synth["options"]["renderer"] == "mitsuba" else None,
                 "views": len(dops), "true_dop_median": float(np.median(np.concatenate(dops)))}
    for source, regions_err in errors.items():
        for region, parts in regions_err.items():
            err = np.concatenate(parts)
            out[f"{source}|{region}"] = {"median_deg": float(np.median(err)), "mean_deg": float(err.mean()),
                                         "pixels": int(err.size)}
    return out


def _label(capture: Path, res: dict) -> str:
    """The capture in a row: its shape, renderer (sample count) and texture."""
    shape = json.loads((capture / "gt" / "synth.json").read_text())["source"].get("shape", "mesh")
    renderer = f"mitsuba {res['spp']} spp" if res["renderer"] == "mitsuba" else res["renderer"]
    return f"{shape}, {renderer}, {res['texture']} albedo"


def main() -> None:
    args = relief_arguments(__doc__.splitlines()[0], "synthetic captures rendered with --save-stokes",
                            ROOT / "results" / "aop_error_sources.json")
    data = {capture: measure(capture, args.relief_px, args.relief_deg) for capture in args.captures}
    rows = [[_label(capture, res), res["views"], round(res["true_dop_median"], 4), source,
             round(res[f"{source}|relief"]["median_deg"], 2), round(res[f"{source}|all"]["median_deg"], 2),
             round(res[f"{source}|all"]["mean_deg"], 2)]
            for capture, res in data.items() for source in SOURCES]
    columns = ["capture", "views", "true DoP median", "AoP", "relief median deg", "all median deg", "all mean deg"]
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join(str(c) for c in row))
    note = (f"AoP error modulo 90 deg against the true normal's azimuth; relief: the true normal turns > "
            f"{args.relief_deg} deg from its blur over {args.relief_px} px; all: object pixels 3 px inside the "
            "mask; noise-free read-out: the saved Stokes through the sensor model without shot or read noise, "
            "decoded with the default options")
    write_results(
        "aop_error_sources", title="Where the decoded AoP's error comes from", path=args.out,
        peer="the renderer's own AoP", tables=[table("AoP error by source", columns, rows, note=note)],
        data={"relief_px": args.relief_px, "relief_deg": args.relief_deg,
              "results": {str(capture): res for capture, res in data.items()}},
    )


if __name__ == "__main__":
    main()
