"""Demosaicing benchmark: pmvir vs polanalyser on 2448x2048 12-bit colour-polarization frames.

Synthetic frames (IMX250MYR layout) of a known Stokes field: the left half is
smooth, the right half textured (blocks, stripes near the per-angle Nyquist
limit, random speckle, sharp discs, a few saturated highlights); AoP and DoP
vary smoothly over the frame. Samples get photon shot noise (10,000 e- at
white), 2.5 e- read noise and 12-bit quantization.

Timed (wall clock, median and minimum over the calls, and CPU time of all threads, median),
round-robin on the same frames, 2 threads (cv2.setNumThreads(2), CPU
affinity limited to 2 cores when there are more):

* pmvir ``demosaic(mosaic_f32, layout, method=...)`` on the normalized float32
  mosaic (what the capture reader hands over), fresh output each call, and
  (bilinear) with ``out=`` reusing the previous result's memory;
* ``polanalyser.demosaicing(raw_u16, COLOR_PolarRGB)`` (and ``_EA``) on the
  uint16 samples (its fastest input; float input is slower there);
* the chain to AoP/DoP: pmvir ``decode_frame`` (demosaic, Stokes, I_int, I_min,
  validity) vs polanalyser demosaicing + ``calcStokes`` of the colour-mean
  intensities + ``cvtStokesToAoLP`` / ``cvtStokesToDoLP``.

The end-to-end target (``decode_frame`` with the default ``guided`` at
>= 2x polanalyser's chain's throughput) is timed first and on its own, robust to a shared
machine: the two chains alternate call by call on the same frames (``--pairs``
repeats, the order flipped from pair to pair), and the table gives each side's
median wall time and median process CPU time per frame, the ratio of the
medians and the median of the per-pair ratios (``--only-end-to-end``: only this,
written to results/demosaic_end_to_end.json).

Accuracy against the true field: AoP error (degrees, modulo 180) and DoP error,
mean and 90th percentile, on the valid pixels of the smooth half (8 px from the
texture and the border) and, separately, of the textured half. "Valid" is the
intersection over methods of pmvir's valid mask (noise floor 0.01, saturation
footprint), so every method is scored on the same pixels.

Physically rendered frames (``--mitsuba``, on by default): captures rendered
by ``pmvir synth --renderer mitsuba --save-stokes`` (Mitsuba 3 path tracing,
procedural albedo texture, environment lighting), cached under
bench/results/demosaic_frames/ (rendered once, a few minutes each):

* ``plastic``: the dented sphere, plastic, 2 views at 1224x1024, 64 spp;
* ``plastic-hq``: the torus knot, plastic, 2 views at 612x512, 1024 spp;
* ``lambert``: the blob, Lambertian (unpolarized), 2 views at 1224x1024, 64 spp.

(2448x2048 renders at enough samples per pixel take too long for a benchmark
on two cores: these are smaller, stated as such.) The noise-free per-pixel
Stokes image (gt/views ``stokes``) is the truth; the 12-bit frames are made
from it here through pmvir's sensor model (``capture_mosaic``: shot noise at
10,500 e-, read noise, black level 64), seeded, so every method sees the same
samples. Scored on the object (mask) pixels valid for every method (pmvir's
saturation footprint of the widest method, noise floor): DoP-weighted AoP error
``sum(dop_true * |aop - aop_true|) / sum(dop_true)`` (degrees, modulo 180)
and mean DoP error, for pmvir's methods and polanalyser's, same frames, same
run. On the Lambert capture (true DoP 0) the measured DoP is false
polarization: reported at albedo/shading edges (top 20 % of the true
intensity's log-gradient) and in flat areas (bottom 50 %).

Held-out frames (``--held-out``: only these, written to results/demosaic_heldout.json):
path-traced plastic frames of shapes, seeds, lighting and sensor noise the decoding was never
tuned on (the fine-relief rock, panel and cloth, the spring; 2 views each at 612x512, 32 spp,
cached beside the others), read out at three noise levels (the default sensor; a smaller full
well with more read noise; that at half the exposure). DoP error and DoP-weighted AoP error as
above, pooled over frames and noise levels, for the default decoding, its unbiased DoP
(``decode.dop_estimator unbiased``: :func:`pmvir.polarization.noise.unbiased_dop`) and polanalyser's.

Methods: pmvir's ``bilinear``, ``edge-aware``, ``guided``, ``eari`` (Morimatsu et al.'s
edge-aware residual interpolation) and ``eari-guided`` (EARI intensities, then the guided
polarization step), and polanalyser's two.

Run: .venv/bin/python bench/demosaic.py [--frames 3] [--reps 5] [--pairs 5] [--no-mitsuba]
     [--only-end-to-end] [--held-out]
Prints tables, writes bench/results/demosaic.json.
"""

from __future__ import annotations

import argparse
import importlib.metadata
import os
import platform
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from _results import table as results_table
from _results import write_results

from pmvir.config import DecodeOptions
from pmvir.decode import decode_frame
from pmvir.polarization.demosaic import demosaic, saturation_footprint, support_radius
from pmvir.polarization.layout import IMX250MYR, mosaic
from pmvir.polarization.stokes import intensities_from_polarization, polarization_images
from pmvir.synth.sensor import SensorModel, capture_mosaic

