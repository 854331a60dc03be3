"""Benchmark of pmvir.evaluate: a 300k-vertex estimate against a ~70k-face ground truth.

Prints a table and writes bench/results/evaluate.json. Run: .venv/bin/python bench/bench_evaluate.py
"""

from __future__ import annotations

import os
import time

import numpy as np
import open3d as o3d
from _results import table, write_results

from pmvir.evaluate import SurfaceQuery, evaluate, sample_surface
from pmvir.io.ply import Mesh


def sphere(radius: float, resolution: int, seed: int) -> Mesh:
    m = o3d.geometry.TriangleMesh.create_sphere(radius=radius, resolution=resolution)
    v = np.asarray(m.vertices)
    rng = np.random.default_rng(seed)
    return Mesh(v, np.asarray(m.triangles), albedo=rng.uniform(0.1, 0.9, (len(v), 3)).astype(np.float32))


def main() -> None:
    gt = sphere(1.0, 132, 0)  # 132 -> 69,168 faces
    est = sphere(1.01, 388, 1)  # 388 -> ~301k vertices
    rows = []
    t = time.perf_counter()
    sample_surface(gt.vertices, gt.faces, 1_000_000, seed=0)
    rows.append(("sample 1M points by area", time.perf_counter() - t))
    t = time.perf_counter()
    q = SurfaceQuery(gt.vertices, gt.faces)
    q.closest(est.vertices)
    rows.append((f"closest points, {len(est.vertices):,} vertices", time.perf_counter() - t))
    t = time.perf_counter()
    res = evaluate(est, gt, n_samples=1_000_000)
    rows.append(("evaluate() total", time.perf_counter() - t))
    print(f"GT faces {len(gt.faces):,}, estimate vertices {len(est.vertices):,}, cores {os.cpu_count()}")
    print(f"{'step':<40} {'seconds':>8}")
    for name, s in rows:
        print(f"{name:<40} {s:8.2f}")
    print(f"accuracy {res.accuracy:.6f} completeness {res.completeness:.6f}")
    write_results(
        "evaluate",
        title="Evaluation (accuracy and completeness of a mesh against ground truth)",
        tables=[
            table(
                f"A {len(est.vertices):,}-vertex estimate against a {len(gt.faces):,}-face ground truth, "
                "1,000,000 samples",
                ["step", "seconds"],
                [[name, round(s, 3)] for name, s in rows],
                note=f"accuracy {res.accuracy:.6f}, completeness {res.completeness:.6f} (a sphere of radius "
                "1.01 against one of radius 1)",
            )
        ],
        data={
            "gt_faces": len(gt.faces),
            "est_vertices": len(est.vertices),
            "seconds": dict(rows),
            "accuracy": res.accuracy,
            "completeness": res.completeness,
        },
    )

if __name__ == "__main__":
    main()
