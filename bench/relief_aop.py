"""The decoded AoP against the true azimuth of the surface, at the pixels where the relief is.

For a synthetic capture (``pmvir synth``: gt/views/<stem>.npz holds each view's true camera-frame
normals and mask) every frame is decoded as the pipeline does (``decode``, default options, and
the unbiased DoP), and the AoP compared with the perspective-exact azimuth alpha of the true
normal (spec section 2). A plastic's AoP is alpha where diffuse reflection dominates and
alpha + 90 degrees where specular reflection does, so the error is taken modulo 90 degrees: what
remains is the decoding's (noise, demosaicing blur) and the renderer's mixing of the two.

"Relief pixels" are object pixels at least 3 px inside the mask whose true normal turns by more
than --relief-deg from the normal map blurred over --relief-px (Gaussian sigma): the detail a
smooth surface does not have. The noise-free AoP the renderer saved (gt/views ``aop``) is scored
the same way, so what the decoding loses shows apart from what the model cannot see.

A second table per capture checks nu, the AoP noise E_pol's absolute weight predicts from the
polarizer closure residual (``refine.pol.aop_noise_scale_deg``), against the decoding's own error
(the decoded AoP against the renderer's noise-free one, modulo 90 degrees) on the polarized pixels,
by quintiles of nu. Beside nu it gives nu with the relief's share of the residual taken out
(:func:`relief_free_closure`): with 0, 45, 90 and 135 degrees at the four corners of a block,
``r = (I0 + I90) - (I45 + I135)`` holds first differences of s1 and s2 across the block, which a
surface whose AoP turns inside a few pixels adds to the residual without being noise. The fit
``error^2 = a^2 + (b nu)^2`` over the quintiles gives the decoding's floor a and the share b of nu
that reaches the AoP after the demosaicing's averaging.

Prints a table and writes bench/results/relief_aop.json (or --out).
Run: .venv/bin/python bench/relief_aop.py CAPTURE [CAPTURE ...] [--relief-px 4] [--relief-deg 5] [--out FILE]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import cv2
import numpy as np
from _results import capture_description, table, write_results

from pmvir.capture import open_capture
from pmvir.config import DecodeOptions
from pmvir.decode import decode_frame
from pmvir.polarization.azimuth import perspective_azimuth
from pmvir.polarization.demosaic import demosaic
from pmvir.polarization.layout import MosaicLayout
from pmvir.polarization.noise import _CLOSURE_SIGN, closure_noise

ROOT = Path(__file__).resolve().parent
#: The "polarized" pixels: a decoded DoP at least this (E_pol's default floor, refine.pol.dop_min).
POL_DOP = 0.05


def err_mod_90(aop: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """|aop - alpha| modulo 90 degrees, in [0, 45], degrees."""
    d = np.mod(np.degrees(aop.astype(np.float64) - alpha), 90.0)
    return np.minimum(d, 90.0 - d)


def relief_pixels(normal_cam: np.ndarray, mask: np.ndarray, sigma_px: float, min_deg: float) -> np.ndarray:
    """Pixels inside the mask whose normal turns by more than ``min_deg`` from its blurred neighbourhood."""
    inside = cv2.erode(mask.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
    w = mask.astype(np.float32)
    blurred = np.stack([cv2.GaussianBlur(normal_cam[..., k] * w, (0, 0), sigma_px) for k in range(3)], -1)
    blurred /= np.maximum(np.linalg.norm(blurred, axis=-1, keepdims=True), 1e-9)
    turn = np.degrees(np.arccos(np.clip((blurred * normal_cam).sum(-1), -1.0, 1.0)))
    return inside & (turn > min_deg)


#: cos 2 theta and sin 2 theta of each angle (0, 45, 90, 135 degrees); the closure residual's signs
#: are pmvir.polarization.noise's.
_COS2 = np.array([1.0, 0.0, -1.0, 0.0])
_SIN2 = np.array([0.0, 1.0, 0.0, -1.0])
#: Gaussian sigma (px) of the demosaiced Stokes images the relief's share of the residual is taken from.
_STOKES_BLUR_PX = 1.0


def _blur(a: np.ndarray, sigma: float) -> np.ndarray:
    return cv2.GaussianBlur(a.astype(np.float32), (0, 0), sigma, borderType=cv2.BORDER_REPLICATE)


def relief_free_closure(mosaic: np.ndarray, layout: MosaicLayout, valid: np.ndarray, *, sigma_px: float = 3.0) -> np.ndarray:
    """:func:`~pmvir.polarization.noise.closure_noise` (same window) after subtracting from each block's
    residual what the demosaiced, slightly blurred Stokes images predict for it at the four samples'
    positions: ``sum sign * (s0 + s1 cos 2 theta + s2 sin 2 theta) / 2``, relative to s0."""
    h, w = mosaic.shape
    i = demosaic(mosaic, layout, method=DecodeOptions().demosaic).mean(-1)  # (H, W, 4) colour means
    s0 = _blur(0.5 * i.sum(-1), _STOKES_BLUR_PX)
    s1, s2 = _blur(i[..., 0] - i[..., 2], _STOKES_BLUR_PX), _blur(i[..., 1] - i[..., 3], _STOKES_BLUR_PX)
    index = layout.angle_index_block()
    r = np.zeros((h // 2, w // 2))
    block_s0, predicted, mean_s0 = np.zeros_like(r), np.zeros_like(r), np.zeros_like(r)
    ok = np.ones(r.shape, bool)
    for dy in range(2):
        for dx in range(2):
            a = index[dy, dx]
            r += _CLOSURE_SIGN[a] * mosaic[dy::2, dx::2]
            block_s0 += 0.5 * mosaic[dy::2, dx::2]
            predicted += 0.5 * _CLOSURE_SIGN[a] * (s0 + _COS2[a] * s1 + _SIN2[a] * s2)[dy::2, dx::2]
            mean_s0 += 0.25 * s0[dy::2, dx::2]
            ok &= valid[dy::2, dx::2]
    ok &= (block_s0 > 0) & (mean_s0 > 0)
    rel = np.where(ok, r / np.where(ok, block_s0, 1.0) - predicted / np.where(ok, mean_s0, 1.0), 0.0)
    weight = _blur(ok.astype(np.float32), 0.5 * sigma_px)
    mean_sq = _blur(rel * rel, 0.5 * sigma_px) / np.maximum(weight, 1e-12)
    return cv2.resize(np.sqrt(mean_sq), (w, h), interpolation=cv2.INTER_LINEAR)


def _nu_deg(sigma: np.ndarray, dop: np.ndarray) -> np.ndarray:
    """The AoP noise (degrees) a relative Stokes noise ``sigma`` gives at this DoP: sigma / (2 sqrt(2) DoP)."""
    return np.degrees(sigma / (2.0 * np.sqrt(2.0) * np.maximum(dop, 1e-3)))


def calibration(err: np.ndarray, nu: np.ndarray, nu_free: np.ndarray) -> dict:
    """The decoding's AoP error by quintile of nu, and the fit error^2 = a^2 + (b nu)^2 over the quintiles."""
    finite = np.isfinite(nu) & np.isfinite(nu_free)
    err, nu, nu_free = err[finite], nu[finite], nu_free[finite]
    edges = np.quantile(nu, np.linspace(0.0, 1.0, 6))
    bins = np.clip(np.searchsorted(edges, nu, side="right") - 1, 0, 4)
    rows = [{"nu": float(np.median(nu[bins == k])), "nu_relief_free": float(np.median(nu_free[bins == k])),
             "error": float(np.median(err[bins == k])), "pixels": int((bins == k).sum())} for k in range(5)]
    x = np.array([r["nu"] ** 2 for r in rows])
    y = np.array([r["error"] ** 2 for r in rows])
    slope, intercept = np.polyfit(x, y, 1)
    return {"quintiles": rows, "a_deg": float(np.sqrt(max(intercept, 0.0))), "b": float(np.sqrt(max(slope, 0.0)))}


