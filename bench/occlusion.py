"""Benchmark of the fusion's occlusion test (``geometry.mvs.max_occluding``): the initial surface with and without it.

The peer is the same capture fused without the test (``--set geometry.mvs.max_occluding=null``),
in the same run. Captures (all with known poses and the true masks, plastic; 36 views unless said):

* the shapes of bench/geometry.py, 612x512, built-in renderer: the Stanford bunny, dragon and
  armadillo (skipped where ../shared is absent), the knot, gear and mug;
* ``bunny-sparse``, ``dragon-sparse``, ``armadillo-sparse``: the Stanford models on the paper's
  sparse rig (12 views of 304x256, where one confirming view fuses a depth);
* ``blob-pathtraced``: the blob rendered by Mitsuba (32 spp), 612x512;
* ``table-fullsize``: the blob on a textured table, 2448x2048 (the capture of bench/as_taken.py),
  with its true masks: the capture whose glossy top, fused without the test, gave the initial
  surface a dent 7 % of the diagonal deep.

For each: the initial surface's accuracy, completeness and median normal error against gt/mesh.ply
(spec section 5), its largest vertex distance and share beyond 2 % of the diagonal, the fused
points and the fusion's time. Prints a table and writes bench/results/occlusion.json.

Run: .venv/bin/python bench/occlusion.py [--captures knot table-fullsize] [--work DIR] [--append]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from _results import RESULTS, table, write_results
from as_taken import _capture as table_capture
from geometry import MODELS, SHARED, make_capture
from nomask import _with_true_masks, vertex_distances

from pmvir.evaluate import evaluate
from pmvir.io.ply import Mesh, read_mesh
from pmvir.synth.generate import synthesize

PMVIR = str(Path(sys.executable).with_name("pmvir"))
PATHTRACED = "blob-pathtraced"
FULLSIZE = "table-fullsize"
SPARSE = {f"{m}-sparse": m for m in MODELS}
CAPTURES = [*MODELS, "knot", "gear", "mug", *SPARSE, PATHTRACED, FULLSIZE]
VARIANTS = {"without": ["--set", "geometry.mvs.max_occluding=null"], "with": []}


def _prepare(name: str, work: Path) -> tuple[Path, str, str]:
    """The capture (cached in ``work``), its views x size and its renderer."""
    if name == FULLSIZE:
        return _with_true_masks(table_capture("2448x2048", 36, work), work / "table-fullsize-masks"), \
            "36 x 2448x2048", "builtin"
    if name in SPARSE:
        out = work / name
        if not (out / "capture.json").is_file():
            synthesize(out, views=12, size=(304, 256), material="plastic", seed=0, overwrite=True,
                       mesh=SHARED / "data" / "models" / MODELS[SPARSE[name]], mesh_up="y")
        return out, "12 x 304x256", "builtin"
    if name == PATHTRACED:
        out = work / PATHTRACED
        if not (out / "capture.json").is_file():
            subprocess.run([PMVIR, "synth", "--shape", "blob", "--renderer", "mitsuba", "--spp", "32", "--views", "36",
                            "--size", "612x512", "--seed", "0", "--out", str(out), "--force", "--quiet"], check=True)
        return out, "36 x 612x512", "mitsuba"
    return make_capture(name, work), "36 x 612x512", "builtin"


def _measure(capture: Path, out: Path, extra: list[str]) -> dict:
    """The geometric stage of ``capture`` into ``out`` and the initial surface's measures."""
    t0 = time.perf_counter()
    subprocess.run([PMVIR, "reconstruct", str(capture), "--out", str(out), "--stop-after", "geometry", "--quiet",
                    *extra], check=True)
    seconds = time.perf_counter() - t0
    gt = read_mesh(capture / "gt" / "mesh.ply")
    mesh = read_mesh(out / "initial.ply")
    r = evaluate(Mesh(mesh.vertices, mesh.faces), gt, n_samples=300_000)
    geometry = json.loads((out / "report.json").read_text())["geometry"]
    return {
        "accuracy": r.accuracy,
        "completeness": r.completeness,
        "normal_error_median": r.normal_error_median,
        **vertex_distances(mesh.vertices, gt),
        "vertices": len(mesh.vertices),
        "fused_points": geometry["dense"]["points"],
        "fusion_seconds": geometry["timings"]["fusion"],
        "seconds": seconds,
    }


def _pair(a: float, b: float, digits: int) -> str:
    return f"{a:.{digits}f} / {b:.{digits}f}"


def _write(runs: list[dict]) -> Path:
    columns = ["capture", "views x size", "renderer", "accuracy without / with (1e-2)", "ratio",
               "completeness without / with (1e-2)", "ratio", "normal median without / with (deg)",
               "max dist without / with (diag)", "> 2 % diag without / with", "fused points without / with",
               "fusion s without / with"]
    rows = []
    for run in runs:
        a, b = run["without"], run["with"]
        rows.append([
            run["capture"], run["views_size"], run["renderer"],
            _pair(100 * a["accuracy"], 100 * b["accuracy"], 4), round(b["accuracy"] / a["accuracy"], 3),
            _pair(100 * a["completeness"], 100 * b["completeness"], 4),
            round(b["completeness"] / a["completeness"], 3),
            _pair(a["normal_error_median"], b["normal_error_median"], 2),
            _pair(a["max_vertex_distance"], b["max_vertex_distance"], 4),
            f"{100 * a['share_beyond_2pct']:.2f} % / {100 * b['share_beyond_2pct']:.2f} %",
            f"{a['fused_points']} / {b['fused_points']}", _pair(a["fusion_seconds"], b["fusion_seconds"], 1),
        ])
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join(str(v) for v in row))
    out = write_results(
        "occlusion",
        title="Fusion's occlusion test: the initial surface with and without it",
        peer="the same capture fused without the occlusion test (--set geometry.mvs.max_occluding=null), same run",
        tables=[table("Initial surface (known poses, true masks) without and with the occlusion test", columns, rows,
                      note="ratio: with / without (below 1: the test helps); distances in GT bounding-box "
                      "diagonals; '> 2 % diag': share of the initial surface's vertices farther than 2 % of "
                      "the diagonal from the object")],
        data={"runs": runs},
    )
    print(f"wrote {out}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--captures", nargs="+", default=CAPTURES, choices=CAPTURES)
    ap.add_argument("--work", type=Path, default=Path("/tmp/pmvir-occlusion"), help="captures and results")
    ap.add_argument("--append", action="store_true",
                    help="keep the other captures' runs already in bench/results/occlusion.json")
    args = ap.parse_args()
    shared = (SHARED / "data" / "models").is_dir()
    names = [n for n in args.captures if shared or (n not in MODELS and n not in SPARSE)]
    args.work.mkdir(parents=True, exist_ok=True)
    earlier = RESULTS / "occlusion.json"
    runs = json.loads(earlier.read_text())["runs"] if args.append and earlier.exists() else []
    runs = [r for r in runs if r["capture"] not in names]
    for name in names:
        capture, views_size, renderer = _prepare(name, args.work)
        run = {"capture": name, "views_size": views_size, "renderer": renderer}
        for variant, extra in VARIANTS.items():
            run[variant] = _measure(capture, args.work / f"result-{name}-{variant}", extra)
        runs.append(run)
        runs.sort(key=lambda r: CAPTURES.index(r["capture"]))
        print(json.dumps(run), flush=True)
        _write(runs)  # after every capture: an interrupted benchmark keeps what it measured
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
