"""Benchmark of ``pmvir synth`` with the built-in renderer: time per view and in total.

Usage: .venv/bin/python bench/synth.py [--views 36] [--size 612x512] [--shape blob]
       [--material plastic] [--lighting sh] [--keep DIR]

Prints one row per view (render = ray casting + shading; view = render + sensor
+ writing frame, mask and gt/views/*.npz) and a summary, and writes
bench/results/synth.json. Target: 36 views at 612x512 in under 60 s on a
2-core machine.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _results import table, write_results

from pmvir.synth.generate import ViewDone, synthesize


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--views", type=int, default=36)
    ap.add_argument("--size", default="612x512")
    ap.add_argument("--shape", default="blob")
    ap.add_argument("--material", default="plastic")
    ap.add_argument("--lighting", default="sh")
    ap.add_argument("--keep", type=Path, help="write the capture here instead of a temporary folder")
    args = ap.parse_args()

    rows: list[ViewDone] = []

    def progress(v: ViewDone) -> None:
        rows.append(v)
        print(f"{v.index:5d} {v.render_s * 1000:10.1f} {v.total_s * 1000:10.1f}", flush=True)

    print(
        f"pmvir synth --shape {args.shape} --views {args.views} --size {args.size} "
        f"--material {args.material} --lighting {args.lighting} (builtin renderer)"
    )
    print(f"{'view':>5} {'render ms':>10} {'view ms':>10}")
    with tempfile.TemporaryDirectory() as tmp:
        out = args.keep if args.keep else Path(tmp) / "capture"
        t0 = time.perf_counter()
        synthesize(
            out,
            shape=args.shape,
            views=args.views,
            size=args.size,
            material=args.material,
            lighting=args.lighting,
            overwrite=True,
            progress=progress,
        )
        total = time.perf_counter() - t0
        size_mb = sum(p.stat().st_size for p in Path(out).rglob("*") if p.is_file()) / 1e6
    render = np.array([r.render_s for r in rows])
    view = np.array([r.total_s for r in rows])
    setup = total - view.sum()
    print(
        f"\nviews {len(rows)}: render mean {render.mean() * 1000:.1f} ms (max {render.max() * 1000:.1f}), "
        f"view mean {view.mean() * 1000:.1f} ms; setup + final files {setup:.2f} s; "
        f"total {total:.2f} s (target < 60 s); capture {size_mb:.1f} MB"
    )
    result = {
        "options": vars(args) | {"keep": str(args.keep) if args.keep else None},
        "per_view_render_s": render.round(4).tolist(),
        "per_view_total_s": view.round(4).tolist(),
        "render_mean_s": float(render.mean()),
        "view_mean_s": float(view.mean()),
        "setup_and_final_s": float(setup),
        "total_s": float(total),
        "target_s": 60.0,
        "capture_mb": float(size_mb),
    }
    rows_out = [
        [
            f"{args.shape}, {args.material}, {args.lighting}",
            len(rows),
            args.size,
            round(render.mean() * 1000, 1),
            round(view.mean() * 1000, 1),
            round(setup, 2),
            round(total, 2),
            round(size_mb, 1),
        ]
    ]
    write_results(
        "synth",
        title="Synthetic captures (pmvir synth, built-in renderer)",
        tables=[
            table(
                "Time per view and in total (target: 36 views of 612x512 in under 60 s on 2 cores)",
                ["capture", "views", "size", "render ms/view", "view ms", "setup + final s", "total s", "MB"],
                rows_out,
                note="render = ray casting + shading; view = render + sensor + writing frame, mask and truth",
            )
        ],
        data=result,
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