def measure(capture: Path, sigma_px: float, min_deg: float) -> dict:
    """DoP-weighted and median AoP errors (mod 90) per decoding, at relief pixels and at all object pixels."""
    decodings = {"decoded (default)": DecodeOptions(), "decoded, unbiased DoP": DecodeOptions(dop_estimator="unbiased")}
    acc: dict[str, dict[str, list[np.ndarray]]] = {}
    checks: dict[str, list[np.ndarray]] = {"error": [], "nu": [], "nu_free": []}
    with open_capture(capture) as cap:
        for i, frame in enumerate(cap.frames):
            with np.load(capture / "gt" / "views" / f"{Path(frame.file).stem}.npz") as z:
                normal, mask, true_aop = z["normal_cam"].astype(np.float64), z["mask"], z["aop"]
            cam = frame.camera
            _, d_world = cam.pixel_rays()
            alpha, defined = perspective_azimuth(normal, d_world @ cam.R.T)
            regions = {"relief": relief_pixels(normal.astype(np.float32), mask, sigma_px, min_deg) & defined,
                       "all": cv2.erode(mask.astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool) & defined}
            raw = cap.read_raw(i)
            images = {"noise-free (renderer)": (true_aop, None, None)}
            for name, opts in decodings.items():
                d = decode_frame(raw.mosaic, cap.layout, saturated=raw.saturated, mask=cap.read_mask(i),
                                 options=opts)
                # the AoP noise E_pol's absolute weight predicts (refine.pol.aop_noise_scale_deg)
                sigma = closure_noise(raw.mosaic, cap.layout, valid=d.valid, sigma_px=3.0)
                nu = _nu_deg(sigma, d.dop)
                images[name] = (d.aop, d.dop, nu)
                if name == "decoded (default)":
                    polarized = regions["all"] & d.valid & (d.dop >= POL_DOP)
                    free = _nu_deg(relief_free_closure(raw.mosaic, cap.layout, d.valid), d.dop)
                    checks["error"].append(err_mod_90(d.aop, true_aop.astype(np.float64))[polarized])
                    checks["nu"].append(nu[polarized].astype(np.float64))
                    checks["nu_free"].append(free[polarized].astype(np.float64))
                for region in regions:
                    regions[region] &= d.valid
            for name, (aop, dop, nu) in images.items():
                err = err_mod_90(aop, alpha)
                polarized = regions["all"] & (np.ones_like(err, bool) if dop is None else dop >= POL_DOP)
                for region, sel in (*regions.items(), ("polarized", polarized)):
                    a = acc.setdefault(f"{name}|{region}", {"err": [], "dop": [], "nu": []})
                    a["err"].append(err[sel])
                    a["dop"].append(np.ones(int(sel.sum())) if dop is None else dop[sel].astype(np.float64))
                    a["nu"].append(np.full(int(sel.sum()), np.nan) if nu is None else nu[sel].astype(np.float64))
    out = {}
    for key, a in acc.items():
        err, w, nu = np.concatenate(a["err"]), np.concatenate(a["dop"]), np.concatenate(a["nu"])
        finite = nu[np.isfinite(nu)]
        out[key] = {"mean_deg": float(err.mean()), "median_deg": float(np.median(err)),
                    "dop_weighted_deg": float((err * w).sum() / max(w.sum(), 1e-12)), "pixels": int(err.size),
                    "predicted_noise_median_deg": float(np.median(finite)) if finite.size else None}
    out["calibration"] = calibration(*(np.concatenate(checks[k]) for k in ("error", "nu", "nu_free")))
    return out