H, W = 2048, 2448
WHITE = 4095
FULL_WELL = 10_000.0  # electrons at white
READ_NOISE = 2.5  # electrons
MARGIN = 8


def make_frame(seed: int) -> dict[str, np.ndarray]:
    """Ground truth and 12-bit samples of one synthetic frame."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:H, 0:W].astype(np.float32)
    smooth = 0.45 + 0.15 * np.sin(x / 310 + seed) * np.cos(y / 270)
    tex = (
        0.25 * (((x // 37) + (y // 29)) % 2)
        + 0.2 * (np.sin(1.3 * x + 0.4 * y + seed) > 0)
        + 0.15 * rng.random((H, W), dtype=np.float32)
    )
    for _ in range(60):  # sharp-edged discs
        cy, cx, r = rng.uniform(0, H), rng.uniform(W / 2, W), rng.uniform(8, 60)
        disc = (y - cy) ** 2 + (x - cx) ** 2 < r * r
        tex[disc] = rng.uniform(0.0, 0.6)
    textured = x >= W / 2
    base = np.where(textured, 0.35 * smooth + 0.55 * tex, smooth)
    for _ in range(6):  # saturated highlights in the textured half
        cy, cx = rng.uniform(50, H - 50), rng.uniform(W / 2 + 50, W - 50)
        base[(y - cy) ** 2 + (x - cx) ** 2 < 15**2] = 2.5
    s0 = np.stack([0.9 * base, base, 0.7 * base], axis=-1).astype(np.float32)
    aop = np.mod(np.pi * (0.8 * x / W + 0.1 * np.sin(y / 300 + seed)), np.pi).astype(np.float32)
    dop = (0.05 + 0.4 * (0.5 + 0.5 * np.cos(x / 400) * np.sin(y / 350 + seed))).astype(np.float32)
    ints = intensities_from_polarization(s0, aop, dop)
    del s0
    clean = mosaic(ints, IMX250MYR)
    del ints
    electrons = rng.poisson(np.clip(clean, 0, None) * FULL_WELL).astype(np.float32)
    electrons += rng.normal(0.0, READ_NOISE, (H, W)).astype(np.float32)
    samples = np.clip(np.rint(electrons / FULL_WELL * WHITE), 0, WHITE).astype(np.uint16)
    return {"samples": samples, "aop": aop, "dop": dop, "textured": textured}


def polanalyser_aop_dop(channels: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """polanalyser's own Stokes/AoLP/DoLP of the colour-mean intensities of its [I0, I45, I90, I135]."""
    import polanalyser as pa

    means = np.stack([c.astype(np.float32).mean(axis=2) for c in channels])
    stokes = pa.calcStokes(means, np.deg2rad([0.0, 45.0, 90.0, 135.0]))
    with np.errstate(divide="ignore", invalid="ignore"):
        dop = np.clip(np.nan_to_num(pa.cvtStokesToDoLP(stokes)), 0.0, 1.0)
    return pa.cvtStokesToAoLP(stokes).astype(np.float32), dop.astype(np.float32)


def aop_err_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    d = np.abs(a.astype(np.float64) - b) % np.pi
    return np.degrees(np.minimum(d, np.pi - d))


def stats(values: np.ndarray) -> dict[str, float]:
    return {"mean": float(values.mean()), "p90": float(np.percentile(values, 90))}


#: Rendered captures: name -> synthesize() options (cached under bench/results/demosaic_frames/).
RENDERS: dict[str, dict[str, object]] = {
    "plastic": {"shape": "dented", "size": "1224x1024", "material": "plastic", "spp": 64},
    "plastic-hq": {"shape": "knot", "size": "612x512", "material": "plastic", "spp": 1024},
    "lambert": {"shape": "blob", "size": "1224x1024", "material": "lambert", "spp": 64},
}
PMVIR_METHODS = ("bilinear", "edge-aware", "guided", "eari", "eari-guided")
#: the method with the widest saturation footprint (scored pixels are valid for every method)
WIDEST = max(PMVIR_METHODS, key=lambda m: support_radius(IMX250MYR, m))
PA_METHODS = {"polanalyser COLOR_PolarRGB": "COLOR_PolarRGB", "polanalyser COLOR_PolarRGB_EA": "COLOR_PolarRGB_EA"}


#: Held-out renders: shapes, seeds, lighting and roughness the decoding was not tuned on.
HELD_OUT: dict[str, dict[str, object]] = {
    "heldout-rock": {"shape": "rock", "seed": 7, "lighting": "envmap"},
    "heldout-cloth": {"shape": "cloth", "seed": 11, "lighting": "sh"},
    "heldout-spring": {"shape": "spring", "seed": 13, "lighting": "envmap"},
    "heldout-panel": {"shape": "panel", "seed": 17, "lighting": "envmap", "roughness": 0.3},
}
#: Held-out read-outs: name -> (sensor, exposure gain).
HELD_OUT_NOISE: dict[str, tuple[SensorModel, float]] = {
    "default sensor": (SensorModel(), 1.0),
    "4,000 e-, read noise 0.002": (SensorModel(full_well=4000.0, read_noise=0.002), 1.0),
    "the same, half exposure": (SensorModel(full_well=4000.0, read_noise=0.002), 0.5),
}


