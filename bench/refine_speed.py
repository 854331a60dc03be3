"""Speed and memory of the three-stage refinement (pmvir.refine) at full size.

A synthetic ~300k-vertex bumpy sphere seen by 36 views at 612 x 512, rendered
with the refinement's own image model (pmvir.refine.forward), is refined from a
perturbed copy (details attenuated, noise added) with the default options on
the CPU (``--device cuda --peer cpu``: on the GPU and then on the same
machine's CPU, compared as a ratio), visibility refreshed between stages by
pmvir.geometry.visibility.

Prints a table and writes bench/results/NAME.json (``--results``, default refine_speed). Peak memory is the
process's maximum resident set size (ru_maxrss), which includes what torch
allocates (tracemalloc would not see it); on a GPU also torch's peak allocated
GPU memory.

Run: .venv/bin/python bench/refine_speed.py [--frequency 173] [--views 36] [--max-iterations N] [--device cuda --peer cpu --results refine_speed_gpu]
"""

from __future__ import annotations

import argparse
import platform
import resource
import sys
import time
from pathlib import Path

import numpy as np
import torch
from _results import table, write_results

from pmvir.camera import Camera, look_at
from pmvir.config import RefineOptions
from pmvir.geometry.visibility import vertex_visibility
from pmvir.progress import Progress
from pmvir.refine import observation_from_decoded, refine_surface
from pmvir.refine.forward import render_decoded
from pmvir.refine.state import make_visibility_fn
from pmvir.synth.shapes import geodesic_sphere


