"""The object found without masks: table and turntable scenes, with and without masks, both renderers.

Usage: .venv/bin/python bench/nomask.py [--shapes blob,knot] [--views 24] [--size 320x256]
       [--renderers builtin,mitsuba] [--scenes table,turntable] [--spp 32] [--stop-after geometry]
       [--work /tmp/nomask] [--append] [--reuse] [--masks true,none] [--set KEY=VALUE ...] [--results NAME]

Per shape, scene and renderer one capture is rendered with ``pmvir synth --shape SHAPE --scene S
--no-masks`` (``--reuse``: one already in --work with the same options is kept); a copy names its
true masks (gt/masks/) in capture.json. Both are reconstructed with ``pmvir reconstruct``
(by default the geometric stage only) and the initial (or refined) mesh compared with the object
alone: accuracy and completeness (pmvir.evaluate, GT diagonals), the median normal error (the
angle between each vertex's normal and the true surface's, degrees), the largest vertex distance and
the share of vertices farther than 2 % of the diagonal, the largest distance of the vertices within
2 % of the diagonal above the table (table left in the mesh, or a web across the gaps at the
object's base), the masks' IoU against the true ones (no-mask runs) and the time. Prints a table
and writes bench/results/nomask.json (the initial surface) or bench/results/nomask_refine.json
(``--stop-after refine``: the refined mesh);
``--results NAME``: bench/results/NAME.json. ``--set KEY=VALUE`` passes an option to every
reconstruction (e.g. ``geometry.isolate.see_past=false``); the no-mask rows then read
``none, see_past=false`` and stand beside those with the defaults in one table (``--append``).
"""

from __future__ import annotations

import argparse
import itertools
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _results import RESULTS, table, write_results

from pmvir.evaluate import SurfaceQuery, bbox_diagonal, evaluate
from pmvir.io.ply import Mesh, read_mesh
from pmvir.synth.options import SynthOptions

PMVIR = str(Path(sys.executable).with_name("pmvir"))


