"""A capture as people take it: a folder of full-size frames, an object on a table, no manifest, masks or poses.

Per size (default 2448x2048) a capture of an object standing on a textured table is rendered
(``pmvir synth --scene table --no-masks``: ``--shape`` (blob) or a mesh file (``--mesh``, its up axis
``--mesh-up``, e.g. a Stanford model), plastic, environment light, ``--views`` views from above the
table, seed 0, by ``--renderer``: builtin, or mitsuba at ``--spp``) and its
frames alone are copied into a bare folder. That
folder is reconstructed with ``pmvir reconstruct FOLDER`` and the default options, under
``/usr/bin/time -v`` (the run's peak resident memory): pmvir infers the manifest, estimates the
intrinsics and poses by SfM and finds the object itself. With ``--reference`` the same frames
run again as the lab prepares them: the capture's manifest (true intrinsics and poses) and the
true masks; ``--reference-only`` makes that run alone (with ``--append`` the bare-frames runs in the
result file stay).

The meshes are compared with the object alone, after a similarity fitted from the estimated
camera centres to the true ones (``pmvir evaluate --align``): accuracy of the initial surface
and of the refined mesh, completeness, the median normal error, the largest vertex distance and
the share of vertices farther than 2 % of the diagonal, the largest distance of the vertices
within 2 % of the diagonal above the table (table left in the mesh, or a web across the gaps
at the object's base), and the masks' IoU against the true ones. Prints a table and writes
bench/results/as_taken.json (``--results NAME``: NAME.json; ``--append`` keeps its runs, a new one
replacing the run of the same object, input, size and views; a run with ``--set`` options names
them beside its input); ``--reuse`` measures again only the runs without a finished result in
``--work``.

    .venv/bin/python bench/as_taken.py [--sizes 2448x2048] [--views 36] [--shape blob | --mesh FILE [--mesh-up y]]
        [--renderer builtin]
        [--spp 32] [--reference | --reference-only] [--work DIR] [--reuse] [--set KEY=VALUE ...]
        [--results NAME] [--append]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _results import RESULTS, table, write_results
from fullsize import GIB, _peak_rss_bytes
from nomask import _mask_iou, _with_true_masks, vertex_distances

from pmvir.evaluate import (
    align_by_cameras,
    bbox_diagonal,
    estimated_camera_centres,
    evaluate,
    refine_alignment,
    true_camera_centres,
)
from pmvir.io.ply import Mesh, read_mesh

PMVIR = str(Path(sys.executable).with_name("pmvir"))
SEED = 0


def _capture(size: str, views: int, work: Path, args: argparse.Namespace) -> Path:
    """The rendered capture (cached in ``work``): frames, its manifest, gt/ with the true masks."""
    cap = work / f"cap_{_object(args)}_{args.renderer}_{size}_{views}v"
    source = ["--mesh", str(args.mesh), "--mesh-up", args.mesh_up] if args.mesh else ["--shape", args.shape]
    if not (cap / "capture.json").is_file():
        subprocess.run([PMVIR, "synth", *source, "--scene", "table", "--no-masks", "--views", str(views),
                        "--size", size, "--lighting", "envmap", "--renderer", args.renderer, "--spp", str(args.spp),
                        "--seed", str(SEED), "--out", str(cap), "--force", "--quiet"], check=True)
    return cap


def _inputs(args: argparse.Namespace) -> list[str]:
    """The runs made of each capture, in order: the bare frames (not with ``--reference-only``), and the
    manifest with the true masks (``--reference`` or ``--reference-only``, which exclude each other)."""
    if args.reference_only:
        return ["manifest and true masks"]
    return ["bare frames"] + (["manifest and true masks"] if args.reference else [])


def _object(args: argparse.Namespace) -> str:
    """The captured object's name: the mesh file's stem, or the built-in shape."""
    return args.mesh.stem if args.mesh else args.shape


def _bare_frames(capture: Path, out: Path) -> Path:
    """A folder holding the capture's frames and nothing else."""
    if out.exists():
        shutil.rmtree(out)
    out.mkdir(parents=True)
    for frame in json.loads((capture / "capture.json").read_text())["frames"]:
        shutil.copy2(capture / frame["file"], out / Path(frame["file"]).name)
    return out


