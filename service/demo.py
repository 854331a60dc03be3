"""``make demo``: the main job end to end, on an embedded synthetic capture.

It starts Redis, the API and a worker by itself (loopback ports, a storage
folder under ``--out``), generates a synthetic capture with ground truth
(built-in shape, no download), submits it over HTTP with ``pmvir submit``
(upload, start, progress, download), prints the result's accuracy against the
ground truth and, when stdin is a terminal, the web console's address, keeping
the service up until Enter so the result can be looked at in a browser; without
a terminal, or with ``--no-wait``, it stops everything it started while it
evaluates the result (and at once when a step fails).

    python -m service.demo --out demo-out [--views 24] [--size 408x340] [--no-wait]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from pmvir.cli import main as pmvir_main
from pmvir.stages import AVAILABLE_STAGES

API_KEY = "demo-key"
#: A lighter schedule than the defaults so the demo ends in about a minute on an idle 2-core
#: machine, longer on a loaded one (the benchmarks page, "Time of make demo"): coarser subdivision (about 8 px^2 per triangle), 15 L-BFGS iterations per stage (on the demo's
#: capture rendered with seeds 0-2, 12 saved 8 of 52 evaluations and kept the accuracy within 1 %,
#: but the albedo's RMSE rose by 13 %, 0.119 to 0.134 on average), a stage ends
#: once an iteration gains under 0.03 % (the second stage stalls there: its last four iterations took
#: 15 evaluations for 0.03 %), and the offset scan only before the first stage (on this capture the
#: later scans moved the surface by under 0.1 px at 3 s each, while the first one buys 4 % in
#: accuracy); no textured exports (the decimated mesh's UV atlas and texture bake take about 17 s
#: and the console shows mesh.glb, which is written as always).
DEMO_OPTIONS = (
    "--set", "geometry.subdivision.max_area_px=8", "--set", "refine.solver.max_iterations=15",
    "--set", "refine.solver.rel_tolerance=3e-4",
    "--set", "refine.offset_scan.mode=start", "--set", "export.textured=false",
)


def _parse_args(argv: list[str] | None) -> argparse.Namespace:
    p = argparse.ArgumentParser(prog="python -m service.demo", description=__doc__.split("\n\n")[0])
    p.add_argument(
        "--out", type=Path, default=Path("demo-out"), help="folder for everything (default demo-out)"
    )
    p.add_argument("--shape", default="blob", help="built-in shape (default blob)")
    p.add_argument("--material", default="plastic", choices=("lambert", "plastic", "conductor"))
    p.add_argument("--views", type=int, default=24, help="views (default 24)")
    p.add_argument("--size", default="408x340", help="image size WxH, multiples of 4 (default 408x340)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-wait", action="store_true", help="stop the service at the end even in a terminal")
    return p.parse_args(argv)


def main(argv: list[str] | None = None) -> int:
    from service.testing import ServiceStack  # the same launcher the end-to-end tests use

    args = _parse_args(argv)
    out = args.out.resolve()
    capture, result = out / "capture", out / "result"
    out.mkdir(parents=True, exist_ok=True)
    stop_after = AVAILABLE_STAGES[-1]

    t0 = time.perf_counter()
    print(f"[demo] 1/4 synthesizing a {args.views}-view {args.material} '{args.shape}' capture -> {capture}")
    # the capture is rendered while the service starts (Redis, the API and the worker mostly wait on imports)
    synth = ThreadPoolExecutor(max_workers=1)
    rendered = synth.submit(
        pmvir_main,
        [
            "synth",
            "--shape",
            args.shape,
            "--out",
            str(capture),
            "--views",
            str(args.views),
            "--size",
            args.size,
            "--material",
            args.material,
            "--seed",
            str(args.seed),
            "--force",
            "--quiet",
        ],
    )
    synth.shutdown(wait=False)
    print("[demo] 2/4 starting redis-server, the API and a worker")
    stack = ServiceStack(out / "service", api_keys=(API_KEY,))
    try:
        stack.start()  # Redis, then the worker and the API loading at once
        print(f"[demo]     API at {stack.url}; logs in {stack.log_dir}")
        rc = rendered.result()
        if rc:
            return rc
        print(f"[demo] 3/4 submitting over HTTP (stop after '{stop_after}')")
        os.environ["PMVIR_API_KEY"] = API_KEY
        rc = pmvir_main(
            [
                "submit",
                str(capture),
                "--server",
                stack.url,
                "--out",
                str(result),
                "--stop-after",
                stop_after,
                "--poll",
                "0.5",
                "--label",
                "demo",
                *DEMO_OPTIONS,
            ]
        )
        if rc:
            print(f"[demo] the job did not succeed; service logs:\n{stack.logs()}", file=sys.stderr)
            return rc
        print("[demo] 4/4 result")
        if args.no_wait or not sys.stdin.isatty():
            # nothing left for the service to do: it stops while the result is evaluated
            stopping = threading.Thread(target=stack.stop)
            stopping.start()
            try:
                _summarize(result, capture)
            finally:
                stopping.join()
            return _done(t0, out)
        _summarize(result, capture)
        print(f"[demo] the web console: {stack.url}/ui/  (API key: {API_KEY}); API docs: {stack.url}/docs")
        try:
            input("[demo] the service stays up until you press Enter ")
        except (EOFError, KeyboardInterrupt):
            print()
    finally:
        stack.stop()  # also after a failed step; a stopped stack stops at once
    return _done(t0, out)


def _done(t0: float, out: Path) -> int:
    print("[demo]     service stopped")
    print(f"[demo] done in {time.perf_counter() - t0:.0f} s; everything is under {out}")
    return 0


def _summarize(result: Path, capture: Path) -> None:
    report = json.loads((result / "report.json").read_text())
    timings = ", ".join(f"{k} {v:.1f} s" for k, v in report["timings_s"].items())
    print(f"[demo]     stages {report['stages']}: {timings}")
    # the initial surface, and the refined result (mesh, albedo, lighting) when refinement ran
    rows = [("initial.ply", result / "initial.ply"), ("mesh.ply", result)]
    rows = [(name, path) for name, path in rows if (result / name).exists()]
    if rows:
        from pmvir.evaluate import evaluate_paths

        keys = ("accuracy", "completeness", "albedo_rmse", "illumination_error")
        print("[demo]     against the ground truth (distances in bounding-box diagonals):")
        print("[demo]       " + f"{'':12s}" + "".join(f"{k:>20s}" for k in keys))
        for name, path in rows:
            metrics = evaluate_paths(path, capture / "gt").to_dict()
            cells = "".join(
                f"{'n/a' if metrics[k] is None else format(metrics[k], '.5f'):>20s}" for k in keys
            )
            print(f"[demo]       {name:12s}{cells}")
        return
    decoded = sorted((result / "decoded").glob("*.npz"))
    print(f"[demo]     {len(decoded)} decoded frames with previews in {result / 'decoded'}")


if __name__ == "__main__":
    sys.exit(main())