def _with_true_masks(capture: Path, out: Path) -> Path:
    """A copy of a no-mask capture whose capture.json names its true masks (gt/masks/)."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(capture, out)
    shutil.copytree(out / "gt" / "masks", out / "masks")
    manifest = json.loads((out / "capture.json").read_text())
    for frame in manifest["frames"]:
        frame["mask"] = "masks/" + Path(frame["file"]).stem + ".png"
    (out / "capture.json").write_text(json.dumps(manifest, indent=1))
    return out


def _mask_iou(result: Path, capture: Path) -> float | None:
    found = sorted((result / "masks").glob("*.png")) if (result / "masks").is_dir() else []
    if not found:
        return None
    ious = []
    for path in found:
        m = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE) > 0
        t = cv2.imread(str(capture / "gt" / "masks" / path.name), cv2.IMREAD_GRAYSCALE) > 0
        if m.shape != t.shape:
            m = cv2.resize(m.astype(np.uint8), t.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
        ious.append((m & t).sum() / max((m | t).sum(), 1))
    return float(np.mean(ious))


def vertex_distances(vertices: np.ndarray, gt: Mesh) -> dict[str, float]:
    """The largest vertex distance to the object, the share of vertices beyond 2 % and the largest
    distance of the vertices within 2 % of the diagonal above the table, in GT diagonals."""
    diag = bbox_diagonal(gt.vertices)
    closest, _, _ = SurfaceQuery(gt.vertices, gt.faces).closest(vertices)
    far = np.linalg.norm(vertices - closest, axis=1) / diag
    near_table = vertices[:, 2] < gt.vertices[:, 2].min() + 0.02 * diag  # the support touches the lowest point
    return {"max_vertex_distance": float(far.max()), "share_beyond_2pct": float((far > 0.02).mean()),
            "max_distance_near_table": float(far[near_table].max(initial=0.0))}


def _measure(capture: Path, result: Path, stop_after: str, settings: list[str]) -> dict:
    t0 = time.perf_counter()
    proc = subprocess.run(
        [PMVIR, "reconstruct", str(capture), "--out", str(result), "--stop-after", stop_after, "--quiet",
         *(a for kv in settings for a in ("--set", kv))],
        capture_output=True, text=True, check=False,
    )
    seconds = time.perf_counter() - t0
    if proc.returncode != 0:
        return {"error": proc.stderr.strip().splitlines()[-1:] or ["failed"], "seconds": seconds}
    mesh = read_mesh(result / ("mesh.ply" if stop_after == "refine" else "initial.ply"))
    gt = read_mesh(capture / "gt" / "mesh.ply")
    r = evaluate(Mesh(mesh.vertices, mesh.faces), gt, n_samples=200_000)
    report = json.loads((result / "report.json").read_text())
    return {
        "accuracy": r.accuracy,
        "completeness": r.completeness,
        "normal_error_median": r.normal_error_median,
        **vertex_distances(mesh.vertices, gt),
        "vertices": len(mesh.vertices),
        "mask_iou": _mask_iou(result, capture),
        "isolation": report.get("geometry", {}).get("isolation"),
        "seconds": seconds,
    }


#: Options of ``pmvir synth`` this benchmark leaves at their defaults: a capture rendered with others
#: (another lighting or seed) is not reused.
_DEFAULTED = ("material", "lighting", "texture", "seed", "noise", "roughness")


def _rendered_as(capture: Path, shape: str, scene: str, renderer: str, args: argparse.Namespace) -> bool:
    """Whether ``capture`` holds a rendering with these options (its gt/synth.json)."""
    path = capture / "gt" / "synth.json"
    if not (capture / "capture.json").exists() or not path.exists():
        return False
    made = json.loads(path.read_text())
    o = made.get("options", {})
    width, height = (int(x) for x in args.size.split("x"))
    defaults = all(o.get(k) == SynthOptions.model_fields[k].default for k in _DEFAULTED)
    return (made.get("source", {}).get("shape") == shape and o.get("scene") == scene and o.get("renderer") == renderer
            and o.get("views") == args.views and o.get("size") == [width, height] and o.get("spp") == args.spp
            and defaults)


def _key(row: dict) -> tuple:
    """A row's identity in the table: shape, scene, views x size, renderer and masks."""
    return row.get("shape", "blob"), row["scene"], row.get("capture"), row["renderer"], row["masks"]


def _label(masks: str, settings: list[str]) -> str:
    """The masks column: ``none`` followed by the options set (their last key), so that runs with and
    without them stand in one table (``none, see_past=false``); ``true`` as it is (isolation does not run)."""
    if masks != "none" or not settings:
        return masks
    return ", ".join([masks, *(kv.split("=", 1)[0].rsplit(".", 1)[-1] + "=" + kv.split("=", 1)[1] for kv in settings)])


def _name(args: argparse.Namespace) -> str:
    """The result's name: the initial surface's runs and the refined mesh's are kept apart (``--results``: this)."""
    return args.results or ("nomask" if args.stop_after == "geometry" else "nomask_refine")