def _reconstruct(capture: Path, out: Path, *, reuse: bool, settings: list[str]) -> str | None:
    """``pmvir reconstruct`` (with ``--set`` of each of ``settings``) under /usr/bin/time -v (its record kept
    in out/time-v.txt); the error, or None."""
    time_v = out / "time-v.txt"
    if reuse and (out / "mesh.ply").is_file() and time_v.is_file():
        return None
    if out.exists():
        shutil.rmtree(out)
    proc = subprocess.run(["/usr/bin/time", "-v", PMVIR, "reconstruct", str(capture), "--out", str(out), "--quiet",
                           *(a for kv in settings for a in ("--set", kv))],
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        return proc.stderr.strip().splitlines()[-1] if proc.stderr.strip() else f"exit status {proc.returncode}"
    time_v.write_text(proc.stderr)
    return None


def _measure(
    kind: str, size: str, views: int, capture: Path, source: Path, out: Path, reuse: bool, settings: list[str]
) -> dict:
    label = ", ".join([kind, *settings])  # a run with options other than the defaults names them
    row: dict = {"run": label, "size": size, "views": views, "source": str(source)}
    error = _reconstruct(source, out, reuse=reuse, settings=settings)
    if error is not None:
        return row | {"error": error}
    report = json.loads((out / "report.json").read_text())
    geometry = report.get("geometry", {})
    alignment = align_by_cameras(estimated_camera_centres(out / "poses" / "images.txt"),
                                 true_camera_centres(capture / "capture.json"))
    gt = read_mesh(capture / "gt" / "mesh.ply")
    for name in ("initial", "mesh"):
        mesh = read_mesh(out / f"{name}.ply")
        vertices = alignment.transform.apply(mesh.vertices)
        r = evaluate(Mesh(vertices, mesh.faces), gt, n_samples=300_000)
        prefix = "initial_" if name == "initial" else ""
        row |= {f"{prefix}accuracy": r.accuracy, f"{prefix}completeness": r.completeness,
                f"{prefix}normal_error_median": r.normal_error_median}
        row |= {f"{prefix}{k}": v for k, v in vertex_distances(vertices, gt).items()}
    # the refined mesh once more with the camera fit refined by ICP on the true surface: its own error
    # apart from the camera fit's (which a few views leave at a tenth of a percent of the diagonal)
    refined = refine_alignment(alignment, mesh.vertices, gt)
    r = evaluate(Mesh(mesh.vertices, mesh.faces), gt, n_samples=300_000, alignment=refined)
    row |= {"icp_accuracy": r.accuracy, "icp_completeness": r.completeness,
            "icp_shift": r.alignment_refine_shift}
    peak = _peak_rss_bytes((out / "time-v.txt").read_text())
    timings = report["timings_s"]
    geometry_timings = geometry.get("timings", {})
    return row | {
        "registered": geometry.get("poses", {}).get("registered_views"),
        "pose_mode": geometry.get("poses", {}).get("mode"),
        "alignment_rmse": alignment.rmse / bbox_diagonal(gt.vertices),
        "working_size": (report.get("resolution") or {}).get("refine"),
        "vertices": geometry.get("subdivision", {}).get("vertices"),
        "peak_rss_gib": round(peak / GIB, 2) if peak else None,
        "seconds": {k: round(float(timings[k]), 1) for k in ("decode", "geometry", "refine", "total") if k in timings},
        "geometry_seconds": {k: round(float(v), 1) for k, v in geometry_timings.items()},
        "mask_iou": _mask_iou(out, capture),
        "isolation": geometry.get("isolation"),
    }


COLUMNS = ["input", "frames", "views", "registered", "working size", "vertices", "peak RSS GiB", "poses s",
           "isolation s", "geometry s", "refine s", "total min", "initial accuracy x1e-2", "accuracy x1e-2",
           "completeness x1e-2", "accuracy after ICP x1e-2", "ICP move x1e-2", "camera fit RMSE x1e-2",
           "normal error median deg", "max dist (diag)", "> 2 % diag", "max dist near table", "mask IoU"]


def _stored_runs(document: dict) -> list[dict]:
    """A result file's runs, each naming its object: a run stored without one is of the file's own
    (its options' mesh or shape), so that ``--append`` replaces it like any other."""
    options = document.get("options", {})
    own = Path(options["mesh"]).stem if options.get("mesh") else options.get("shape", "blob")
    return [{"object": own} | run for run in document["runs"]]


def _key(run: dict) -> tuple:
    """What a new run replaces in the result file: the run of the same object, input, size and views."""
    return run["object"], run["run"], run["size"], run["views"]


def _row(r: dict, *, named: bool) -> list:
    """A run's row; ``named``: its input prefixed with the object (a table of several objects)."""
    head = [f"{r['object']}, {r['run']}" if named else r["run"], r["size"], r["views"]]
    if "error" in r:
        return head + [f"failed: {r['error']}"] + [None] * (len(COLUMNS) - 4)
    g, s = r["geometry_seconds"], r["seconds"]
    return head + [
        f"{r['registered']}/{r['views']}", r["working_size"], r["vertices"], r["peak_rss_gib"],
        g.get("poses"), None if r["isolation"] is None else g.get("isolation"), s.get("geometry"), s.get("refine"),
        round(s["total"] / 60, 1),
        round(100 * r["initial_accuracy"], 4), round(100 * r["accuracy"], 4), round(100 * r["completeness"], 3),
        round(100 * r["icp_accuracy"], 4), round(100 * r["icp_shift"], 3), round(100 * r["alignment_rmse"], 3),
        round(r["normal_error_median"], 2), round(r["max_vertex_distance"], 4),
        f"{100 * r['share_beyond_2pct']:.2f} %", round(r["max_distance_near_table"], 4),
        None if r["mask_iou"] is None else round(r["mask_iou"], 3),
    ]


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--sizes", nargs="+", default=["2448x2048"], help="frame sizes WxH (default 2448x2048)")
    p.add_argument("--views", type=int, default=36, help="views per capture (default 36)")
    p.add_argument("--shape", default="blob", help="built-in shape (pmvir synth --shape; default blob)")
    p.add_argument("--mesh", type=Path, help="a mesh file (PLY/OBJ) instead of a built-in shape")
    p.add_argument("--mesh-up", default="z", choices=["x", "y", "z"], help="the mesh's up axis (default z)")
    p.add_argument("--renderer", default="builtin", choices=["builtin", "mitsuba"], help="renderer (default builtin)")
    p.add_argument("--spp", type=int, default=32, help="mitsuba's samples per pixel (default 32)")
    p.add_argument("--results", default="as_taken", help="write bench/results/NAME.json (default as_taken)")
    p.add_argument("--append", action="store_true",
                   help="keep the runs already in the result file (a new run replaces one of the same object, input, size and "
                   "views)")
    which = p.add_mutually_exclusive_group()
    which.add_argument("--reference", action="store_true",
                       help="also reconstruct each capture with its manifest (true poses) and the true masks")
    which.add_argument("--reference-only", action="store_true",
                       help="reconstruct each capture only with its manifest and the true masks (with --append, "
                       "the bare-frames runs already in the result file stay)")
    p.add_argument("--work", type=Path, default=Path("/tmp/pmvir-as-taken"), help="captures and results")
    p.add_argument("--reuse", action="store_true", help="keep the finished results found in --work")
    p.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                   help="an option of every reconstruction, as `pmvir reconstruct --set` takes it")
    args = p.parse_args()
    args.work.mkdir(parents=True, exist_ok=True)
    earlier = RESULTS / f"{args.results}.json"
    runs = _stored_runs(json.loads(earlier.read_text())) if args.append and earlier.exists() else []
    for size in args.sizes:
        capture = _capture(size, args.views, args.work, args)
        tag = f"{_object(args)}_{args.renderer}_{size}_{args.views}v"
        sources = [(kind, _bare_frames(capture, args.work / f"frames_{tag}") if kind == "bare frames" else
                    _with_true_masks(capture, args.work / f"masked_{tag}")) for kind in _inputs(args)]
        for kind, source in sources:
            # runs with other options in folders of their own, so that --reuse never takes one for another
            options = "_" + hashlib.sha1(" ".join(args.set).encode()).hexdigest()[:8] if args.set else ""
            out = args.work / f"out_{'bare' if kind == 'bare frames' else 'reference'}_{tag}{options}"
            row = {"object": _object(args)} | _measure(kind, size, args.views, capture, source, out, args.reuse,
                                                       args.set)
            runs = [r for r in runs if _key(r) != _key(row)] + [row]
            print(json.dumps(runs[-1], default=str), flush=True)
    columns = COLUMNS
    objects = sorted({r["object"] for r in runs})
    rows = [_row(r, named=len(objects) > 1) for r in runs]
    print(" | ".join(columns))
    for row in rows:
        print(" | ".join("-" if v is None else str(v) for v in row))
    tab = table(
        "A folder of frames of an object on a table: no manifest, masks or poses", columns, rows,
        note=f"Capture: {' / '.join(objects) if len(objects) > 1 else _object(args)} standing on a textured table, {args.renderer} renderer"
        f"{f' ({args.spp} spp)' if args.renderer == 'mitsuba' else ''}, plastic, envmap lighting, seed 0, "
        "views from above the table. 'bare frames': the frames alone (manifest inferred, intrinsics and "
        "poses by SfM, the object found without masks); 'manifest and true masks': the same frames with "
        "the rendered manifest and the true masks. Meshes aligned to the ground truth by a similarity "
        "from the camera centres ('after ICP': that similarity refined by ICP on the true surface, pmvir evaluate "
        "--icp, and the largest move it made; 'camera fit RMSE': the camera centres' residual after that "
        "similarity, the poses' own error); distances in GT bounding-box diagonals; 'near table': vertices within "
        "2 % of the diagonal above the table; peak RSS of the whole run from /usr/bin/time -v.",
    )
    referenced = any(r["run"].startswith("manifest and true masks") for r in runs)
    peer = "the same frames with their manifest (true poses) and true masks" if referenced else None
    out = write_results(args.results, title="Captures as people take them", tables=[tab], peer=peer,
                        data={"options": vars(args) | {"work": str(args.work), "mesh": args.mesh and str(args.mesh)},
                              "runs": runs})
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