def dop_free(name: str) -> bool:
    """The renderer's AoP comes without a decoded DoP: no "polarized" row for it."""
    return name.startswith("noise-free")


def relief_arguments(description: str, captures_help: str, out: Path) -> argparse.Namespace:
    """The command line of a benchmark over synthetic captures' relief pixels: the captures,
    --relief-px, --relief-deg and --out (default ``out``)."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("captures", type=Path, nargs="+", metavar="CAPTURE", help=captures_help)
    parser.add_argument("--relief-px", type=float, default=4.0, help="blur (Gaussian sigma, px) of the smooth normals")
    parser.add_argument("--relief-deg", type=float, default=5.0, help="turn (deg) from the smooth normal that is relief")
    parser.add_argument("--out", type=Path, default=out)
    return parser.parse_args()


def main() -> None:
    args = relief_arguments(__doc__.splitlines()[0], "synthetic captures (gt/views with normals)",
                            ROOT / "results" / "relief_aop.json")
    tables, data = [], {}
    for capture in args.captures:
        res = measure(capture, args.relief_px, args.relief_deg)
        data[str(capture)] = res
        rows = []
        for name in ("noise-free (renderer)", "decoded (default)", "decoded, unbiased DoP"):
            for region in ("relief", "all") if dop_free(name) else ("relief", "all", "polarized"):
                r = res[f"{name}|{region}"]
                nu = r["predicted_noise_median_deg"]
                rows.append([name, region, r["pixels"], round(r["mean_deg"], 2), round(r["median_deg"], 2),
                             round(r["dop_weighted_deg"], 2), None if nu is None else round(nu, 2)])
        print(f"{capture}\n{'AoP':<24} {'pixels':<9} {'count':>8} {'mean':>6} {'median':>6} {'DoP-w':>6} {'nu':>6}"
              "  (deg, mod 90)")
        for row in rows:
            print(f"{row[0]:<24} {row[1]:<9} {row[2]:8d} {row[3]:6.2f} {row[4]:6.2f} {row[5]:6.2f} "
                  f"{'-' if row[6] is None else format(row[6], '6.2f')}")
        made = capture_description(capture)
        tables.append(table(f"{capture.name} ({made}): AoP error modulo 90 deg against the true normal's azimuth",
                            ["AoP", "pixels", "count", "mean deg", "median deg", "DoP-weighted deg",
                             "predicted noise median deg"], rows,
                            note=f"relief: the true normal turns > {args.relief_deg} deg from its blur over "
                            f"{args.relief_px} px; polarized: all pixels with a decoded DoP of at least "
                            f"{POL_DOP}; predicted noise: closure residual / (2 sqrt(2) DoP), the nu of "
                            "refine.pol.aop_noise_scale_deg"))
        cal = res["calibration"]
        cal_rows = [[k + 1, q["pixels"], round(q["nu"], 2), round(q["nu_relief_free"], 2), round(q["error"], 2),
                     round(q["error"] / q["nu"], 3)] for k, q in enumerate(cal["quintiles"])]
        print(f"nu against the decoding's error (polarized pixels): a = {cal['a_deg']:.2f} deg, b = {cal['b']:.3f}")
        for row in cal_rows:
            print("  quintile {} ({} px): nu {} relief-free {} error {} (error / nu {})".format(*row))
        tables.append(table(f"{capture.name}: the predicted AoP noise nu against the decoding's error",
                            ["nu quintile", "pixels", "nu median deg", "relief-free nu median deg",
                             "decoding error median deg", "error / nu"], cal_rows,
                            note=f"polarized pixels (decoded DoP at least {POL_DOP}); decoding error: the decoded "
                            "AoP against the renderer's noise-free AoP, modulo 90 deg; relief-free nu: the closure "
                            "residual less what the demosaiced Stokes images predict for it; fit over the quintiles "
                            f"error^2 = a^2 + (b nu)^2: a = {cal['a_deg']:.2f} deg, b = {cal['b']:.3f}"))
    write_results(
        "relief_aop", title="Decoded AoP against the true azimuth at relief pixels", path=args.out,
        peer="the renderer's noise-free AoP", tables=tables,
        data={"relief_px": args.relief_px, "relief_deg": args.relief_deg, "results": data},
    )


if __name__ == "__main__":
    main()
