"""Benchmark of the geometric stage (pmvir.geometry.stage) on the three shared models and the built-in shapes.

For each model of ../shared/data/models (bunny, dragon, armadillo; y up, normalized to a unit
bounding-box diagonal), or built-in shape (``--models blob knot gear mug``: genus 0 and genus 1
shapes with self-occlusion, a bore and a thin handle), a synthetic capture is made with pmvir synth
(plastic, 36 views of 612 x 512, seed 0; cached under $TMPDIR/pmvir-bench/geometry), decoded, and
the stage run twice:

* known poses (the capture's intrinsics and cam_from_world): per-step times, counts, and the
  accuracy / completeness of initial.ply (the subdivided initial surface) against gt/mesh.ply
  (spec section 5, 1,000,000 samples);
* SfM (poses and intrinsics removed from the manifest): registered views, pose error after a
  similarity alignment of the camera centres (centre error in GT diagonals, rotation error in
  degrees, focal length error), the same surface metrics after that alignment, and the times.

Prints a table and writes bench/results/geometry.json.
Run: .venv/bin/python bench/geometry.py [--models bunny dragon] [--no-sfm] [--work DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np
from _results import table, write_results

from pmvir.capture import open_capture
from pmvir.config import GeometryOptions
from pmvir.decode import decode_frame
from pmvir.errors import ReconstructionError
from pmvir.evaluate import evaluate
from pmvir.geometry.sfm.align import CameraAlignment, umeyama
from pmvir.geometry.stage import GeometryResult, geometry_report, run_geometry
from pmvir.io.ply import Mesh, read_mesh
from pmvir.synth.generate import synthesize
from pmvir.synth.shapes import SHAPES

ROOT = Path(__file__).resolve().parent
SHARED = Path(os.environ.get("PMVIR_SHARED", ROOT.parent / ".." / "shared"))
MODELS = {"bunny": "bunny.ply", "dragon": "dragon.ply", "armadillo": "armadillo.obj"}
STEPS = ("poses", "depth_maps", "fusion", "surface", "visibility", "subdivision", "total")


def make_capture(name: str, work: Path) -> Path:
    """The benchmark capture of a Stanford model or a built-in shape (cached under ``work``)."""
    out = work / name
    if (out / "capture.json").is_file():
        return out
    source = (
        {"mesh": SHARED / "data" / "models" / MODELS[name], "mesh_up": "y"} if name in MODELS else {"shape": name}
    )
    synthesize(out, views=36, size=(612, 512), material="plastic", seed=0, overwrite=True, **source)
    return out


def strip_poses(capture: Path, out: Path) -> Path:
    """A copy of the capture without cam_from_world and intrinsics (SfM estimates both)."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(capture, out, ignore=shutil.ignore_patterns("gt"))
    manifest = json.loads((capture / "capture.json").read_text())
    manifest.pop("intrinsics", None)
    for frame in manifest["frames"]:
        frame.pop("cam_from_world", None)
        frame.pop("intrinsics", None)
    (out / "capture.json").write_text(json.dumps(manifest, indent=1))
    return out


def decode(capture: Path) -> tuple[list, float]:
    t = time.perf_counter()
    with open_capture(capture) as cap:
        views = []
        for i in range(len(cap)):
            raw = cap.read_raw(i)
            views.append(decode_frame(raw.mosaic, cap.layout, saturated=raw.saturated, mask=cap.read_mask(i)))
    return views, time.perf_counter() - t


