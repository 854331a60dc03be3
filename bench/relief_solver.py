"""The refinement on fine relief: the fairing, the preconditioner's strength and the iteration budget.

A built-in relief capture (``pmvir synth``: rock, plastic, 24 views of 408x340, seed 5 by default) goes
through the decode and geometry stages once (cached in ``--work``); the refinement then runs once per
variant (``--variant NAME KEY=VALUE ...``, on top of the common ``--set KEY=VALUE`` options) from that
same initial surface. Prints per variant the refinement's seconds and cost evaluations and the result's
accuracy, its gain over the initial surface, and the normal error (median and mean) against the ground
truth, with the median's ratio to MVIR's (the variant named ``mvir``); writes bench/results/relief_solver.json.

Run: .venv/bin/python bench/relief_solver.py [--shape rock] [--views 24] [--size 408x340] [--seed 5]
     [--set KEY=VALUE ...] [--variant NAME KEY=VALUE ...] [--work DIR] [--capture DIR] [--results NAME]
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
from pathlib import Path

from _results import capture_description, table, write_results

from pmvir.commands.options import parse_overrides
from pmvir.config import PipelineConfig, merge_options
from pmvir.evaluate import evaluate_paths
from pmvir.pipeline import run

PMVIR = str(Path(sys.executable).with_name("pmvir"))
#: The variants measured without --variant: the defaults, no fairing, fairing not scaled to the
#: mesh's face size, two weaker preconditioners,
#: a larger iteration budget, and MVIR (the peer of the normal error).
DEFAULT_VARIANTS = [
    ["full"],
    ["no-fairing", "refine.surface.fair_iterations=0"],
    ["fairing-in-edges", "refine.surface.fair_reference_area_px=0"],
    ["lambda-5", "refine.solver.precondition_lambda=5"],
    ["lambda-2", "refine.solver.precondition_lambda=2"],
    ["iterations-40", "refine.solver.max_iterations=40"],
    ["mvir", "refine.pol.enabled=false"],
]
METRICS = ("accuracy", "completeness", "normal_error", "normal_error_median")


def _measure(capture: Path, work: Path, common: list[str], name: str, overrides: list[str]) -> dict:
    out = work / f"result-{name}"
    shutil.rmtree(out, ignore_errors=True)
    cache = work / "cache"
    resume = "refine" if (cache / "geometry.pkl").exists() else None
    config = PipelineConfig.model_validate(merge_options(parse_overrides(common), parse_overrides(overrides)))
    run(config, capture, out, cache=cache, resume_from=resume)
    report = json.loads((out / "report.json").read_text())["refine"]
    metrics = evaluate_paths(out, capture / "gt").to_dict()
    initial = evaluate_paths(out / "initial.ply", capture / "gt").to_dict()
    return {
        "variant": name,
        "overrides": overrides,
        "vertices": report["vertices"],
        "refine_s": report["timings"]["total"],
        "evaluations": sum(st["evaluations"] for st in report["stages"]),
        **{k: metrics[k] for k in METRICS},
        "initial": {k: initial[k] for k in METRICS},
    }


def _forget_other_capture(args: argparse.Namespace) -> None:
    """Clear ``--work`` of a rendered capture and cached stages that belong to another capture: the
    stage cache's key covers the options, not the capture they were run on."""
    identity = (f"capture {args.capture.resolve()}" if args.capture is not None
                else f"builtin {args.shape} plastic {args.views} views {args.size} seed {args.seed}")
    marker = args.work / "capture.id"
    if marker.exists() and marker.read_text() == identity:
        return
    shutil.rmtree(args.work / "cache", ignore_errors=True)
    shutil.rmtree(args.work / "capture", ignore_errors=True)
    args.work.mkdir(parents=True, exist_ok=True)
    marker.write_text(identity)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shape", default="rock")
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--size", default="408x340")
    ap.add_argument("--seed", type=int, default=5)
    ap.add_argument("--set", dest="common", action="append", default=[], metavar="KEY=VALUE")
    ap.add_argument("--variant", dest="variants", action="append", nargs="+", metavar="NAME [KEY=VALUE ...]")
    ap.add_argument("--work", type=Path, default=Path("/tmp/relief_solver"))
    ap.add_argument("--capture", type=Path, help="an existing capture with gt/ (e.g. path-traced) instead of the "
                    "built-in one rendered into --work")
    ap.add_argument("--results", default="relief_solver", help="name of the results JSON under bench/results")
    args = ap.parse_args()
    capture = args.capture or args.work / "capture"
    _forget_other_capture(args)
    if args.capture is None and not (capture / "capture.json").exists():
        subprocess.run([PMVIR, "synth", "--shape", args.shape, "--views", str(args.views), "--size", args.size,
                        "--material", "plastic", "--seed", str(args.seed), "--out", str(capture), "--force",
                        "--quiet"], check=True)
    runs = [_measure(capture, args.work, args.common, v[0], v[1:]) for v in (args.variants or DEFAULT_VARIANTS)]
    write_table(runs, capture_description(capture), args.common, args.results)


def write_table(runs: list[dict], capture: str, common: list[str], results: str, extra_note: str = "") -> None:
    """Print the variants' table and write bench/results/<results>.json (``capture``: its description)."""
    mvir = next((r for r in runs if r["variant"] == "mvir"), None)
    initial = runs[0]["initial"]
    columns = ["variant", "refine s", "evaluations", "accuracy x1e-2", "accuracy gain over initial",
               "normal error median deg", "normal error mean deg", "median / MVIR's"]
    rows = [["initial surface", None, None, round(100 * initial["accuracy"], 4), None,
             round(initial["normal_error_median"], 2), round(initial["normal_error"], 2), None]]
    for r in runs:
        rows.append([
            r["variant"] + (f" ({', '.join(r['overrides'])})" if r["overrides"] else ""),
            round(r["refine_s"], 1), r["evaluations"], round(100 * r["accuracy"], 4),
            f"{100 * (1 - r['accuracy'] / initial['accuracy']):.1f} %",
            round(r["normal_error_median"], 2), round(r["normal_error"], 2),
            None if mvir is None else round(r["normal_error_median"] / mvir["normal_error_median"], 2),
        ])
    note = (f"Capture: {capture}"
            + (f"; common options {', '.join(common)}" if common else "")
            + ". Every variant starts from the same initial surface; distances in GT bounding-box diagonals."
            + extra_note)
    tab = table("Refinement variants on fine relief", columns, rows, note=note)
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join(str(c) for c in row))
    write_results(results, title="The refinement on fine relief", tables=[tab],
                  peer="MVIR (refine.pol.enabled=false)" if mvir is not None else f"the variant {runs[0]['variant']}",
                  data={"runs": runs})


if __name__ == "__main__":
    main()