def rendered_views(cache: Path, name: str) -> list[dict[str, np.ndarray]]:
    """Noise-free Stokes (H, W, 3, 3) and mask of each view of a cached Mitsuba capture (rendered if absent)."""
    from pmvir.synth.generate import synthesize

    cap = cache / name
    if not (cap / "capture.json").is_file():
        if name in HELD_OUT:
            synthesize(cap, views=2, size="612x512", material="plastic", renderer="mitsuba", spp=32,
                       save_stokes=True, overwrite=True, **HELD_OUT[name])
        else:
            opts = dict(RENDERS[name])
            synthesize(cap, shape=str(opts.pop("shape")), views=2, lighting="envmap", renderer="mitsuba",
                       save_stokes=True, overwrite=True, **opts)
    views = []
    for path in sorted((cap / "gt" / "views").glob("*.npz")):
        with np.load(path) as z:
            views.append({"stokes": z["stokes"], "mask": z["mask"], "name": f"{name}/{path.stem}"})
    return views


def decode_all(samples: np.ndarray) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(aop, dop, valid) of a 12-bit frame (black 64) for pmvir's methods and polanalyser's."""
    import polanalyser as pa

    sensor = SensorModel()
    span = sensor.white_level - sensor.black_level
    floats = (samples.astype(np.float32) - sensor.black_level) / np.float32(span)
    saturated = samples >= sensor.white_level
    out = {}
    for method in PMVIR_METHODS:
        d = decode_frame(floats, IMX250MYR, saturated=saturated, options=DecodeOptions(demosaic=method))
        out[f"pmvir {method}"] = (d.aop, d.dop, d.valid)
    above_black = np.clip(samples.astype(np.int32) - sensor.black_level, 0, None).astype(np.uint16)
    for name, code in PA_METHODS.items():
        aop, dop = polanalyser_aop_dop(pa.demosaicing(above_black, getattr(pa, code)))
        out[name] = (aop, dop, np.ones_like(dop, dtype=bool))
    return out


def true_aop_dop(stokes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    mean = stokes.astype(np.float64).mean(axis=2)
    aop = np.mod(0.5 * np.arctan2(mean[..., 2], mean[..., 1]), np.pi)
    dop = np.hypot(mean[..., 1], mean[..., 2]) / np.maximum(mean[..., 0], 1e-12)
    return aop, np.clip(dop, 0.0, 1.0)


def rendered_accuracy(cache: Path, seed: int) -> dict[str, dict[str, float]]:
    """DoP-weighted AoP error and DoP error per method, pooled over the plastic renders' views."""
    sums: dict[str, dict[str, float]] = {}
    for name in ("plastic", "plastic-hq"):
        for k, view in enumerate(rendered_views(cache, name)):
            samples = capture_mosaic(view["stokes"], gain=1.0, sensor=SensorModel(),
                                     rng=np.random.default_rng([seed, k, len(name)]))
            results = decode_all(samples)
            aop_t, dop_t = true_aop_dop(view["stokes"])
            sel = view["mask"].copy()
            for _, _, valid in results.values():
                sel &= valid
            sel &= ~saturation_footprint(samples >= SensorModel().white_level, IMX250MYR, method=WIDEST)
            for method, (aop, dop, _) in results.items():
                err = aop_err_deg(aop[sel], aop_t[sel])
                for _key, acc in ((name, sums.setdefault(f"{method}|{name}", {})),
                                 ("all", sums.setdefault(f"{method}|all", {}))):
                    acc["w_err"] = acc.get("w_err", 0.0) + float((dop_t[sel] * err).sum())
                    acc["w"] = acc.get("w", 0.0) + float(dop_t[sel].sum())
                    acc["dop_err"] = acc.get("dop_err", 0.0) + float(np.abs(dop[sel] - dop_t[sel]).sum())
                    acc["n"] = acc.get("n", 0.0) + float(sel.sum())
    return {key: {"aop_dopw_deg": v["w_err"] / v["w"], "dop_err": v["dop_err"] / v["n"], "pixels": v["n"]}
            for key, v in sums.items()}


HELD_OUT_METHODS = ("pmvir guided (default)", "pmvir guided, unbiased DoP", "pmvir bilinear",
                    "pmvir bilinear, unbiased DoP", "polanalyser COLOR_PolarRGB")


