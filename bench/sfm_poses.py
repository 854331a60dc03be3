"""Benchmark of the poses step (pmvir.geometry.sfm.poses): known-pose triangulation and SfM.

Usage: .venv/bin/python bench/sfm_poses.py [--models bunny dragon armadillo] [--views 36]
       [--size 612x512] [--focal-factor 1.2] [--keep DIR] [--capture NAME=DIR ...]

For each model of ../shared/data/models (normalized, plastic, pmvir synth's built-in renderer)
it synthesizes a capture, decodes I_int and I_min and runs ``estimate_poses`` on the images
``--grey`` names (default ``auto``, as the geometric stage: SfM on I_min, again on I_int when that leaves views out)
three times: with the capture's cameras (known poses), without them but with the intrinsics
(``sfm-K``), and with neither (``sfm``, intrinsics estimated); ``--mapper global`` uses COLMAP's
global mapper, ``--guided`` turns guided matching on, ``--rematch N`` sets sfm.rematch_rounds and
``--rematch-min-track N`` sfm.rematch_min_track. It
prints per run the
registered views, sparse points (and their median / 90th-percentile distance to the true
surface for known poses), the mean reprojection error, the camera-centre errors after a Umeyama
similarity (largest, in % of the scene size = bounding-box diagonal of the true camera centres,
and in object units = bounding-box diagonal 1), the focal-length error, the time per step and
what each refinement after the mapping cost and gave (``extras``), and writes
bench/results/sfm_poses.json. Beside every SfM run, right after it, pycolmap's plain pipeline
(default SIFT extraction, exhaustive matching, incremental mapping) runs on the same SIFT images
(``--no-plain``: not), with the same measures and the ratio of the two times. Target: ours within
2x of the plain pipeline.

``--capture NAME=DIR`` adds a capture made elsewhere (its frames, manifest with the true cameras, and masks
where it has them), e.g. a path-traced object on a table from ``pmvir synth --scene table --renderer mitsuba
--no-masks``, as a row named NAME; ``--models`` with no name runs the captures alone.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from _results import table, write_results

from pmvir.capture import open_capture
from pmvir.config import SfmOptions
from pmvir.decode import decode_frame
from pmvir.errors import ReconstructionError
from pmvir.evaluate import SurfaceQuery
from pmvir.geometry.sfm.align import umeyama
from pmvir.geometry.sfm.poses import estimate_poses
from pmvir.io.ply import read_mesh
from pmvir.synth.generate import synthesize

MODELS = {"bunny": "bunny.ply", "dragon": "dragon.ply", "armadillo": "armadillo.obj"}
#: Up axis of each model file (Stanford scans are y-up).
UP = {"bunny": "y", "dragon": "y", "armadillo": "y"}


def _shared() -> Path:
    env = os.environ.get("PMVIR_SHARED")
    return Path(env) if env else Path(__file__).resolve().parents[1] / ".." / "shared"


#: The rows per model: known poses; SfM with the intrinsics given; SfM estimating them.
MODES = ("known", "sfm-K", "sfm")


def _run(capture: Path, mode: str, workdir: Path, options: SfmOptions, *, plain: bool) -> dict:
    known = mode == "known"
    with open_capture(capture) as cap:
        t0 = time.perf_counter()
        i_int, i_min, masks = [], [], []
        for i in range(len(cap)):
            raw = cap.read_raw(i)
            mask = cap.read_mask(i)
            decoded = decode_frame(raw.mosaic, cap.layout, saturated=raw.saturated, mask=mask)
            i_int.append(decoded.i_int)
            i_min.append(decoded.i_min)
            masks.append(mask)
        # as the geometric stage does: I_min for SfM with I_int as the fallback ('auto'), I_int with known poses
        use_min = options.grey == "min" or (options.grey == "auto" and not known)
        images = i_min if use_min else i_int
        fallback = i_int if options.grey == "auto" and not known else None
        decode_s = time.perf_counter() - t0
        true = [f.camera for f in cap.frames]
        names = [f.name for f in cap.frames]
    t0 = time.perf_counter()
    cpu0 = time.process_time()
    model = estimate_poses(
        images, names, cameras=true if known else None, masks=masks, options=options, workdir=workdir,
        intrinsics=[c.K for c in true] if mode == "sfm-K" else None, fallback_images=fallback,
    )
    row: dict = {
        "mode": mode,
        "registered": model.num_registered,
        "views": len(names),
        "points": len(model.points),
        "sift_images": "I_int" if not use_min or model.fallback else "I_min",
        "reprojection_px": model.mean_reprojection_error,
        "wall_s": time.perf_counter() - t0,
        "cpu_s": time.process_time() - cpu0,
        "decode_s": decode_s,
        "timings": model.timings,
    }
    if known:
        mesh = read_mesh(capture / "gt" / "mesh.ply")
        closest, _, _ = SurfaceQuery(mesh.vertices, mesh.faces).closest(model.points)
        d = np.linalg.norm(closest - model.points, axis=1)
        row["points_median_dist"] = float(np.median(d))
        row["points_p90_dist"] = float(np.percentile(d, 90))
    else:
        reg = [i for i, c in enumerate(model.cameras) if c is not None]
        row |= _centre_errors(reg, np.stack([model.cameras[i].center for i in reg]), true)
        row["extras"] = model.extras
        if plain:  # side by side: pycolmap's plain pipeline on the SIFT images ours saw
            kept = [e["step"] for e in model.extras if e.get("kept") is True]
            run_dir = {"denoised_first": "denoised-first", "denoised": "denoised",
                       "without_upsampling": "without-upsampling"}
            sift_dir = workdir / (run_dir[kept[0]] if kept else "fallback" if model.fallback else "") / "images"
            row["plain"] = _plain_colmap(sift_dir, workdir / "plain", true, names, options.seed)
            row["ratio_wall"] = row["timings"]["total"] / row["plain"]["timings"]["total"]
            row["ratio_cpu"] = row["cpu_s"] / row["plain"]["cpu_s"]
        focal = np.array([model.cameras[i].K[0, 0] for i in reg])
        row["focal_err_pct"] = float(100 * (focal.mean() / true[0].K[0, 0] - 1.0))
    return row


def _plain_colmap(image_dir: Path, workdir: Path, true: list, names: list[str], seed: int) -> dict:
    """pycolmap's plain pipeline on the SIFT images ours wrote: default SIFT extraction (one shared
    camera, COLMAP's default model), exhaustive matching, incremental mapping; its largest model."""
    import pycolmap

    from pmvir.geometry.sfm.colmap import quiet_colmap

    workdir.mkdir(parents=True, exist_ok=True)
    database = workdir / "database.db"
    database.unlink(missing_ok=True)
    timings: dict[str, float] = {}
    t_all, cpu0 = time.perf_counter(), time.process_time()
    with quiet_colmap():
        t0 = time.perf_counter()
        pycolmap.extract_features(database, image_dir, camera_mode=pycolmap.CameraMode.SINGLE)
        timings["features"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        pycolmap.match_exhaustive(database)
        timings["matching"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        mapping = pycolmap.IncrementalPipelineOptions()
        mapping.random_seed = seed
        models = pycolmap.incremental_mapping(database, image_dir, workdir / "sparse", options=mapping)
        timings["mapping"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_all
    row: dict = {"timings": timings, "wall_s": timings["total"], "cpu_s": time.process_time() - cpu0,
                 "registered": 0, "views": len(names), "models": len(models)}
    if not models:
        return row
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    index = {f"{i:05d}.png": i for i in range(len(names))}
    centres = {index[im.name]: im.projection_center() for im in rec.images.values() if im.has_pose}
    row["registered"] = len(centres)
    row["points"] = rec.num_points3D()
    row["reprojection_px"] = float(rec.compute_mean_reprojection_error())
    if len(centres) >= 3:  # a similarity needs three centres
        row |= _centre_errors(list(centres), np.stack([centres[i] for i in centres]), true)
    return row


def _centre_errors(reg: list[int], est: np.ndarray, true: list) -> dict:
    """Camera-centre errors after a similarity to the true centres of the registered views."""
    tru = np.stack([true[i].center for i in reg])
    err = np.linalg.norm(umeyama(est, tru).apply(est) - tru, axis=1)
    scene = float(np.linalg.norm(tru.max(0) - tru.min(0)))
    return {"centre_err_max": float(err.max()), "centre_err_mean": float(err.mean()),
            "centre_err_max_pct_scene": float(100 * err.max() / scene), "scene_size": scene}


def sfm_table(results: list[dict], args: argparse.Namespace) -> dict:
    """The runs as one table of the benchmarks page (known poses: distance of the points to the surface), each
    SfM run followed by pycolmap's plain pipeline on the same images and the ratio of the two times."""
    rows = []
    for r in results:
        if "error" in r:
            rows.append([r["model"], r["mode"], None, None, None, None, None, None, f"failed: {r['error'][:120]}"])
            continue
        quality = (
            f"points to surface: median {r['points_median_dist']:.4f}" if r["mode"] == "known" else
            f"centre error max {r['centre_err_max_pct_scene']:.3f}% of the scene; focal {r['focal_err_pct']:+.2f}%"
        )
        rows.append([r["model"], r["mode"], f"{r['registered']}/{r['views']}", r["points"],
                     round(r["reprojection_px"], 2), round(r["timings"]["total"], 1), round(r["cpu_s"], 1),
                     None, quality])
        plain = r.get("plain")
        if plain is not None:
            quality = ("no model" if not plain["registered"] else
                       f"{plain['registered']} views: no similarity" if "centre_err_max_pct_scene" not in plain else
                       f"centre error max {plain['centre_err_max_pct_scene']:.3f}% of the scene")
            rows.append([r["model"], f"{r['mode']}, pycolmap plain", f"{plain['registered']}/{plain['views']}",
                         plain.get("points"), round(plain.get("reprojection_px", float("nan")), 2),
                         round(plain["timings"]["total"], 1), round(plain["cpu_s"], 1),
                         f"{r['ratio_wall']:.2f} (CPU {r['ratio_cpu']:.2f})", quality])
    title = f"{args.views} views of {args.size}, plastic, built-in renderer" if args.models else "Captures given"
    if args.models and args.capture:
        title += " (the models; the captures given as named)"
    return table(
        title,
        ["model", "mode", "registered", "points", "reprojection px", "seconds", "CPU s", "ours / plain", "quality"],
        rows,
        note="known: the capture's poses; sfm-K: intrinsics given; sfm: neither. pycolmap plain: default SIFT "
        "extraction, exhaustive matching and incremental mapping on the SIFT images of the run above it, right "
        "after it; ours / plain: the ratio of their seconds (and CPU seconds)",
    )


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--models", nargs="*", default=list(MODELS))
    ap.add_argument(
        "--capture", action="append", default=[], metavar="NAME=DIR",
        help="one more capture (a folder with capture.json and the true cameras), its rows named NAME",
    )
    ap.add_argument("--views", type=int, default=36)
    ap.add_argument("--size", default="612x512")
    ap.add_argument("--focal-factor", type=float, default=1.2)
    ap.add_argument("--keep", type=Path, help="keep the captures and work folders here")
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--mapper", choices=("incremental", "global"), default=SfmOptions().mapper)
    ap.add_argument("--grey", choices=("auto", "int", "min"), default=SfmOptions().grey)
    ap.add_argument("--guided", action="store_true", help="guided matching")
    ap.add_argument("--rematch", type=int, default=SfmOptions().rematch_rounds, help="sfm.rematch_rounds")
    ap.add_argument(
        "--rematch-min-track", type=int, default=SfmOptions().rematch_min_track, help="sfm.rematch_min_track"
    )
    ap.add_argument("--no-plain", action="store_true", help="do not run pycolmap's plain pipeline beside ours")
    ap.add_argument("--tag", default="", help="results go to bench/results/sfm_poses[-TAG].json")
    ap.add_argument(
        "--set", action="append", default=[], metavar="KEY=VALUE",
        help="one more SfM option (a field of SfmOptions; VALUE is JSON), e.g. --set sift_affine_shape=false",
    )
    args = ap.parse_args()
    extra = {key: json.loads(value) for key, _, value in (item.partition("=") for item in args.set)}
    options = SfmOptions(
        mapper=args.mapper, grey=args.grey, guided_matching=args.guided, rematch_rounds=args.rematch,
        rematch_min_track=args.rematch_min_track, **extra,
    )
    models_dir = _shared() / "data" / "models"
    if args.models and not models_dir.is_dir():
        print(f"no models at {models_dir}", file=sys.stderr)
        return 1
    given = dict(item.partition("=")[::2] for item in args.capture)
    for name, folder in given.items():
        if not (Path(folder) / "capture.json").is_file():
            print(f"--capture {name}={folder}: no capture.json there", file=sys.stderr)
            return 1
    results = []
    with tempfile.TemporaryDirectory() as tmp:
        root = args.keep or Path(tmp)
        for name in [*args.models, *given]:
            capture = Path(given[name]) if name in given else root / f"{name}-capture"
            t0 = time.perf_counter()
            if not (capture / "capture.json").exists():
                synthesize(
                    capture, mesh=models_dir / MODELS[name], views=args.views, size=args.size, material="plastic",
                    focal_factor=args.focal_factor, mesh_up=UP[name], overwrite=True,
                )
            synth_s = time.perf_counter() - t0
            for mode in args.modes:
                known = mode == "known"
                try:
                    work = root / f"{name.replace(' ', '_').replace(',', '')}-work"
                    row = {"model": name, "synth_s": synth_s, **({"capture": str(capture)} if name in given else {}),
                           **_run(capture, mode, work, options, plain=not args.no_plain)}
                except ReconstructionError as exc:
                    results.append({"model": name, "mode": mode, "error": str(exc)})
                    print(f"{name:10s} {mode:5s} ReconstructionError: {exc}", flush=True)
                    continue
                results.append(row)
                t = row["timings"]
                steps = " ".join(f"{k}={v:.1f}" for k, v in t.items() if k != "total")
                quality = (
                    f"points on surface: median {row['points_median_dist']:.4f} p90 {row['points_p90_dist']:.4f}"
                    if known else
                    f"centres: max {row['centre_err_max']:.4f} ({row['centre_err_max_pct_scene']:.2f} % of scene "
                    f"{row['scene_size']:.2f}) mean {row['centre_err_mean']:.4f}; focal {row['focal_err_pct']:+.2f} %"
                )
                if "plain" in row:
                    pl = row["plain"]
                    print(f"{name:10s} {mode:5s} pycolmap plain: reg {pl['registered']}/{pl['views']} "
                          f"centres max {pl.get('centre_err_max_pct_scene', float('nan')):.3f} % of scene | "
                          f"total {pl['timings']['total']:.1f}s (cpu {pl['cpu_s']:.1f}s) | ours / plain "
                          f"{row['ratio_wall']:.2f} (cpu {row['ratio_cpu']:.2f})", flush=True)
                print(
                    f"{name:10s} {row['mode']:5s} {row['sift_images']} reg {row['registered']:2d}/{row['views']} "
                    f"pts {row['points']:5d} "
                    f"reproj {row['reprojection_px']:.2f}px | {quality} | total {t['total']:.1f}s "
                    f"(cpu {row['cpu_s']:.1f}s; {steps})",
                    flush=True,
                )
    name = f"sfm_poses{'-' + args.tag if args.tag else ''}"
    out = write_results(
        name,
        title="Poses (structure from motion)",
        tables=[sfm_table(results, args)],
        data={"views": args.views, "size": args.size, "focal_factor": args.focal_factor,
              "options": options.model_dump(mode="json"), "results": results},
    )
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