def pose_errors(result: GeometryResult, capture: Path) -> tuple[dict, CameraAlignment]:
    with open_capture(capture) as cap:
        true = [f.camera for f in cap.frames]
    idx = [i for i, c in enumerate(result.cameras) if c is not None]
    est = np.stack([result.cameras[i].center for i in idx])
    ref = np.stack([true[i].center for i in idx])
    sim = umeyama(est, ref)
    err = np.linalg.norm(sim.apply(est) - ref, axis=1)
    rot = []
    for i in idx:
        # world rotation of the estimated camera mapped into the true frame: R_est @ sim.R^T
        d = result.cameras[i].R @ sim.R.T @ true[i].R.T
        rot.append(np.degrees(np.arccos(np.clip((np.trace(d) - 1.0) / 2.0, -1.0, 1.0))))
    focal = np.array([result.cameras[i].K[0, 0] / true[i].K[0, 0] - 1.0 for i in idx])
    rmse = float(np.sqrt((err**2).mean()))
    names = [result.files[i] for i in idx]
    return {
        "registered": len(idx),
        "centre_error_max": float(err.max()),
        "centre_error_rms": rmse,
        "rotation_error_max_deg": float(max(rot)),
        "focal_error_max": float(np.abs(focal).max()),
    }, CameraAlignment(sim, rmse, list(zip(names, names, strict=True)))


def run(
    name: str,
    capture: Path,
    views: list,
    options: GeometryOptions,
    work: Path,
    gt: Mesh,
    *,
    truth: Path | None,
) -> dict:
    """One stage run; with ``truth`` (the capture with poses) the poses are compared and aligned first."""
    with open_capture(capture) as cap:
        t = time.perf_counter()
        result = run_geometry(
            cap, views, options=options, workdir=work / f"{name}-{'known' if truth is None else 'sfm'}"
        )
        wall = time.perf_counter() - t
    report = geometry_report(result)
    row: dict = {
        "wall_s": wall,
        "timings": report["timings"],
        "registered": report["poses"]["registered_views"],
        "reprojection_px": report["poses"]["mean_reprojection_error_px"],
        "sparse_points": report["poses"]["sparse_points"],
        "dense_points": report["dense"]["points"],
        "surface": report["surface"],
        "subdivision": report["subdivision"],
    }
    alignment = None
    if truth is not None:
        row["pose"], alignment = pose_errors(result, truth)
    metrics = evaluate(Mesh(result.vertices, result.faces), gt, alignment=alignment)
    row.update(
        accuracy=metrics.accuracy,
        completeness=metrics.completeness,
        accuracy_p90=metrics.accuracy_p90,
        completeness_p90=metrics.completeness_p90,
        signed_offset=metrics.signed_offset,
        vertices=len(result.vertices),
    )
    return row


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--models", nargs="+", default=list(MODELS), choices=list(MODELS) + list(SHAPES))
    parser.add_argument("--no-sfm", action="store_true", help="only the known-pose run")
    parser.add_argument("--work", type=Path, default=Path(tempfile.gettempdir()) / "pmvir-bench" / "geometry")
    args = parser.parse_args()
    if set(args.models) & set(MODELS) and not (SHARED / "data" / "models").is_dir():
        raise SystemExit(f"no models under {SHARED / 'data' / 'models'} (set PMVIR_SHARED)")
    args.work.mkdir(parents=True, exist_ok=True)
    options = GeometryOptions()
    results = {}
    for name in args.models:
        t = time.perf_counter()
        capture = make_capture(name, args.work)
        synth_s = time.perf_counter() - t
        views, decode_s = decode(capture)
        gt = read_mesh(capture / "gt" / "mesh.ply")
        entry = {
            "synth_s": synth_s,
            "decode_s": decode_s,
            "known": run(name, capture, views, options, args.work, gt, truth=None),
        }
        print_model(name, entry, flush=True)
        if not args.no_sfm:
            try:
                entry["sfm"] = run(
                    name,
                    strip_poses(capture, args.work / f"{name}-noposes"),
                    views,
                    options,
                    args.work,
                    gt,
                    truth=capture,
                )
            except ReconstructionError as exc:  # reported, not fatal: the other models still run
                entry["sfm"] = {"error": str(exc)}
            print_model(name, {"sfm": entry["sfm"]}, flush=True)
        results[name] = entry
    out = ROOT / "results"
    out.mkdir(exist_ok=True)
    previous = out / "geometry.json"
    if previous.is_file():  # a partial run (--models, --no-sfm) updates the entries it measured
        old = json.loads(previous.read_text()).get("models", {})
        for name, entry in results.items():
            old[name] = {**old.get(name, {}), **entry}
        results = old
    doc = {
        "options": options.model_dump(mode="json"),
        "capture": "plastic, 36 views, 612x512, seed 0",
        "models": results,
    }
    write_results("geometry", title="Geometric stage (initial surface)", tables=[geometry_table(results)], data=doc)
    print_summary(results)


