"""Full-size captures: peak memory and time per stage at 612x512, 1224x1024 and 2448x2048.

For each size a built-in capture of the same object (blob, plastic, environment light,
``--views`` views) is synthesized, then reconstructed with the default options in a child
process run under ``/usr/bin/time -v`` (the whole run's peak resident memory). The child
records each stage's own peak (the kernel's high-water mark, reset at every stage boundary
through ``/proc/self/clear_refs``) and time; the mesh is evaluated against the ground truth.
Prints a table and writes bench/results/fullsize.json.

    .venv/bin/python bench/fullsize.py [--views 36] [--sizes 612x512 1224x1024 2448x2048] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
import time
from pathlib import Path

from _results import ROOT, table, write_results

GIB = 2**30


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


def child(capture: Path, out: Path) -> None:
    """Reconstruct ``capture`` into ``out`` with the defaults; write ``out/stage_memory.json``."""
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
        elif not current:
            current.append(top)

    _reset_hwm()
    run(PipelineConfig(), capture, out, progress=Progress(on_event))
    if current:
        peaks[current[0]] = max(peaks.get(current[0], 0), _vm_hwm_bytes())
    (out / "stage_memory.json").write_text(json.dumps(peaks))


def _peak_rss_bytes(time_v: str) -> int:
    m = re.search(r"Maximum resident set size \(kbytes\): (\d+)", time_v)
    return int(m.group(1)) * 1024 if m else 0


def measure(size: str, views: int, work: Path) -> dict:
    from pmvir.evaluate import evaluate_paths
    from pmvir.synth import synthesize

    w, h = (int(x) for x in size.split("x"))
    capture = work / f"cap_{size}"
    if not (capture / "capture.json").is_file():
        synthesize(capture, shape="blob", views=views, size=(w, h), material="plastic", lighting="envmap", seed=7)
    out = work / f"out_{size}"
    t0 = time.perf_counter()
    proc = subprocess.run(
        ["/usr/bin/time", "-v", sys.executable, __file__, "--child", str(capture), str(out)],
        capture_output=True, text=True, check=False,
    )
    wall = time.perf_counter() - t0
    if proc.returncode != 0:
        return {"size": size, "views": views, "error": proc.stderr[-2000:], "wall_s": wall}
    report = json.loads((out / "report.json").read_text())
    stage_peaks = json.loads((out / "stage_memory.json").read_text())
    metrics = evaluate_paths(out, capture / "gt")
    timings = report["timings"]
    return {
        "size": size,
        "views": views,
        "megapixels_x_views": round(w * h * views / 1e6, 1),
        "resolution": report.get("resolution"),
        "peak_rss_gib": round(_peak_rss_bytes(proc.stderr) / GIB, 2),
        "stage_peak_gib": {k: round(v / GIB, 2) for k, v in stage_peaks.items()},
        "stage_s": {k: round(float(timings[k]), 1) for k in ("decode", "geometry", "refine") if k in timings},
        "total_s": round(float(timings["total"]), 1),
        "accuracy": metrics.accuracy,
        "completeness": metrics.completeness,
        "normal_error_median": getattr(metrics, "normal_error_median", None),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--child", nargs=2, type=Path, metavar=("CAPTURE", "OUT"), help=argparse.SUPPRESS)
    p.add_argument("--views", type=int, default=36)
    p.add_argument("--sizes", nargs="+", default=["612x512", "1224x1024", "2448x2048"])
    p.add_argument("--work", type=Path, default=ROOT / "bench" / "results" / "fullsize")
    args = p.parse_args()
    if args.child:
        child(*args.child)
        return
    args.work.mkdir(parents=True, exist_ok=True)
    runs = [measure(size, args.views, args.work) for size in args.sizes]
    rows = []
    for r in runs:
        if "error" in r:
            rows.append([r["size"], r["views"], None, None, None, None, None, None, None, None, "failed"])
            continue
        peaks, secs = r["stage_peak_gib"], r["stage_s"]
        res = r["resolution"] or {}
        rows.append([
            r["size"], r["views"], res.get("refine"), r["peak_rss_gib"],
            peaks.get("decode"), peaks.get("geometry"), peaks.get("refine"),
            secs.get("decode"), secs.get("geometry"), secs.get("refine"),
            f"{r['accuracy'] * 100:.3f} / {r['completeness'] * 100:.3f}",
        ])
    columns = [
        "frames", "views", "working size", "peak RSS GiB", "decode GiB", "geometry GiB", "refine GiB",
        "decode s", "geometry s", "refine s", "accuracy / completeness (x1e-2)",
    ]
    tab = table("Full-size captures: peak memory and time per stage (default options)", columns, rows,
                note="Peak RSS from /usr/bin/time -v; per-stage peaks from the kernel's high-water mark.")
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join("" if v is None else str(v) for v in row))
    write_results("fullsize", title="Full-size captures", tables=[tab], data={"runs": runs})


if __name__ == "__main__":
    main()