def rss_gib() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def bumps(d: np.ndarray, n: int, amp: float, width: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    c = rng.normal(size=(n, 3))
    c /= np.linalg.norm(c, axis=1, keepdims=True)
    h = amp * rng.choice([-1.0, 1.0], n)
    out = np.zeros(len(d))
    for k in range(0, n, 16):  # chunks keep (N, 16) temporaries small
        ang = np.arccos(np.clip(d @ c[k : k + 16].T, -1.0, 1.0))
        out += (h[k : k + 16] * np.exp(-((ang / width) ** 2))).sum(1)
    return out


def scene(frequency: int, n_views: int, width: int, height: int, seed: int = 0):
    d, faces = geodesic_sphere(frequency)
    coarse = bumps(d, 12, 0.06, 0.35, seed)
    fine = bumps(d, 300, 0.008, 0.06, seed + 1)
    true_v = d * (1.0 + coarse + fine)[:, None]
    rng = np.random.default_rng(seed + 2)
    h = np.linalg.norm(true_v[faces[:, 0]] - true_v[faces[:, 1]], axis=1).mean()
    init_v = d * (1.0 + coarse + 0.3 * fine + rng.normal(0.0, 0.3 * h, len(d)))[:, None]
    albedo = np.tile([0.6, 0.45, 0.3], (len(d), 1))
    albedo[d @ np.array([0.0, 0.6, 0.8]) > 0.85] = [0.25, 0.45, 0.6]
    cams = []
    f = 0.9 * width
    for i in range(n_views):
        ring = i % 3
        az = 2 * np.pi * (i // 3) / (n_views // 3) + ring * 0.3
        el = np.radians([-30.0, 0.0, 30.0][ring])
        c = 4.0 * np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
        R, t = look_at(c, np.zeros(3))
        cams.append(Camera.from_intrinsics(f, f, width / 2, height / 2, width, height, R, t))
    sh = np.tile([0.7, 0.15, 0.3, 0.1, 0.05, 0.05, 0.1, 0.05, 0.03], (n_views, 1))
    sh[:, 1:] += rng.normal(0.0, 0.03, (n_views, 8))
    scale = np.array([1.0, 0.9, 0.8]) * rng.uniform(0.9, 1.1, (n_views, 1))
    frames = render_decoded(
        true_v,
        faces,
        albedo,
        cams,
        sh,
        scale,
        specular_dirs=np.array([[0.3, 0.2, 1.0]]),
        stokes_noise=0.01,
        intensity_noise=0.003,
        seed=seed,
    )
    return true_v, init_v, faces, cams, frames


def accuracy(v: np.ndarray, true_v: np.ndarray, faces: np.ndarray) -> float:
    import open3d as o3d

    sc = o3d.t.geometry.RaycastingScene()
    sc.add_triangles(true_v.astype(np.float32), faces.astype(np.uint32))
    dist = sc.compute_distance(o3d.core.Tensor(v.astype(np.float32))).numpy()
    return float(dist.mean() / np.linalg.norm(true_v.max(0) - true_v.min(0)))


def refine_on(device: str, max_iterations: int | None, init_v, faces, cams, obs, vis, masks) -> dict:
    """One refinement of the scene on ``device``: its result, wall time, step rows and peak GPU memory."""
    opts = RefineOptions(device=device)
    cuda = opts.device != "cpu" and torch.cuda.is_available()
    if cuda:
        torch.cuda.reset_peak_memory_stats()
    if max_iterations is not None:
        opts.solver.max_iterations = max_iterations
    t1 = time.perf_counter()
    res = refine_surface(
        init_v,
        faces,
        cams,
        obs,
        vis,
        options=opts,
        visibility_fn=make_visibility_fn(cams, masks),
        masks=masks,
        progress=Progress(
            lambda _, f, m: print(
                f"{time.perf_counter() - t1:8.1f}s {f:5.3f} {m}", file=sys.stderr, flush=True
            )
        ),
    )
    seconds = time.perf_counter() - t1
    rows = [
        ("refine: setup", res.timings["setup"], ""),
        ("refine: offset scans before and after the stages", res.timings.get("offset_scan", 0.0), ""),
    ]
    for st, parts in zip(res.stages, res.stage_timings, strict=True):
        for part, sec in parts.items():
            if part != "solve":
                rows.append((f"refine: stage {st.index + 1}: {_PARTS.get(part, part)}", sec, ""))
        e0, e1 = st.energies[0]["total"], st.energies[-1]["total"]
        rows.append(
            (
                f"refine: stage {st.index + 1}: solver ({len(st.energies) - 1} it, {st.evaluations} ev, "
                f"{st.stop_reason})",
                st.seconds,
                f"E {e0:.4g} -> {e1:.4g}, {st.n_pairs:,} pairs",
            )
        )
        if "solve" in parts:
            rest = max(parts["solve"] - st.seconds, 0.0)
            rows.append((f"refine: stage {st.index + 1}: acceptance and tangential relaxation", rest, ""))
    for key, label in (
        ("hull_fit", "hull fit"),
        ("rim_fit", "rim fit"),
        ("fairing", "fairing"),
        ("lighting", "lighting fit"),
    ):
        if key in res.timings:
            rows.append((f"refine: {label}", res.timings[key], ""))
    rows.append(("refine: total", seconds, "limit 600 s"))
    return {
        "options": opts,
        "result": res,
        "seconds": seconds,
        "rows": rows,
        "gpu_peak": torch.cuda.max_memory_allocated() / 2**30 if cuda else None,
        "device_name": torch.cuda.get_device_name() if cuda else platform.processor() or platform.machine(),
    }


#: RefineResult.stage_timings' keys, as the table names them.
_PARTS = {
    "lift": "lift to the subdivided mesh",
    "offset_scan": "offset scan",
    "prepare": "visibility, samples and pairs",
    "lighting_prefit": "lighting prefit",
}


def _iterations(step: str) -> str:
    """'10 it, 13 ev, max_iterations' from a stage row's name, '' for the other rows."""
    return step.split(" (", 1)[1].rstrip(")") if " (" in step else ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frequency", type=int, default=173, help="geodesic frequency (173: 299,292 vertices)")
    ap.add_argument("--views", type=int, default=36)
    ap.add_argument("--width", type=int, default=612)
    ap.add_argument("--height", type=int, default=512)
    ap.add_argument("--max-iterations", type=int, default=None, help="override RefineOptions.max_iterations")
    ap.add_argument("--device", default="cpu", help="RefineOptions.device: cpu, cuda, cuda:N or auto")
    ap.add_argument(
        "--peer",
        default=None,
        help="a second device refining the same scene in this run (e.g. cpu beside cuda)",
    )
    ap.add_argument("--results", default="refine_speed", help="results name: bench/results/NAME.json")
    ap.add_argument("--out", default=None, help="the JSON's path (default bench/results/NAME.json)")
    args = ap.parse_args()

    t0 = time.perf_counter()
    true_v, init_v, faces, cams, frames = scene(args.frequency, args.views, args.width, args.height)
    obs = [observation_from_decoded(fr, intensity="min") for fr in frames]
    masks = [fr["mask"] for fr in frames]
    del frames
    vis = vertex_visibility(init_v, faces, cams, masks)
    t_scene = time.perf_counter() - t0
    rss_scene = rss_gib()

    runs = [refine_on(args.device, args.max_iterations, init_v, faces, cams, obs, vis, masks)]
    rss_peak = rss_gib()
    if args.peer:
        runs.append(refine_on(args.peer, args.max_iterations, init_v, faces, cams, obs, vis, masks))
    acc0 = accuracy(init_v, true_v, faces)
    for run in runs:
        run["accuracy"] = accuracy(run["result"].vertices, true_v, faces)
    main_run = runs[0]
    opts, res, gpu_peak = main_run["options"], main_run["result"], main_run["gpu_peak"]
    print(
        f"pmvir refine speed: {len(init_v):,} vertices, {len(faces):,} faces, {args.views} views "
        f"{args.width}x{args.height}, torch {torch.__version__}, {torch.get_num_threads()} threads"
    )
    print(f"scene + render + visibility (not timed below): {t_scene:.1f} s")
    for run in runs:
        print(f"device {run['options'].device} ({run['device_name']})")
        print(f"{'step':60s} {'seconds':>9s}  notes")
        for name, sec, note in run["rows"]:
            print(f"{name:60s} {sec:9.1f}  {note}")
        if run["gpu_peak"] is not None:
            print(f"peak GPU memory allocated {run['gpu_peak']:.2f} GiB")
        print(f"accuracy (GT diagonals): initial {acc0:.6f} -> refined {run['accuracy']:.6f}")
    print(f"peak RSS of the first run {rss_peak:.2f} GiB (after scene: {rss_scene:.2f} GiB; limit 8 GiB)")
    out = {
        "vertices": len(init_v),
        "faces": len(faces),
        "views": args.views,
        "image": [args.width, args.height],
        "threads": torch.get_num_threads(),
        "device": opts.device,
        "device_name": main_run["device_name"],
        "peak_gpu_gib": gpu_peak,
        "torch": torch.__version__,
        "options": opts.model_dump(),
        "scene_seconds": t_scene,
        "refine_seconds": main_run["seconds"],
        "timings": res.timings,
        "stage_timings": res.stage_timings,
        "stages": [
            {
                "iterations": len(st.energies) - 1,
                "evaluations": st.evaluations,
                "stop_reason": st.stop_reason,
                "seconds": st.seconds,
                "pairs": st.n_pairs,
                "energy_start": st.energies[0],
                "energy_end": st.energies[-1],
            }
            for st in res.stages
        ],
        "peak_rss_gib": rss_peak,
        "rss_after_scene_gib": rss_scene,
        "accuracy_initial": acc0,
        "accuracy_refined": main_run["accuracy"],
        "under_10_min": main_run["seconds"] < 600.0,
        "under_8_gib": rss_peak < 8.0,
    }
    tables = [
        table(
            f"{len(init_v):,} vertices, {args.views} views of {args.width}x{args.height}, device {opts.device} "
            f"({main_run['device_name']}), {torch.get_num_threads()} torch threads",
            ["step", "seconds", "notes"],
            [["scene + render + visibility (not timed below)", round(t_scene, 1), ""]]
            + [[name, round(sec, 1), note] for name, sec, note in main_run["rows"]],
            note=f"peak resident memory {rss_peak:.2f} GiB"
            + (f", peak GPU memory {gpu_peak:.2f} GiB" if gpu_peak is not None else "")
            + f"; accuracy (diagonals) {acc0:.6f} initial, {main_run['accuracy']:.6f} refined",
        )
    ]
    if args.peer:
        peer = runs[1]
        out["peer"] = {
            "device": peer["options"].device,
            "device_name": peer["device_name"],
            "refine_seconds": peer["seconds"],
            "accuracy_refined": peer["accuracy"],
            "stage_seconds": [st.seconds for st in peer["result"].stages],
        }
        a, b = main_run["options"].device, peer["options"].device
        tables.append(
            table(
                f"The same refinement on {a} ({main_run['device_name']}) and {b} ({peer['device_name']})",
                ["step", f"{a} s", f"{a} iterations", f"{b} s", f"{b} iterations", f"{b} / {a}"],
                [
                    [
                        ra[0].split(" (")[0],
                        round(ra[1], 1),
                        _iterations(ra[0]),
                        round(rb[1], 1),
                        _iterations(rb[0]),
                        round(rb[1] / max(ra[1], 1e-9), 2),
                    ]
                    for ra, rb in zip(main_run["rows"], peer["rows"], strict=True)
                ],
                note=f"accuracy (diagonals) refined {main_run['accuracy']:.6f} on {a}, {peer['accuracy']:.6f} on {b}",
            )
        )
    write_results(
        args.results,
        title="Refinement speed and memory" + (" on a GPU" if args.peer else ""),
        path=Path(args.out) if args.out else None,
        peer=f"the {args.peer} run on the same machine" if args.peer else None,
        tables=tables,
        data=out,
    )


if __name__ == "__main__":
    main()
