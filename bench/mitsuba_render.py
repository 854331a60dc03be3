"""Mitsuba 3 renderer benchmark: one 612x512 view per material, polarized path tracing on the CPU.

Scene: the built-in ``blob`` shape (pmvir.synth.shapes) with a striped albedo,
lit by a pmvir-sh9 environment, seen by a 612x512 pinhole camera it fills
about half of. Each material (diffuse, pplastic, conductor) is rendered once
to warm up (Dr.Jit compiles, or loads from its kernel cache, one kernel per
material) and then timed ``--reps`` times at ``--spp`` samples per pixel.

Reported per material: wall seconds, CPU seconds of the process (all Dr.Jit
threads), camera paths per CPU second (3 colour passes x pixels x spp), and the
peak resident memory. The machine's 1-minute load average is recorded before
and after, because wall time on a shared machine depends on it; CPU seconds do
not.

With ``--scalar`` it also times Mitsuba's own ``scalar_spectral_polarized``
variant (``mi.render`` with the ``stokes`` integrator, a perspective sensor and
a constant albedo, so no per-vertex colour) on the same mesh, in a child
process, for comparison.

Run: .venv/bin/python bench/mitsuba_render.py [--spp 64] [--reps 1] [--scalar]
Prints a table, writes bench/results/mitsuba_render.json.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
from _results import table, write_results

from pmvir.camera import Camera, look_at
from pmvir.synth.mitsuba_renderer import VARIANT, _mitsuba, render_view_stokes
from pmvir.synth.shapes import builtin_shape

WIDTH, HEIGHT = 612, 512
SH = np.array([0.9, 0.25, 0.35, -0.2, 0.05, -0.05, 0.1, 0.05, -0.05])
RGB_SCALE = np.array([1.0, 0.95, 0.9])
MATERIALS = {"diffuse": {}, "pplastic": {"ior": 1.5, "roughness": 0.1},
             "conductor": {"ior": 0.47, "extinction": 2.4}}


def scene():
    mesh = builtin_shape("blob")
    v = mesh.vertices - mesh.vertices.mean(axis=0)
    v /= np.linalg.norm(v.max(axis=0) - v.min(axis=0))
    stripes = 0.5 + 0.4 * np.sign(np.sin(40.0 * v[:, 2]))[:, None] * np.array([0.5, 0.3, 0.1])
    R, t = look_at(np.array([0.9, -1.4, 0.5]), np.zeros(3), up=np.array([0.0, 0.0, 1.0]))
    camera = Camera.from_intrinsics(900.0, 900.0, WIDTH / 2, HEIGHT / 2, WIDTH, HEIGHT, R, t)
    return v, mesh.faces, np.clip(stripes, 0.05, 0.95).astype(np.float32), camera


SCALAR_CHILD = r"""
import json, sys, time
import mitsuba as mi
mi.set_variant("scalar_spectral_polarized")
d = json.loads(sys.argv[1])
bsdfs = {"diffuse": {"type": "diffuse"}, "pplastic": {"type": "pplastic"},
         "conductor": {"type": "conductor", "material": "Au"}}
out = {}
for material, bsdf in bsdfs.items():
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "stokes", "nested": {"type": "path", "max_depth": 6}},
        "mesh": {"type": "ply", "filename": d["ply"], "bsdf": bsdf},
        "light": {"type": "constant"},
        "sensor": {"type": "perspective", "fov": d["fov"], "fov_axis": "x",
                   "to_world": mi.ScalarTransform4f(d["to_world"]),
                   "film": {"type": "hdrfilm", "width": d["w"], "height": d["h"],
                            "rfilter": {"type": "box"}}}})
    w0, c0 = time.perf_counter(), time.process_time()
    mi.render(scene, spp=d["spp"])
    out[material] = [time.perf_counter() - w0, time.process_time() - c0]
