"""Benchmark of per-vertex visibility and sqrt(3) subdivision (pmvir.geometry).

A bumpy sphere (self-occluding) seen by 36 cameras of 1224 x 1024 pixels.
Prints a table and writes bench/results/subdivision.json.
Run: .venv/bin/python bench/subdivision.py
"""

from __future__ import annotations

import os
import time

import numpy as np
import open3d as o3d
from _results import table, write_results

from pmvir.camera import Camera, look_at
from pmvir.geometry.mesh_ops import ReferenceSurface
from pmvir.geometry.subdivision import sqrt3_subdivide, subdivide_until
from pmvir.geometry.visibility import vertex_visibility
from pmvir.sh import fibonacci_sphere


def bumpy_sphere(resolution: int) -> tuple[np.ndarray, np.ndarray]:
    m = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution)
    v = np.asarray(m.vertices)
    r = 1.0 + 0.15 * np.sin(5 * v[:, 0]) * np.sin(5 * v[:, 1]) * np.sin(5 * v[:, 2])
    return v * r[:, None], np.asarray(m.triangles, dtype=np.int64)


def cameras(n: int, *, focal: float) -> list[Camera]:
    cams = []
    for c in fibonacci_sphere(n) * 4.0:
        up = np.array([0.0, 0.0, 1.0]) if abs(c[2]) < 3.6 else np.array([1.0, 0.0, 0.0])
        R, t = look_at(c, np.zeros(3), up=up)
        cams.append(Camera.from_intrinsics(focal, focal, 612.0, 512.0, 1224, 1024, R, t))
    return cams


def timed(rows: list, name: str, fn):
    t = time.perf_counter()
    out = fn()
    rows.append((name, time.perf_counter() - t))
    return out


def main() -> None:
    rows: list[tuple[str, float]] = []
    cams = cameras(36, focal=1000.0)
    v, f = bumpy_sphere(388)  # ~300k vertices, ~600k faces
    vis = timed(rows, f"visibility {len(v):,} vertices x 36 views", lambda: vertex_visibility(v, f, cams))
    visible_fraction = float(vis.mean())

    v1, f1 = bumpy_sphere(224)  # ~100k vertices, ~200k faces
    v3, f3 = bumpy_sphere(129)  # ~33k vertices, ~66k faces
    small_v, small_f = bumpy_sphere(158)  # ~50k vertices, ~100k faces
    name = f"sqrt3 step {len(small_f):,} -> {3 * len(small_f):,} faces"
    timed(rows, name, lambda: sqrt3_subdivide(small_v, small_f))
    timed(rows, f"sqrt3 step {len(f1):,} -> {3 * len(f1):,} faces", lambda: sqrt3_subdivide(v1, f1))
    surface = ReferenceSurface(small_v, small_f)
    pts = sqrt3_subdivide(small_v, small_f).vertices
    timed(rows, f"project {len(pts):,} points onto {len(small_f):,} faces", lambda: surface.project(pts))

    vis3 = vertex_visibility(v3, f3, cams)
    res = timed(
        rows,
        f"subdivide_until {len(f3):,} faces, 2 px^2",
        lambda: subdivide_until(v3, f3, vis3, cams, max_area_px=2.0, max_rounds=6, max_vertices=3_000_000),
    )

    print(f"cores {os.cpu_count()}, visible fraction {visible_fraction:.3f}")
    print(f"subdivide_until: {res.rounds} rounds, {len(res.vertices):,} vertices, {len(res.faces):,} faces, "
          f"max area {res.max_area_px:.2f} px^2, converged {res.converged}")
    print(f"{'step':<52} {'seconds':>8}")
    for name, s in rows:
        print(f"{name:<52} {s:8.2f}")
    write_results(
        "subdivision",
        title="Visibility and sqrt(3) subdivision",
        tables=[
            table(
                "A bumpy sphere seen by 36 cameras of 1224 x 1024",
                ["step", "seconds"],
                [[name, round(s, 3)] for name, s in rows],
                note=f"subdivide_until: {res.rounds} rounds, {len(res.vertices):,} vertices, "
                f"largest face {res.max_area_px:.2f} px^2, converged {res.converged}; "
                f"visible fraction {visible_fraction:.3f}",
            )
        ],
        data={
            "seconds": dict(rows),
            "visible_fraction": visible_fraction,
            "subdivide_until": {
                "rounds": res.rounds,
                "vertices": len(res.vertices),
                "faces": len(res.faces),
                "max_area_px": res.max_area_px,
                "converged": res.converged,
            },
        },
    )

if __name__ == "__main__":
    main()
