"""Full-size captures: peak memory and time per stage at 612x512, 1224x1024 and 2448x2048.

For each size a built-in capture of the same object (blob, plastic, environment light,
``--views`` views) is synthesized, then reconstructed with the default options (and any
``--set KEY=VALUE``) in a child process run under ``/usr/bin/time -v`` (the whole run's peak
resident memory). The child records each stage's own peak (the kernel's high-water mark, reset
at every stage boundary through ``/proc/self/clear_refs``) and time; the mesh is evaluated
against the ground truth. A size's views can be set apart (``--views-for 2448x2048=12``).
Prints a table with each run's working size, vertices, time per stage, its time per megapixel
and view, its accuracy against the smallest run and its median normal error; writes bench/results/fullsize.json
(``--append`` keeps the stored runs of the other sizes).

    .venv/bin/python bench/fullsize.py [--views 36] [--sizes 612x512 1224x1024 2448x2048] [--work DIR]
        [--set KEY=VALUE ...] [--views-for SIZE=N ...] [--append]
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

from _results import ROOT, table, write_results

GIB = 2**30
RESULTS_PATH = ROOT / "bench" / "results" / "fullsize.json"


def _vm_hwm_bytes() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) * 1024
    return 0


def _reset_hwm() -> None:
    try:
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:  # not Linux, or not allowed: the peaks then accumulate
        pass


def child(capture: Path, out: Path, overrides: list[str]) -> None:
    """Reconstruct ``capture`` into ``out`` with the defaults and ``overrides``; write ``out/stage_memory.json``."""
    from pmvir.commands.options import parse_overrides
    from pmvir.config import PipelineConfig
    from pmvir.pipeline import run
    from pmvir.progress import Progress

    peaks: dict[str, int] = {}
    current: list[str] = []

    def on_event(stage: str, fraction: float, message: str) -> None:
        top = str(stage).split("/")[0]
        if current and current[0] != top:
            peaks[current[0]] = max(peaks.get(current[0], 0), _vm_hwm_bytes())
            _reset_hwm()
            current[0] = top
            (out / "stage_memory.json").write_text(json.dumps(peaks))  # kept when a run is stopped later
        elif not current:
            current.append(top)

    _reset_hwm()
    run(PipelineConfig.model_validate(parse_overrides(overrides)), capture, out, progress=Progress(on_event))
    if current:
        peaks[current[0]] = max(peaks.get(current[0], 0), _vm_hwm_bytes())
    (out / "stage_memory.json").write_text(json.dumps(peaks))


def _peak_rss_bytes(time_v: str) -> int:
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", time_v)
    return int(m.group(1)) * 1024 if m else 0


def _stage_peaks(out: Path) -> dict[str, int]:
    path = out / "stage_memory.json"
    return json.loads(path.read_text()) if path.is_file() else {}


def measure(size: str, views: int, work: Path, overrides: list[str], *, reuse: bool = False) -> dict:
    from pmvir.evaluate import evaluate_paths
    from pmvir.synth import synthesize

    w, h = (int(x) for x in size.split("x"))
    capture = work / f"cap_{size}_{views}v"
    if not (capture / "capture.json").is_file():
        synthesize(capture, shape="blob", views=views, size=(w, h), material="plastic", lighting="envmap", seed=7)
    out = work / f"out_{size}_{views}v"
    time_v = out / "time-v.txt"
    finished = (out / "report.json").is_file() and "refine" in _stage_peaks(out)
    if not (reuse and finished):
        proc = subprocess.run(
            ["/usr/bin/time", "-v", sys.executable, __file__, "--child", str(capture), str(out),
             *(f"--set={o}" for o in overrides)],
            capture_output=True, text=True, check=False,
        )
        if proc.returncode != 0:
            return {"size": size, "views": views, "error": proc.stderr[-2000:]}
        time_v.write_text(proc.stderr)
    report = json.loads((out / "report.json").read_text())
    stage_peaks = _stage_peaks(out)
    # without /usr/bin/time's record (a run whose measuring process stopped), the largest stage peak
    peak = _peak_rss_bytes(time_v.read_text()) if time_v.is_file() else max(stage_peaks.values())
    metrics = evaluate_paths(out, capture / "gt")
    timings = report["timings_s"]
    subdivision = report.get("geometry", {}).get("subdivision", {})
    return {
        "size": size,
        "views": views,
        "megapixels_x_views": round(w * h * views / 1e6, 1),
        "resolution": report.get("resolution"),
        "vertices": subdivision.get("vertices"),
        "subdivision_rounds": subdivision.get("rounds"),
        "peak_rss_gib": round(peak / GIB, 2),
        "peak_from": "/usr/bin/time -v" if time_v.is_file() else "stage peaks",
        "stage_peak_gib": {k: round(v / GIB, 2) for k, v in stage_peaks.items()},
        "stage_s": {k: round(float(timings[k]), 1) for k in ("decode", "geometry", "refine") if k in timings},
        "total_s": round(float(timings["total"]), 1),
        "accuracy": metrics.accuracy,
        "completeness": metrics.completeness,
        "normal_error_median": getattr(metrics, "normal_error_median", None),
    }


def fit_memory(runs: list[dict]) -> dict[str, float] | None:
    """The coefficients of :mod:`pmvir.memory`'s model fitted to the runs' peaks (non-negative least squares).

    peak = base + per_view_pixel * views * working pixels + per_frame_pixel * frame pixels; None with
    fewer than three measured runs.
    """
    import numpy as np
    from scipy.optimize import nnls

    ok = [r for r in runs if "error" not in r and r.get("resolution")]
    if len(ok) < 3:
        return None
    features = []
    for r in ok:
        w, h = (int(x) for x in r["size"].split("x"))
        f = int(r["resolution"]["binning"])
        features.append([1.0, r["views"] * (w // f) * (h // f), w * h])
    a = np.array(features, np.float64)
    scale = a.max(axis=0)
    coef, _ = nnls(a / scale, np.array([r["peak_rss_gib"] * GIB for r in ok]))
    base, per_view_pixel, per_frame_pixel = (float(c) for c in coef / scale)
    return {"base_bytes": base, "per_view_pixel_bytes": per_view_pixel, "per_frame_pixel_bytes": per_frame_pixel}


def _row(r: dict, reference: dict | None) -> list:
    """One table row: sizes, vertices, peaks, seconds per stage, the time per megapixel and view, accuracy,
    completeness and the median normal error."""
    if "error" in r:
        return [r["size"], r["views"], None, None, None, None, None, None, None, None, None, None, None, "failed", None]
    peaks, secs = r["stage_peak_gib"], r["stage_s"]
    res = r["resolution"] or {}
    per_mpv = round(r["total_s"] / r["megapixels_x_views"], 2)
    versus = ""
    if reference is not None and reference is not r and "error" not in reference:
        versus = f" ({(r['accuracy'] / reference['accuracy'] - 1) * 100:+.0f}%)"
    return [
        r["size"], r["views"], res.get("refine"), r.get("vertices"),
        r["peak_rss_gib"] if r.get("peak_from") != "stage peaks" else f"{r['peak_rss_gib']} *",
        peaks.get("decode"), peaks.get("geometry"), peaks.get("refine"),
        secs.get("decode"), secs.get("geometry"), secs.get("refine"), per_mpv,
        f"{r['accuracy'] * 100:.4f}{versus}", f"{r['completeness'] * 100:.4f}",
        None if r.get("normal_error_median") is None else round(r["normal_error_median"], 2),
    ]


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--child", nargs=2, type=Path, metavar=("CAPTURE", "OUT"), help=argparse.SUPPRESS)
    p.add_argument("--views", type=int, default=36, help="views per capture (default 36)")
    p.add_argument("--views-for", nargs="+", default=[], metavar="SIZE=N",
                   help="views of one size instead of --views, e.g. 2448x2048=12")
    p.add_argument("--sizes", nargs="+", default=["612x512", "1224x1024", "2448x2048"])
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="an option of every run, as `pmvir reconstruct --set` takes it")
    p.add_argument("--append", action="store_true",
                   help="keep the stored runs of sizes not measured now (bench/results/fullsize.json)")
    p.add_argument("--reuse", action="store_true",
                   help="measure again only the sizes without a finished run in --work (its files are read back)")
    p.add_argument("--work", type=Path, default=ROOT / "bench" / "results" / "fullsize")
    args = p.parse_args()
    if args.child:
        child(*args.child, args.overrides)
        return
    args.work.mkdir(parents=True, exist_ok=True)
    views_for = dict(item.split("=") for item in args.views_for)
    runs = [measure(size, int(views_for.get(size, args.views)), args.work, args.overrides, reuse=args.reuse)
            for size in args.sizes]
    stored = RESULTS_PATH.is_file() and args.append
    if stored:
        kept = [r for r in json.loads(RESULTS_PATH.read_text())["runs"] if r["size"] not in args.sizes]
        runs = sorted(kept + runs, key=lambda r: int(r["size"].split("x")[0]))
    reference = runs[0] if runs else None
    rows = [_row(r, reference) for r in runs]
    columns = [
        "frames", "views", "working size", "vertices", "peak RSS GiB", "decode GiB", "geometry GiB", "refine GiB",
        "decode s", "geometry s", "refine s", "s per MP x view", "accuracy x1e-2", "completeness x1e-2",
        "normal error median deg",
    ]
    options = ", ".join(args.overrides) or "default options"
    tab = table(f"Full-size captures: peak memory and time per stage ({options})", columns, rows,
                note="Peak RSS from /usr/bin/time -v (* where its record was lost: the largest stage peak); "
                "per-stage peaks from the kernel's high-water mark; "
                "s per MP x view: the whole run's seconds per megapixel of frames times views; accuracy in "
                "brackets: against the first row's")
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join("" if v is None else str(v) for v in row))
    fit = fit_memory(runs)
    if fit is not None:
        print("pmvir.memory fitted: " + ", ".join(f"{k} {v:.4g}" for k, v in fit.items()))
    write_results("fullsize", title="Full-size captures", tables=[tab],
                  data={"options": args.overrides, "runs": runs, "memory_fit": fit})


if __name__ == "__main__":
    main()