def _write(runs: list[dict], args: argparse.Namespace) -> Path:
    """Print the table of the runs so far and write bench/results/<_name>.json."""
    columns = ["shape", "scene", "views x size", "renderer", "masks", "accuracy (1e-2)", "completeness (1e-2)",
               "normal error median deg", "max dist (diag)", "> 2 % diag", "max dist near table", "mask IoU",
               "time (s)"]
    rows = []
    for r in runs:
        if "error" in r:
            rows.append([r.get("shape", "blob"), r["scene"], r.get("capture"), r["renderer"], r["masks"], *[None] * 7,
                         round(r["seconds"], 1)])
            continue
        rows.append([
            r.get("shape", "blob"), r["scene"], r.get("capture"), r["renderer"], r["masks"], round(100 * r["accuracy"], 3), round(100 * r["completeness"], 3),
            None if r.get("normal_error_median") is None else round(r["normal_error_median"], 2),
            round(r["max_vertex_distance"], 4), f"{100 * r['share_beyond_2pct']:.2f} %",
            round(r["max_distance_near_table"], 4),
            None if r["mask_iou"] is None else round(r["mask_iou"], 3), round(r["seconds"], 1),
        ])
    arguments = list(dict.fromkeys(r.get("arguments", "") for r in runs))
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join("-" if v is None else str(v) for v in row))
    out = write_results(
        _name(args),
        title=f"Object isolation without masks (stop after {args.stop_after})",
        tables=[table("With the true masks and without masks", columns, rows,
                      note="masks 'none': pmvir finds the object itself (geometry.isolate); distances in "
                      "GT bounding-box diagonals; 'near table': vertices within 2 % of the diagonal above "
                      "the table; the rows come from bench/nomask.py with "
                      + " and with ".join(f"'{a}'" for a in arguments))],
        data={"options": vars(args) | {"work": str(args.work)}, "runs": runs},
    )
    print(f"wrote {out}")
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--shapes", default="blob", help="built-in shapes, comma-separated (pmvir synth --shape)")
    ap.add_argument("--views", type=int, default=24)
    ap.add_argument("--size", default="320x256")
    ap.add_argument("--renderers", default="builtin,mitsuba")
    ap.add_argument("--scenes", default="table,turntable")
    ap.add_argument("--spp", type=int, default=32)
    ap.add_argument("--stop-after", choices=["geometry", "refine"], default="geometry")
    ap.add_argument("--work", type=Path, default=Path("/tmp/nomask"))
    ap.add_argument("--append", action="store_true",
                    help="keep the runs already in the result file (a new run replaces one of the same row key)")
    ap.add_argument("--masks", default="true,none",
                    help="which runs per capture, comma-separated: true (its true masks), none (no masks); with "
                    "--append the stored rows of the other stay")
    ap.add_argument("--reuse", action="store_true",
                    help="keep a capture already rendered in --work with the same options instead of rendering it again")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="an option for every reconstruction (pmvir reconstruct --set), repeatable")
    ap.add_argument("--results", default="", help="write bench/results/NAME.json instead of nomask(_refine).json")
    args = ap.parse_args()
    if not args.masks or not set(args.masks.split(",")) <= {"true", "none"}:
        ap.error(f"--masks {args.masks!r}: expected true, none or true,none")

    earlier = RESULTS / f"{_name(args)}.json"
    runs = json.loads(earlier.read_text())["runs"] if args.append and earlier.exists() else []
    for shape, scene, renderer in itertools.product(
        args.shapes.split(","), args.scenes.split(","), args.renderers.split(",")
    ):
        cap = args.work / shape / f"{scene}-{renderer}"
        synth = [PMVIR, "synth", "--shape", shape, "--scene", scene, "--no-masks", "--views",
                 str(args.views), "--size", args.size, "--renderer", renderer, "--spp", str(args.spp),
                 "--out", str(cap), "--force", "--quiet"]
        t0 = time.perf_counter()
        if not (args.reuse and _rendered_as(cap, shape, scene, renderer, args)):
            subprocess.run(synth, check=True)
        synth_s = time.perf_counter() - t0
        masked = _with_true_masks(cap, args.work / shape / f"{scene}-{renderer}-masks")
        for masks, capture in (("true", masked), ("none", cap)):
            if masks not in args.masks.split(","):
                continue
            row = {"shape": shape, "scene": scene, "capture": f"{args.views} x {args.size}", "renderer": renderer,
                   "masks": _label(masks, args.set), "synth_seconds": synth_s, "arguments": " ".join(sys.argv[1:])}
            row |= _measure(capture, args.work / shape / f"result-{scene}-{renderer}-{masks}", args.stop_after, args.set)
            same = [k for k, r in enumerate(runs) if _key(r) == _key(row)]
            if same:  # in the earlier row's place, so that the table keeps its order
                runs = [r for k, r in enumerate(runs) if k not in same[1:]]
                runs[same[0]] = row
            else:
                runs.append(row)
            print(json.dumps(row), flush=True)
            _write(runs, args)  # after every run: an interrupted benchmark keeps what it measured

    return 0


if __name__ == "__main__":
    raise SystemExit(main())