def geometry_table(results: dict) -> dict:
    """One row per model and pose mode: registration, surface metrics, vertices and seconds per step."""
    rows = []
    for name, entry in results.items():
        for mode in ("known", "sfm"):
            r = entry.get(mode)
            if r is None:
                continue
            if "error" in r:
                rows.append([name, mode, None, None, None, None, None, *[None for _ in STEPS]])
                continue
            centre = round(r["pose"]["centre_error_max"], 4) if r.get("pose") else None
            rows.append([name, mode, r["registered"], centre, round(r["accuracy"], 4), round(r["completeness"], 4),
                         r["vertices"], *[round(r["timings"].get(s, 0.0), 1) for s in STEPS]])
    return table(
        "Plastic captures, 36 views of 612x512 (accuracy, completeness and centre error in diagonals)",
        ["model", "poses", "registered", "centre error", "accuracy", "completeness", "vertices",
         *[f"{s} s" for s in STEPS]],
        rows,
        note="known: the capture's poses; sfm: poses and intrinsics estimated, aligned by a similarity; "
        "a row of dashes failed (the JSON holds the error)",
    )


def print_model(name: str, entry: dict, *, flush: bool = False) -> None:
    for mode in ("known", "sfm"):
        if mode not in entry:
            continue
        r = entry[mode]
        if "error" in r:
            print(f"{name:<10} {mode:<6} ReconstructionError: {r['error'][:300]}", flush=flush)
            continue
        pose = r.get("pose")
        extra = (
            (
                f" centre err max {pose['centre_error_max']:.4f} rms {pose['centre_error_rms']:.4f}, rot "
                f"{pose['rotation_error_max_deg']:.3f} deg, focal {100 * pose['focal_error_max']:.2f}%"
            )
            if pose
            else ""
        )
        print(f"{name:<10} {mode:<6} registered {r['registered']:>2}/36{extra}", flush=flush)
        print(
            f"{'':<10} {'':<6} accuracy {r['accuracy']:.4f} completeness {r['completeness']:.4f} "
            f"vertices {r['vertices']:,} wall {r['wall_s']:.1f} s",
            flush=flush,
        )


def print_summary(results: dict) -> None:
    head = f"{'model':<10} {'mode':<6} {'reg':>4} {'centre':>7} {'acc':>7} {'comp':>7} {'verts':>8} {'cc':>3} "
    head += " ".join(f"{s[:8]:>8}" for s in STEPS)
    print()
    print(head)
    for name, entry in results.items():
        for mode in ("known", "sfm"):
            if mode not in entry:
                continue
            r = entry[mode]
            if "error" in r:
                print(f"{name:<10} {mode:<6} failed: {r['error'][:80]}")
                continue
            centre = f"{r['pose']['centre_error_max']:.4f}" if r.get("pose") else "-"
            line = (
                f"{name:<10} {mode:<6} {r['registered']:>4} {centre:>7} {r['accuracy']:>7.4f} "
                f"{r['completeness']:>7.4f} {r['vertices']:>8,} "
            )
            kept = [c for c in r.get("surface", {}).get("components", []) if c.get("kept")]
            line += f"{len(kept):>3} "
            line += " ".join(f"{r['timings'].get(s, 0.0):>8.1f}" for s in STEPS)
            print(line)
    print(
        "accuracy / completeness / centre error in GT bounding-box diagonals; cc: surface components kept; "
        "times in seconds "
        f"(decode not included); {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f}"
    )


if __name__ == "__main__":
    main()