def held_out_accuracy(cache: Path, seed: int) -> dict[str, dict[str, float]]:
    """DoP error and DoP-weighted AoP error per method on the held-out renders, per noise level and pooled."""
    import polanalyser as pa

    sums: dict[str, dict[str, float]] = {}
    for name in HELD_OUT:
        for k, view in enumerate(rendered_views(cache, name)):
            aop_t, dop_t = true_aop_dop(view["stokes"])
            for level, (sensor, gain) in HELD_OUT_NOISE.items():
                samples = capture_mosaic(view["stokes"], gain=gain, sensor=sensor,
                                         rng=np.random.default_rng([seed, k, len(name), len(level)]))
                span = sensor.white_level - sensor.black_level
                floats = (samples.astype(np.float32) - sensor.black_level) / np.float32(span * gain)
                saturated = samples >= sensor.white_level
                results = {}
                sel = view["mask"] & ~saturation_footprint(saturated, IMX250MYR, method=WIDEST)
                for method in ("guided", "bilinear"):
                    for estimator in ("plain", "unbiased"):
                        d = decode_frame(floats, IMX250MYR, saturated=saturated,
                                         options=DecodeOptions(demosaic=method, dop_estimator=estimator))
                        label = f"pmvir {method}" + (" (default)" if method == "guided" else "")
                        results[label if estimator == "plain" else f"pmvir {method}, unbiased DoP"] = (d.aop, d.dop)
                        sel &= d.valid
                above_black = np.clip(samples.astype(np.int32) - sensor.black_level, 0, None).astype(np.uint16)
                results["polanalyser COLOR_PolarRGB"] = polanalyser_aop_dop(pa.demosaicing(above_black,
                                                                                           pa.COLOR_PolarRGB))
                for method, (aop, dop) in results.items():
                    err = aop_err_deg(aop[sel], aop_t[sel])
                    for key in (f"{method}|{level}", f"{method}|all"):
                        acc = sums.setdefault(key, {})
                        acc["w_err"] = acc.get("w_err", 0.0) + float((dop_t[sel] * err).sum())
                        acc["w"] = acc.get("w", 0.0) + float(dop_t[sel].sum())
                        acc["dop_err"] = acc.get("dop_err", 0.0) + float(np.abs(dop[sel] - dop_t[sel]).sum())
                        acc["dop_bias"] = acc.get("dop_bias", 0.0) + float((dop[sel] - dop_t[sel]).sum())
                        acc["n"] = acc.get("n", 0.0) + float(sel.sum())
    return {key: {"aop_dopw_deg": v["w_err"] / v["w"], "dop_err": v["dop_err"] / v["n"],
                  "dop_bias": v["dop_bias"] / v["n"], "pixels": v["n"]} for key, v in sums.items()}


def held_out_main(cache: Path, seed: int) -> None:
    """Measure the held-out frames, print the table and write results/demosaic_heldout.json."""
    acc = held_out_accuracy(cache, seed)
    ref = acc["polanalyser COLOR_PolarRGB|all"]
    rows = []
    for method in HELD_OUT_METHODS:
        a = acc[f"{method}|all"]
        rows.append([method, round(a["dop_err"], 4), round(a["dop_err"] / ref["dop_err"], 2),
                     round(a["dop_bias"], 4), round(a["aop_dopw_deg"], 2),
                     round(a["aop_dopw_deg"] / ref["aop_dopw_deg"], 2)])
    columns = ["method", "DoP error", "x polanalyser", "DoP bias", "AoP DoP-weighted deg", "x polanalyser"]
    per_level = []
    for level in HELD_OUT_NOISE:
        r = acc[f"polanalyser COLOR_PolarRGB|{level}"]
        for method in HELD_OUT_METHODS:
            a = acc[f"{method}|{level}"]
            per_level.append([level, method, round(a["dop_err"], 4), round(a["dop_err"] / r["dop_err"], 2),
                              round(a["aop_dopw_deg"], 2), round(a["aop_dopw_deg"] / r["aop_dopw_deg"], 2)])
    print(f"{'method':<32} {'DoP err':>8} {'x pa':>5} {'bias':>8} {'AoP deg':>8} {'x pa':>5}")
    for row in rows:
        print(f"{row[0]:<32} {row[1]:8.4f} {row[2]:5.2f} {row[3]:+8.4f} {row[4]:8.2f} {row[5]:5.2f}")
    for row in per_level:
        print(f"  {row[0]:<28} {row[1]:<32} DoP {row[2]:.4f} ({row[3]:.2f}x)  AoP {row[4]:.2f} ({row[5]:.2f}x)")
    write_results(
        "demosaic_heldout", title="Decoding on held-out path-traced frames against polanalyser",
        peer="polanalyser demosaicing (COLOR_PolarRGB) + calcStokes + cvtStokesToAoLP/DoLP",
        tables=[
            results_table("Held-out path-traced plastic frames (pooled over renders and noise levels)", columns, rows,
                          note=f"{', '.join(HELD_OUT)}: 2 views each, 612x512, 32 spp; "
                          f"{len(HELD_OUT_NOISE)} noise levels. DoP error: mean |DoP - true DoP|; "
                          "AoP: DoP-weighted mean error modulo 180 deg"),
            results_table("Per noise level", ["noise", "method", "DoP error", "x polanalyser", "AoP deg",
                                               "x polanalyser"], per_level),
        ],
        data={"renders": {k: {**v, "views": 2, "size": "612x512", "spp": 32} for k, v in HELD_OUT.items()},
              "noise": {k: {"full_well": s.full_well, "read_noise": s.read_noise, "exposure": g}
                        for k, (s, g) in HELD_OUT_NOISE.items()},
              "seed": seed, "results": acc},
    )


def lambert_false_polarization(cache: Path, seed: int) -> dict[str, dict[str, float]]:
    """Mean measured DoP of an unpolarized (Lambertian) surface at intensity edges and in flat areas."""
    acc: dict[str, dict[str, list[np.ndarray]]] = {}
    for k, view in enumerate(rendered_views(cache, "lambert")):
        samples = capture_mosaic(view["stokes"], gain=1.0, sensor=SensorModel(),
                                 rng=np.random.default_rng([seed, k, 99]))
        results = decode_all(samples)
        s0 = view["stokes"][..., 0].mean(axis=2).astype(np.float32)
        log_s0 = np.log(np.maximum(s0, 1e-4))
        grad = np.hypot(cv2.Sobel(log_s0, cv2.CV_32F, 1, 0), cv2.Sobel(log_s0, cv2.CV_32F, 0, 1)) / 8
        sel = cv2.erode(view["mask"].astype(np.uint8), np.ones((7, 7), np.uint8)).astype(bool)
        for _, _, valid in results.values():
            sel &= valid
        edge_t, flat_t = np.percentile(grad[sel], [80, 50])
        regions = {"edges": sel & (grad >= edge_t), "flat": sel & (grad <= flat_t), "all": sel}
        for method, (_, dop, _) in results.items():
            for region, m in regions.items():
                acc.setdefault(method, {}).setdefault(region, []).append(dop[m])
    return {method: {region: float(np.concatenate(v).mean()) for region, v in regions_.items()}
            for method, regions_ in acc.items()}


