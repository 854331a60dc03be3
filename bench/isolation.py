"""Time of the object's isolation without masks, against the same step at git revisions, on the same inputs.

Usage: .venv/bin/python bench/isolation.py --against REV [REV ...] [--captures mug/table,knot/turntable]
       [--views 36] [--size 612x512] [--repeat 2] [--work /tmp/isolation]

Per built-in capture (``pmvir synth --shape SHAPE --scene SCENE --no-masks``, rendered into --work
unless one with the same options is there) the geometric stage runs up to the isolation once and
its inputs are kept: the dense points, cameras, previews and depth maps. Then this tree's
``isolate_object`` and that of the package ``pmvir/geometry/silhouette/`` at each REV (run with this
tree's other modules) each run ``--repeat`` times, alternating, on those inputs (OpenCV's random
numbers seeded alike). Prints a table and writes bench/results/isolation.json: the fastest run of
each, this tree's time over each revision's, and the mask pixels on which each revision's masks
differ from this tree's.
"""

from __future__ import annotations

import argparse
import importlib
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from types import ModuleType
from typing import Any

import cv2

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _results import ROOT, print_table, table, write_results

import pmvir.geometry.stage as stage
from pmvir.cli import main as pmvir_main
from pmvir.geometry.silhouette import isolate

PMVIR = str(Path(sys.executable).with_name("pmvir"))
PACKAGE = "pmvir/geometry/silhouette"


def _peer(revision: str, folder: Path, name: str) -> ModuleType:
    """The isolation as it is at ``revision``: the silhouette package's modules of that revision, imported
    as the package ``name`` (their imports of each other renamed to it); its ``isolate`` module."""
    listing = subprocess.run(["git", "ls-tree", "--name-only", f"{revision}:{PACKAGE}"], cwd=ROOT,
                             capture_output=True, text=True, check=False)
    if listing.returncode != 0:
        raise SystemExit(f"git ls-tree {revision}:{PACKAGE}: {listing.stderr.strip()}")
    package = folder / name
    package.mkdir()
    for file in listing.stdout.split():
        if not file.endswith(".py"):
            continue
        source = subprocess.run(["git", "show", f"{revision}:{PACKAGE}/{file}"], cwd=ROOT, capture_output=True,
                                text=True, check=True).stdout
        (package / file).write_text(source.replace("pmvir.geometry.silhouette.", f"{name}."))
    if str(folder) not in sys.path:
        sys.path.insert(0, str(folder))
    return importlib.import_module(f"{name}.isolate")


def _capture(work: Path, shape: str, scene: str, views: int, size: str) -> Path:
    cap = work / shape / scene
    wanted = {"shape": shape, "scene": scene, "views": views, "size": size}
    stamp = cap / "bench-isolation.json"
    if not (stamp.exists() and json.loads(stamp.read_text()) == wanted):
        subprocess.run([PMVIR, "synth", "--shape", shape, "--scene", scene, "--no-masks", "--views", str(views),
                        "--size", size, "--out", str(cap), "--force", "--quiet"], check=True)
        stamp.write_text(json.dumps(wanted))
    return cap


def _inputs(capture: Path, out: Path) -> tuple[tuple[Any, ...], dict[str, Any]]:
    """The isolation's arguments on ``capture``: the geometric stage runs up to the isolation and stops."""
    taken: dict[str, Any] = {}

    def take(*args: Any, **kwargs: Any) -> None:
        taken.update(args=args, kwargs=kwargs)
        raise SystemExit(0)

    original = stage.isolate_object
    stage.isolate_object = take  # type: ignore[assignment]
    try:
        pmvir_main(["reconstruct", str(capture), "--out", str(out), "--stop-after", "geometry", "--quiet"])
    except SystemExit:
        pass
    finally:
        stage.isolate_object = original  # type: ignore[assignment]
    if not taken:
        raise SystemExit(f"{capture}: the geometric stage did not reach the isolation (are masks given?)")
    return taken["args"], taken["kwargs"]


def _timed(module: ModuleType, args: tuple[Any, ...], kwargs: dict[str, Any]) -> tuple[float, list[Any]]:
    cv2.setRNGSeed(0)  # a fresh process's start, which the isolation sets itself as well
    t0 = time.perf_counter()
    masks = module.isolate_object(*args, **kwargs).masks
    return time.perf_counter() - t0, masks


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--against", required=True, nargs="+", help="the git revisions whose isolation is the peer")
    ap.add_argument("--captures", default="mug/table,knot/turntable", help="SHAPE/SCENE, comma-separated")
    ap.add_argument("--views", type=int, default=36)
    ap.add_argument("--size", default="612x512")
    ap.add_argument("--repeat", type=int, default=2, help="runs of each version per capture (the fastest counts)")
    ap.add_argument("--work", type=Path, default=Path("/tmp/isolation"))
    args = ap.parse_args()
    rows, runs = [], []
    with tempfile.TemporaryDirectory() as tmp:
        peers = {rev: _peer(rev, Path(tmp), f"isolate_at_{k}") for k, rev in enumerate(args.against)}
        for item in args.captures.split(","):
            shape, scene = item.split("/")
            cap = _capture(args.work, shape, scene, args.views, args.size)
            call = _inputs(cap, Path(tmp) / f"result-{shape}-{scene}")
            versions = {"this": isolate} | peers
            seconds: dict[str, list[float]] = {name: [] for name in versions}
            masks: dict[str, list[Any]] = {}
            for _ in range(args.repeat):
                for name, module in versions.items():
                    s, masks[name] = _timed(module, *call)
                    seconds[name].append(s)
            total = sum(int(m.sum()) for m in masks["this"] if m is not None)
            differ = {rev: sum(int((a != b).sum()) for a, b in zip(masks["this"], masks[rev], strict=True)
                               if a is not None) for rev in peers}
            run = {"shape": shape, "scene": scene, "capture": f"{args.views} x {args.size}", "renderer": "builtin",
                   "points": len(call[0][0]), "seconds": seconds, "mask_pixels": total,
                   "mask_pixels_differing": differ}
            runs.append(run)
            this = min(seconds["this"])
            row: list[Any] = [f"{shape}, {scene}", run["capture"], run["points"], round(this, 1)]
            for rev in peers:
                other = min(seconds[rev])
                row += [round(other, 1), round(this / other, 2), f"{differ[rev]} of {total}"]
            rows.append(row)
            print(json.dumps(run), flush=True)
    columns = ["capture", "views x size", "dense points", "isolation s"]
    for rev in args.against:
        columns += [f"at {rev} s", f"ratio to {rev}", f"mask pixels differing from {rev}"]
    note = (f"The fastest of {args.repeat} runs of each, alternating, in one process on the same inputs "
            f"(built-in renderer, no masks); the peers are the isolation ({PACKAGE}/) at {', '.join(args.against)}.")
    tab = table("Isolation without masks: time against earlier revisions", columns, rows, note=note)
    print_table(tab)
    write_results("isolation", title="Time of the isolation without masks", tables=[tab],
                  peer=f"the isolation at {', '.join(args.against)}", data={"runs": runs, "against": args.against})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