print(json.dumps(out))
"""


def scalar_reference(vertices, faces, camera, spp):
    """Wall and CPU seconds of mi.render in scalar_spectral_polarized, per material (child process)."""
    from pmvir.io.ply import Mesh, write_mesh_ply

    ply = Path("/tmp/pmvir_bench_mitsuba_mesh.ply")
    write_mesh_ply(ply, Mesh(vertices, faces))
    world_from_cam = np.eye(4)
    world_from_cam[:3, :3] = camera.R.T @ np.diag([-1.0, -1.0, 1.0])  # Mitsuba: +x left, +y up
    world_from_cam[:3, 3] = camera.center
    fov = float(np.degrees(2.0 * np.arctan(camera.width / (2.0 * camera.K[0, 0]))))
    arg = json.dumps({"ply": str(ply), "fov": fov, "to_world": world_from_cam.tolist(),
                      "w": camera.width, "h": camera.height, "spp": spp})
    res = subprocess.run([sys.executable, "-c", SCALAR_CHILD, arg], capture_output=True, text=True,
                         check=True)
    line = [line for line in res.stdout.splitlines() if '{"diffuse"' in line][-1]  # after Mitsuba's log
    return json.loads(line[line.index("{"):])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--reps", type=int, default=1)
    parser.add_argument("--scalar", action="store_true", help="also time scalar_spectral_polarized")
    parser.add_argument("--scalar-spp", type=int, default=4)
    args = parser.parse_args()

    _mitsuba()
    vertices, faces, albedo, camera = scene()
    load_before = os.getloadavg()[0]
    rows = []
    for material, options in MATERIALS.items():
        kw = dict(material=material, sh=SH, rgb_scale=RGB_SCALE, **options)
        w0 = time.perf_counter()
        image = render_view_stokes(vertices, faces, albedo, camera, spp=1, **kw)
        warm = time.perf_counter() - w0
        walls, cpus = [], []
        for rep in range(args.reps):
            w0, c0 = time.perf_counter(), time.process_time()
            image = render_view_stokes(vertices, faces, albedo, camera, spp=args.spp, seed=rep, **kw)
            walls.append(time.perf_counter() - w0)
            cpus.append(time.process_time() - c0)
        paths = 3 * WIDTH * HEIGHT * args.spp
        s = image.stokes.mean(axis=2)
        inside = image.alpha == 1.0
        dop = np.hypot(s[..., 1], s[..., 2]) / np.maximum(s[..., 0], 1e-6)
        rows.append({"material": material, "spp": args.spp, "warmup_s_spp1": round(warm, 2),
                     "wall_s": round(float(np.median(walls)), 2), "cpu_s": round(float(np.median(cpus)), 2),
                     "paths_per_cpu_s": round(paths / float(np.median(cpus))),
                     "coverage": round(float(inside.mean()), 3),
                     "median_dop_on_object": round(float(np.median(dop[inside])), 4)})
    peak_mib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    load_after = os.getloadavg()[0]
    scalar = scalar_reference(vertices, faces, camera, args.scalar_spp) if args.scalar else None

    print(f"Mitsuba {VARIANT}, {WIDTH}x{HEIGHT}, {len(faces)} faces, {os.cpu_count()} CPUs, "
          f"load {load_before:.1f} -> {load_after:.1f}, peak RSS {peak_mib:.0f} MiB")
    print(f"{'material':<10} {'spp':>4} {'wall s':>8} {'CPU s':>8} {'paths/CPU s':>12} {'DoP med':>8}")
    for r in rows:
        print(f"{r['material']:<10} {r['spp']:>4} {r['wall_s']:>8.2f} {r['cpu_s']:>8.2f} "
              f"{r['paths_per_cpu_s']:>12,} {r['median_dop_on_object']:>8.4f}")
    if scalar:
        print(f"scalar_spectral_polarized (mi.render, stokes, {args.scalar_spp} spp; wall / CPU s):")
        for material, (wall, cpu) in scalar.items():
            rate = WIDTH * HEIGHT * args.scalar_spp / cpu
            print(f"  {material:<10} {wall:8.2f} {cpu:8.2f}  ({rate:,.0f} paths/CPU s, 4 wavelengths each)")
    out = {"variant": VARIANT, "width": WIDTH, "height": HEIGHT, "faces": len(faces),
           "load_before": load_before, "load_after": load_after,
           "peak_rss_mib": round(peak_mib), "rows": rows,
           "scalar_spectral_polarized": scalar, "scalar_spp": args.scalar_spp if scalar else None}
    tables = [table(
        f"One {WIDTH}x{HEIGHT} view of the blob per material ({VARIANT})",
        ["material", "spp", "wall s", "CPU s", "camera paths per CPU s", "median DoP on the object"],
        [[r["material"], r["spp"], r["wall_s"], r["cpu_s"], r["paths_per_cpu_s"], r["median_dop_on_object"]]
         for r in rows],
        note=f"peak resident memory {round(peak_mib)} MiB",
    )]
    if scalar:
        tables.append(table(
            f"Mitsuba's scalar_spectral_polarized variant (mi.render, stokes integrator, {args.scalar_spp} spp)",
            ["material", "wall s", "CPU s"],
            [[material, round(wall, 2), round(cpu, 2)] for material, (wall, cpu) in scalar.items()],
        ))
    write_results("mitsuba_render", title="Path tracing (Mitsuba 3)", tables=tables,
                  peer="Mitsuba's own scalar_spectral_polarized variant" if scalar else None, data=out)


if __name__ == "__main__":
    main()