def paired_end_to_end(ours: Callable[[int], object], theirs: Callable[[int], object], n_frames: int,
                      reps: int) -> dict[str, Any]:
    """Alternating calls of two chains on the same frames: per-frame wall and process CPU time, and ratios.

    Each repeat calls both on every frame, back to back, the order alternating from pair to pair,
    so a change of machine load between calls hits both about equally. Reports the medians of
    each side, their ratio (theirs / ours) and the median of the per-pair ratios, for wall-clock
    time and for the process's CPU time (all threads: what the work costs, whatever else runs).
    """
    wall: dict[str, list[float]] = {"ours": [], "theirs": []}
    cpu: dict[str, list[float]] = {"ours": [], "theirs": []}
    pair_wall, pair_cpu = [], []
    load_before = os.getloadavg()[0]
    ours(0), theirs(0)  # warm-up
    for rep in range(reps):
        for k in range(n_frames):
            order = [("ours", ours), ("theirs", theirs)]
            if (rep + k) % 2:
                order.reverse()
            got = {}
            for name, fn in order:
                t, c = time.perf_counter(), time.process_time()
                result = fn(k)
                got[name] = (time.perf_counter() - t, time.process_time() - c)
                del result
            for name, (w, c) in got.items():
                wall[name].append(w)
                cpu[name].append(c)
            pair_wall.append(got["theirs"][0] / got["ours"][0])
            pair_cpu.append(got["theirs"][1] / got["ours"][1])
    med = {f"{kind}_{name}_s": float(np.median(v[name])) for kind, v in (("wall", wall), ("cpu", cpu))
           for name in ("ours", "theirs")}
    return {
        **med,
        "pairs": len(pair_wall),
        "wall_ratio_of_medians": med["wall_theirs_s"] / med["wall_ours_s"],
        "wall_median_paired_ratio": float(np.median(pair_wall)),
        "cpu_ratio_of_medians": med["cpu_theirs_s"] / med["cpu_ours_s"],
        "cpu_median_paired_ratio": float(np.median(pair_cpu)),
        "load_average_1min_before_after": [load_before, os.getloadavg()[0]],
    }


def print_end_to_end(e2e: dict[str, Any], args: argparse.Namespace) -> None:
    """The alternating end-to-end comparison as a small table."""
    load = e2e["load_average_1min_before_after"]
    print(f"\nEnd to end, {W}x{H} 12-bit mosaic -> 12 channels + Stokes/AoP/DoP, {e2e['pairs']} alternating "
          f"pairs ({args.frames} frames x {args.pairs}), cv2 threads {cv2.getNumThreads()}, CPUs "
          f"{sorted(os.sched_getaffinity(0))}, load average {load[0]:.1f} -> {load[1]:.1f}:")
    print(f"{'chain':<52} {'median wall ms':>15} {'median CPU ms':>14}")
    print(f"{'pmvir decode_frame (guided, the default)':<52} {1000 * e2e['wall_ours_s']:15.1f} "
          f"{1000 * e2e['cpu_ours_s']:14.1f}")
    print(f"{'polanalyser demosaicing + calcStokes + AoLP/DoLP':<52} {1000 * e2e['wall_theirs_s']:15.1f} "
          f"{1000 * e2e['cpu_theirs_s']:14.1f}")
    print(f"throughput pmvir / polanalyser: wall {e2e['wall_ratio_of_medians']:.2f}x (ratio of medians), "
          f"{e2e['wall_median_paired_ratio']:.2f}x (median of paired ratios); CPU "
          f"{e2e['cpu_ratio_of_medians']:.2f}x / {e2e['cpu_median_paired_ratio']:.2f}x")


def end_to_end_table(e2e: dict[str, Any]) -> dict[str, Any]:
    """The alternating end-to-end comparison, for the benchmarks page."""
    return results_table(
        f"End to end: {W}x{H} 12-bit mosaic to 12 channels, Stokes, AoP and DoP ({e2e['pairs']} alternating pairs)",
        ["chain", "median wall ms", "median CPU ms"],
        [
            ["pmvir decode_frame (guided, the default)", round(1000 * e2e["wall_ours_s"], 1),
             round(1000 * e2e["cpu_ours_s"], 1)],
            ["polanalyser demosaicing + calcStokes + AoLP/DoLP", round(1000 * e2e["wall_theirs_s"], 1),
             round(1000 * e2e["cpu_theirs_s"], 1)],
        ],
        note=f"throughput pmvir / polanalyser: wall {e2e['wall_ratio_of_medians']:.2f}x, "
        f"CPU {e2e['cpu_ratio_of_medians']:.2f}x (ratios of the medians)",
    )


