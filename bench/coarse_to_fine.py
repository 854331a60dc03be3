"""Coarse to fine: the refinement's first stages on the surface one sqrt(3) step coarser (refine.stages.coarse).

A built-in capture (``pmvir synth``, the demo's by default: blob, plastic, 24 views of 408x340) goes
through the decode and geometry stages once (cached in ``--work``); the refinement then runs once per
value of ``refine.stages.coarse`` (``--values``) with the same options (``--set KEY=VALUE``), and once
more as MVIR (``refine.pol.enabled=false``, ``refine.stages.coarse`` 0). Prints per run the
refinement's seconds (the coarse stages and the rest), its cost evaluations, and the result's
accuracy, completeness and normal error against the ground truth; writes
bench/results/coarse_to_fine.json. The first value is the peer: times and accuracy are also given as
ratios to it, and the median normal error as a ratio to MVIR's.

Run: .venv/bin/python bench/coarse_to_fine.py [--values 0 1 2] [--shape blob] [--views 24]
     [--size 408x340] [--set KEY=VALUE ...] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

from _results import table, write_results

from pmvir.commands.options import parse_overrides
from pmvir.config import PipelineConfig, merge_options
from pmvir.evaluate import evaluate_paths
from pmvir.pipeline import run

PMVIR = str(Path(sys.executable).with_name("pmvir"))


#: MVIR, the peer of the normal error: the refinement without the polarimetric term.
MVIR = "refine.pol.enabled=false"


def _config(overrides: list[str], coarse: int, mvir: bool) -> PipelineConfig:
    tree = merge_options(parse_overrides(overrides), {"refine": {"stages": {"coarse": coarse}}})
    if mvir:
        tree = merge_options(tree, parse_overrides([MVIR]))
    return PipelineConfig.model_validate(tree)


def _measure(capture: Path, work: Path, overrides: list[str], coarse: int, *, mvir: bool = False) -> dict:
    out = work / ("result-mvir" if mvir else f"result-coarse{coarse}")
    shutil.rmtree(out, ignore_errors=True)
    cache = work / "cache"
    resume = "refine" if (cache / "geometry.pkl").exists() else None
    run(_config(overrides, coarse, mvir), capture, out, cache=cache, resume_from=resume)
    report = json.loads((out / "report.json").read_text())["refine"]
    stages = report["stages"]
    timings = report["timings"]
    coarse_s = sum(timings[f"stage_{i + 1}"] for i in range(coarse))
    metrics = evaluate_paths(out, capture / "gt").to_dict()
    return {
        "coarse": coarse,
        "mvir": mvir,
        "vertices": report["vertices"],
        "coarse_vertices": report["coarse_vertices"],
        "refine_s": timings["total"],
        "coarse_stages_s": coarse_s,
        "evaluations": sum(st["evaluations"] for st in stages),
        **{k: metrics[k] for k in ("accuracy", "completeness", "normal_error", "normal_error_median")},
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--values", type=int, nargs="+", default=[0, 1, 2], help="refine.stages.coarse per run")
    ap.add_argument("--shape", default="blob")
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--size", default="408x340")
    ap.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--work", type=Path, default=Path("/tmp/coarse_to_fine"))
    args = ap.parse_args()
    capture = args.work / "capture"
    if not (capture / "capture.json").exists():
        subprocess.run([PMVIR, "synth", "--shape", args.shape, "--views", str(args.views), "--size", args.size,
                        "--material", "plastic", "--out", str(capture), "--force", "--quiet"], check=True)
    runs = [_measure(capture, args.work, args.overrides, c) for c in args.values]
    runs.append(_measure(capture, args.work, args.overrides, 0, mvir=True))
    peer, mvir = runs[0], runs[-1]
    columns = ["stages.coarse", "vertices (coarse)", "refine s", "of it coarse stages s", "evaluations",
               "time / first", "accuracy x1e-2", "accuracy / first", "completeness x1e-2",
               "normal error median deg", "median / MVIR's"]
    rows = [
        [f"{r['coarse']}, MVIR ({MVIR})" if r["mvir"] else r["coarse"],
         f"{r['vertices']:,}" + (f" ({r['coarse_vertices']:,})" if r["coarse_vertices"] else ""),
         round(r["refine_s"], 1), round(r["coarse_stages_s"], 1), r["evaluations"],
         round(r["refine_s"] / peer["refine_s"], 2), round(100 * r["accuracy"], 4),
         round(r["accuracy"] / peer["accuracy"], 2), round(100 * r["completeness"], 4),
         round(r["normal_error_median"], 2), round(r["normal_error_median"] / mvir["normal_error_median"], 2)]
        for r in runs
    ]
    title = f"{args.shape}, plastic, {args.views} views of {args.size}" + (
        f" ({', '.join(args.overrides)})" if args.overrides else "")
    tab = table(title, columns, rows, note="the first row is the peer, MVIR (the last row) that of the "
                "normal error; distances in GT bounding-box diagonals")
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join(str(c) for c in row))
    write_results("coarse_to_fine", title="Coarse to fine: the first stages on a coarser surface",
                  tables=[tab], peer=f"refine.stages.coarse={peer['coarse']} (time, accuracy); MVIR (normal error)", data={"runs": runs})


if __name__ == "__main__":
    main()