def page_tables(table_rows: list[dict[str, Any]], rendered: dict[str, dict[str, float]],
                lambert: dict[str, dict[str, float]], e2e: dict[str, Any]) -> list[dict[str, Any]]:
    """The benchmarks page's tables: end to end, speed and accuracy on synthetic frames, rendered frames."""
    tables = [end_to_end_table(e2e)]
    tables.append(results_table(
        f"Speed per {W}x{H} frame (2 threads)",
        ["method", "median ms", "frames/s", "MPix/s", "x polanalyser (wall)", "x polanalyser (CPU)"],
        [[r["name"], round(1000 * r["median_s"], 1), round(r["frames_per_s"], 2), round(r["mpix_per_s"], 1),
          round(r["throughput_vs_polanalyser"], 2), round(r["throughput_vs_polanalyser_cpu"], 2)]
         for r in table_rows],
        note="demosaicing rows against polanalyser COLOR_PolarRGB, decode_frame rows against its whole chain",
    ))
    acc_rows = []
    for r in table_rows:
        a = r.get("accuracy")
        if a:
            acc_rows.append([r["name"], round(a["aop_smooth"]["mean"], 3), round(a["aop_smooth"]["p90"], 3),
                             round(a["dop_smooth"]["mean"], 4), round(a["aop_textured"]["mean"], 2),
                             round(a["dop_textured"]["mean"], 4)])
    tables.append(results_table(
        "Accuracy on synthetic frames (shot and read noise, 12 bits)",
        ["method", "AoP smooth mean deg", "AoP smooth p90 deg", "DoP smooth mean", "AoP textured mean deg",
         "DoP textured mean"],
        acc_rows,
        note="valid pixels of every method, 8 px from the border and the texture edge",
    ))
    if rendered:
        names = [f"pmvir {m}" for m in PMVIR_METHODS] + list(PA_METHODS)
        tables.append(results_table(
            "Path-traced plastic frames (Mitsuba 3), noise through pmvir's sensor model",
            ["method", "AoP DoP-weighted deg (dented)", "AoP (knot)", "AoP (all)", "DoP error (all)",
             "false DoP at edges (Lambert)", "false DoP flat (Lambert)"],
            [[n, round(rendered[f"{n}|plastic"]["aop_dopw_deg"], 2), round(rendered[f"{n}|plastic-hq"]["aop_dopw_deg"], 2),
              round(rendered[f"{n}|all"]["aop_dopw_deg"], 2), round(rendered[f"{n}|all"]["dop_err"], 4),
              round(lambert[n]["edges"], 4), round(lambert[n]["flat"], 4)] for n in names],
        ))
    return tables


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=3)
    parser.add_argument("--reps", type=int, default=5)
    parser.add_argument("--pairs", type=int, default=5,
                        help="repeats of the alternating end-to-end comparison (times --frames pairs)")
    parser.add_argument("--only-end-to-end", action="store_true",
                        help="only the alternating end-to-end timing (no other timings, no accuracy)")
    parser.add_argument("--no-mitsuba", dest="mitsuba", action="store_false",
                        help="skip the physically rendered frames")
    parser.add_argument("--held-out", action="store_true",
                        help="only the held-out path-traced frames (results/demosaic_heldout.json)")
    parser.add_argument("--cache", type=Path, default=Path(__file__).parent / "results" / "demosaic_frames",
                        help="where the Mitsuba captures are cached")
    args = parser.parse_args()

    import polanalyser as pa

    if args.held_out:
        held_out_main(args.cache, seed=2026)
        return
    cores = sorted(os.sched_getaffinity(0))
    if len(cores) > 2:
        os.sched_setaffinity(0, cores[:2])
    cv2.setNumThreads(2)

    frames = [make_frame(seed) for seed in range(args.frames)]
    floats = [f["samples"].astype(np.float32) / np.float32(WHITE) for f in frames]
    reuse = demosaic(floats[0], IMX250MYR)

    demosaic_runs = {
        "pmvir bilinear": lambda k: demosaic(floats[k], IMX250MYR, method="bilinear"),
        "pmvir bilinear, out= reused": lambda k: demosaic(floats[k], IMX250MYR, method="bilinear", out=reuse),
        "pmvir edge-aware": lambda k: demosaic(floats[k], IMX250MYR, method="edge-aware"),
        "pmvir guided": lambda k: demosaic(floats[k], IMX250MYR, method="guided"),
        "pmvir eari": lambda k: demosaic(floats[k], IMX250MYR, method="eari"),
        "pmvir eari-guided": lambda k: demosaic(floats[k], IMX250MYR, method="eari-guided"),
        "polanalyser COLOR_PolarRGB": lambda k: pa.demosaicing(frames[k]["samples"], pa.COLOR_PolarRGB),
        "polanalyser COLOR_PolarRGB_EA": lambda k: pa.demosaicing(frames[k]["samples"], pa.COLOR_PolarRGB_EA),
    }
    def decode_run(method: str) -> Callable[[int], object]:
        return lambda k: decode_frame(floats[k], IMX250MYR, saturated=frames[k]["samples"] >= WHITE,
                                      options=DecodeOptions(demosaic=method))

    chain_runs = {
        **{f"pmvir decode_frame ({m})": decode_run(m) for m in ("bilinear", "guided", "eari", "eari-guided")},
        "polanalyser demosaic+Stokes+AoLP/DoLP": lambda k: polanalyser_aop_dop(
            pa.demosaicing(frames[k]["samples"], pa.COLOR_PolarRGB)
        ),
    }
    end_to_end = paired_end_to_end(decode_run("guided"), chain_runs["polanalyser demosaic+Stokes+AoLP/DoLP"],
                                   len(frames), args.pairs)
    print_end_to_end(end_to_end, args)
    if args.only_end_to_end:
        write_results(
            "demosaic_end_to_end", title="Decoding end to end against polanalyser",
            peer="polanalyser demosaicing + calcStokes + cvtStokesToAoLP/DoLP",
            tables=[end_to_end_table(end_to_end)],
            data={"frames": args.frames, "pairs": args.pairs,
                  "frame": {"width": W, "height": H, "bit_depth": 12, "layout": "IMX250MYR"},
                  "ours": "pmvir decode_frame (guided)", "theirs": "polanalyser demosaic+Stokes+AoLP/DoLP",
                  "machine": {"cpus_used": sorted(os.sched_getaffinity(0)), "cv2_threads": cv2.getNumThreads()},
                  "results": end_to_end},
        )
        return
    times: dict[str, list[float]] = {name: [] for name in {**demosaic_runs, **chain_runs}}
    cpu_times: dict[str, list[float]] = {name: [] for name in times}
    for runs in (demosaic_runs, chain_runs):
        for fn in runs.values():  # warm-up
            fn(0)
        for _ in range(args.reps):
            for k in range(len(frames)):
                for name, fn in runs.items():
                    t, c = time.perf_counter(), time.process_time()
                    result = fn(k)
                    times[name].append(time.perf_counter() - t)
                    cpu_times[name].append(time.process_time() - c)
                    del result

    # accuracy on every frame, pooled
    methods = [f"pmvir {m}" for m in PMVIR_METHODS] + ["polanalyser COLOR_PolarRGB",
                                                       "polanalyser COLOR_PolarRGB_EA"]
    errors: dict[str, dict[str, list[np.ndarray]]] = {m: {} for m in methods}
    for k, f in enumerate(frames):
        sat = f["samples"] >= WHITE
        results = {}
        valid = np.ones((H, W), bool)
        for method in PMVIR_METHODS:
            d = decode_frame(floats[k], IMX250MYR, saturated=sat, options=DecodeOptions(demosaic=method))
            results[f"pmvir {method}"] = (d.aop, d.dop)
            valid &= d.valid
        for code, name in ((pa.COLOR_PolarRGB, "polanalyser COLOR_PolarRGB"),
                           (pa.COLOR_PolarRGB_EA, "polanalyser COLOR_PolarRGB_EA")):
            results[name] = polanalyser_aop_dop(pa.demosaicing(f["samples"], code))
        inner = np.zeros((H, W), bool)
        inner[MARGIN:-MARGIN, MARGIN:-MARGIN] = True
        x = np.arange(W)[None, :]
        smooth = inner & valid & (x < W / 2 - MARGIN)
        textured = inner & valid & (x >= W / 2 + MARGIN)
        for name, (aop, dop) in results.items():
            for region, sel in (("smooth", smooth), ("textured", textured)):
                errors[name].setdefault(f"aop_{region}", []).append(aop_err_deg(aop[sel], f["aop"][sel]))
                errors[name].setdefault(f"dop_{region}", []).append(np.abs(dop[sel] - f["dop"][sel]))
        # sanity: pmvir through polarization_images agrees with decode_frame's AoP
        assert np.allclose(
            polarization_images(demosaic(floats[k], IMX250MYR), noise_floor=0.01).dop,
            results["pmvir bilinear"][1],
            atol=1e-5,
        )

    mpix = H * W / 1e6
    table = []
    for name, ts in times.items():
        med = float(np.median(ts))
        row = {"name": name, "median_s": med, "min_s": float(np.min(ts)), "frames_per_s": 1 / med,
               "mpix_per_s": mpix / med, "calls": len(ts), "cpu_median_s": float(np.median(cpu_times[name]))}
        if name in errors:
            row["accuracy"] = {key: stats(np.concatenate(v)) for key, v in errors[name].items()}
        table.append(row)
    base = next(r for r in table if r["name"] == "polanalyser COLOR_PolarRGB")
    chain_base = next(r for r in table if r["name"].startswith("polanalyser demosaic+"))
    for row in table:
        ref = chain_base if row["name"] in chain_runs else base
        row["throughput_vs_polanalyser"] = row["frames_per_s"] / ref["frames_per_s"]
        # on a shared machine the fastest call is the least disturbed one; CPU time (all threads)
        # is what the work costs whatever else runs
        row["throughput_vs_polanalyser_min"] = ref["min_s"] / row["min_s"]
        row["throughput_vs_polanalyser_cpu"] = ref["cpu_median_s"] / row["cpu_median_s"]

    print(f"{args.frames} frames {W}x{H} 12-bit IMX250MYR, {args.reps} reps each, round-robin; "
          f"cv2 threads {cv2.getNumThreads()}, CPUs {sorted(os.sched_getaffinity(0))}, "
          f"load average {os.getloadavg()[0]:.1f}")
    head = (f"{'method':<40} {'med ms':>7} {'fps':>6} {'MPix/s':>7} {'x pa':>5} {'min':>5} {'cpu':>5} "
            f"{'AoP smooth mean/p90 deg':>24} {'DoP smooth mean/p90':>20} "
            f"{'AoP tex mean/p90':>17} {'DoP tex mean/p90':>17}")
    print(head)
    print("-" * len(head))
    for r in table:
        acc = r.get("accuracy")
        cols = ""
        if acc:
            cols = (f" {acc['aop_smooth']['mean']:>11.3f} / {acc['aop_smooth']['p90']:<10.3f}"
                    f" {acc['dop_smooth']['mean']:>8.4f} / {acc['dop_smooth']['p90']:<9.4f}"
                    f" {acc['aop_textured']['mean']:>7.2f} / {acc['aop_textured']['p90']:<7.2f}"
                    f" {acc['dop_textured']['mean']:>7.4f} / {acc['dop_textured']['p90']:<7.4f}")
        print(f"{r['name']:<40} {1000 * r['median_s']:7.1f} {r['frames_per_s']:6.2f} {r['mpix_per_s']:7.1f} "
              f"{r['throughput_vs_polanalyser']:5.2f} {r['throughput_vs_polanalyser_min']:5.2f} "
              f"{r['throughput_vs_polanalyser_cpu']:5.2f}{cols}")
    ratio = next(r for r in table if r["name"] == "pmvir bilinear")["throughput_vs_polanalyser"]
    print(f"throughput ratio pmvir bilinear / polanalyser COLOR_PolarRGB: {ratio:.2f}x")

    rendered: dict[str, dict[str, float]] = {}
    lambert: dict[str, dict[str, float]] = {}
    if args.mitsuba:
        rendered = rendered_accuracy(args.cache, seed=1)
        lambert = lambert_false_polarization(args.cache, seed=1)
        names = [f"pmvir {m}" for m in PMVIR_METHODS] + list(PA_METHODS)
        base_r = rendered["polanalyser COLOR_PolarRGB|all"]
        print("\nMitsuba-rendered plastic frames (noise through pmvir's sensor model), same frames, same run:")
        head = (f"{'method':<32} {'AoP dopw deg: dented 1224 / knot 612 / all':>44} {'x pa':>5}"
                f" {'DoP err: dented / knot / all':>30} {'x pa':>5}")
        print(head)
        print("-" * len(head))
        for n in names:
            r = [rendered[f"{n}|{part}"] for part in ("plastic", "plastic-hq", "all")]
            print(f"{n:<32} {r[0]['aop_dopw_deg']:>18.2f} / {r[1]['aop_dopw_deg']:6.2f} / "
                  f"{r[2]['aop_dopw_deg']:6.2f}   {r[2]['aop_dopw_deg'] / base_r['aop_dopw_deg']:5.2f}"
                  f" {r[0]['dop_err']:>12.4f} / {r[1]['dop_err']:.4f} / {r[2]['dop_err']:.4f}"
                  f" {r[2]['dop_err'] / base_r['dop_err']:5.2f}")
        print("\nFalse polarization on the Lambert capture (true DoP 0): mean measured DoP")
        print(f"{'method':<32} {'edges':>8} {'flat':>8} {'all':>8}")
        for n in names:
            v = lambert[n]
            print(f"{n:<32} {v['edges']:8.4f} {v['flat']:8.4f} {v['all']:8.4f}")
    chain = {r["name"]: r for r in table}
    print("end to end (decode_frame vs polanalyser chain; median wall / min wall / median CPU): " + ", ".join(
        f"{m} {row['throughput_vs_polanalyser']:.2f}x / {row['throughput_vs_polanalyser_min']:.2f}x / "
        f"{row['throughput_vs_polanalyser_cpu']:.2f}x"
        for m in ("bilinear", "guided", "eari", "eari-guided") for row in [chain[f"pmvir decode_frame ({m})"]]))

    print_end_to_end(end_to_end, args)

    write_results("demosaic", title="Demosaicing and decoding against polanalyser",
                  peer=f"polanalyser {importlib.metadata.version('polanalyser')}",
                  tables=page_tables(table, rendered, lambert, end_to_end), data={
        "frame": {"width": W, "height": H, "bit_depth": 12, "layout": "IMX250MYR",
                  "full_well_e": FULL_WELL, "read_noise_e": READ_NOISE},
        "frames": args.frames, "reps": args.reps,
        "machine": {"cpus_used": sorted(os.sched_getaffinity(0)), "cpu_count": os.cpu_count(),
                    "cv2_threads": cv2.getNumThreads(), "platform": platform.platform(),
                    "python": platform.python_version(), "numpy": np.__version__, "opencv": cv2.__version__,
                    "polanalyser": importlib.metadata.version("polanalyser"),
                    "load_average_1_5_15min_at_end": list(os.getloadavg())},
        "note": "AoP errors in degrees (mod 180); DoP errors absolute; accuracy pixels: valid for every "
                "method, 8 px from border and texture edge. Timings are wall-clock medians; the machine "
                "may be shared.",
        "results": table,
        "throughput_ratio_bilinear_vs_polanalyser": ratio,
        "end_to_end_guided_vs_polanalyser": end_to_end,
        "rendered": {"renders": RENDERS, "accuracy": rendered, "lambert_false_dop": lambert},
    })


if __name__ == "__main__":
    main()
