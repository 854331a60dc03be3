"""Where the refinement's minimum lies: refine starting from the TRUE surface of a synthetic capture.

A model that matched the capture exactly, fed noise-free data, would leave the true surface where
it is; what the refinement moves it by is its floor on that capture: the noise it fits and the
physics it lacks. Comparing variants' floors (MVIR, the full method, options) on a physically
rendered capture and on the built-in renderer's separates the two: on the built-in renderer the
model is exact and only noise moves it.

The true mesh (gt/mesh.ply) is split by --subdivide uniform sqrt(3) steps without smoothing (the
surface does not change; the vertex count comes near the pipeline's subdivided initial surface),
its visibility computed from the capture's true poses and masks, and each variant refined from it
exactly as the pipeline's refine stage does (pmvir.refine.refine_surface with the pipeline's
observations and visibility refresh). Accuracy and the normal error are measured with pmvir.evaluate
(spec section 5);
completeness is printed too, but it depends on the vertex density, which differs from a
reconstruction's.

``--observations`` says what each variant fits: the decoded frames (``decoded``, the default); the
renderer's noise-free AoP and DoP (gt/views/<frame>.npz) in place of the decoded ones
(``noise-free-pol``: the floor the decoding's AoP leaves); those and its noise-free intensity
(``noise-free``: what the model and the schedule leave of the true surface with exact data). The
pixels each view fits and the AoP noise weights stay the decoded frames'.

Prints a markdown table and writes bench/results/refine_from_truth_floor.json (or --out).
Run: .venv/bin/python bench/refine_from_truth.py CAPTURE [--subdivide 1] [--iterations 40]
     [--variant NAME key=value ...] [--samples 200000] [--offset D] [--observations decoded noise-free]
     e.g. --variant mvir pol.enabled=false --variant full --variant rho1 pol.dop_weight_power=1
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
from _results import capture_description, table, write_results

from pmvir.capture import open_capture
from pmvir.commands.options import parse_overrides
from pmvir.config import PipelineConfig, RefineOptions, merge_options
from pmvir.errors import PmvirError
from pmvir.evaluate import bbox_diagonal, evaluate
from pmvir.geometry.subdivision import sqrt3_subdivide
from pmvir.geometry.visibility import vertex_visibility
from pmvir.io.ply import Mesh, read_mesh, vertex_normals
from pmvir.pipeline import decode_views, refinement_observations
from pmvir.refine import make_visibility_fn, refine_surface
from pmvir.refine.sampling import Observation

ROOT = Path(__file__).resolve().parent


#: What the variants fit (module docstring).
OBSERVATIONS = ("decoded", "noise-free-pol", "noise-free")


def noise_free(capture: Path, stems: list[str], observations: list[Observation], kind: str, intensity: str) -> list[Observation]:
    """The observations with the renderer's noise-free AoP and DoP (``kind`` 'noise-free-pol') and
    intensity ('noise-free': I_min = (1 - DoP) I_int, or I_int as ``intensity`` says) from
    gt/views/<stem>.npz; the valid pixels are the decoded ones where the renderer's are defined."""
    out = []
    for stem, obs in zip(stems, observations, strict=True):
        path = capture / "gt" / "views" / f"{stem}.npz"
        if not path.is_file():
            raise PmvirError(f"{path}: not found (noise-free observations need a synthetic capture's gt/views)")
        with np.load(path) as g:
            aop, dop, i_int, mask = g["aop"], g["dop"], g["i_int"], g["mask"]
        if aop.shape != obs.aop.shape:
            raise PmvirError(f"{path}: {aop.shape[1]}x{aop.shape[0]}, the observations are "
                             f"{obs.aop.shape[1]}x{obs.aop.shape[0]} (refine at the frames' size)")
        valid = obs.valid & mask & np.isfinite(aop) & np.isfinite(dop) & np.isfinite(i_int).all(axis=2)
        dop = np.nan_to_num(dop).astype(np.float32)
        new = replace(obs, aop=np.nan_to_num(aop).astype(np.float32), dop=dop, valid=valid)
        if kind == "noise-free":
            linear = np.nan_to_num(i_int).astype(np.float32)
            new = replace(new, intensity=linear if intensity == "int" else (1.0 - dop)[..., None] * linear)
        out.append(new)
    return out


def parse_variants(tokens: list[list[str]]) -> dict[str, dict]:
    """``[[name, key=value, ...], ...]`` -> {name: nested refine options} (keys dotted, values parsed as JSON)."""
    try:
        return {name: parse_overrides(pairs) for name, *pairs in tokens}
    except PmvirError as exc:
        raise SystemExit(f"--variant: {exc}") from exc


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("capture", type=Path, help="a synthetic capture with true poses and gt/mesh.ply")
    parser.add_argument("--subdivide", type=int, default=1, help="sqrt(3) steps applied to the true mesh")
    parser.add_argument("--iterations", type=int, default=40, help="refine.solver.max_iterations per stage")
    parser.add_argument(
        "--variant",
        nargs="+",
        action="append",
        metavar="NAME [key=value]",
        help="refine options of a variant",
    )
    parser.add_argument("--samples", type=int, default=200_000, help="ground-truth samples for the metrics")
    parser.add_argument(
        "--offset",
        type=float,
        default=0.0,
        help="start from the true surface moved along its vertex normals by this many GT diagonals "
        "(negative: inward), to see whether the refinement removes an offset every vertex shares",
    )
    parser.add_argument(
        "--observations", nargs="+", choices=OBSERVATIONS, default=["decoded"],
        help="what every variant fits, each in turn: the decoded frames, the renderer's noise-free AoP and DoP, "
        "or those and its noise-free intensity",
    )
    parser.add_argument("--out", type=Path, default=ROOT / "results" / "refine_from_truth_floor.json")
    args = parser.parse_args()
    variants = parse_variants(args.variant or [["mvir", "pol.enabled=false"], ["full"]])
    try:
        rows = run(
            args.capture,
            variants,
            subdivide=args.subdivide,
            iterations=args.iterations,
            samples=args.samples,
            offset=args.offset,
            observations=args.observations,
        )
    except PmvirError as e:
        sys.exit(f"error: {e}")
    made = f" ({d})" if (d := capture_description(args.capture)) else ""
    start = "the true surface" + (
        f" moved {args.offset:+g} diagonals along its normals" if args.offset else ""
    )
    write_results(
        args.out.stem,  # the results file names its benchmark
        title="Refinement started from the true surface",
        path=args.out,
        peer="MVIR (the refinement without E_pol)" if "mvir" in {r["variant"] for r in rows} else None,
        tables=[
            table(
                f"{args.capture.name}{made}: refined from {start} ({rows[0]['vertices']:,} vertices)",
                ["variant", "observations", "options", "accuracy x1e-2", "signed offset x1e-2", "completeness x1e-2",
                 "normal error mean deg", "normal error median deg", "seconds"],
                [[r["variant"], r["observations"], r["options"] or "defaults", round(100 * r["accuracy"], 4),
                  round(100 * r["signed_offset"], 4), round(100 * r["completeness"], 4),
                  round(r["normal_error"], 2), round(r["normal_error_median"], 2), round(r["time"])]
                 for r in rows],
            )
        ],
        data={"capture": str(args.capture), "subdivide": args.subdivide, "offset": args.offset,
              "observations": args.observations, "rows": rows},
    )
    print(f"\n{args.capture}: refinement started from {start} ({rows[0]['vertices']:,} vertices)\n")
    print(
        "| variant | observations | options | accuracy (x1e-2) | signed offset (x1e-2) | completeness (x1e-2) "
        "| normal err. mean (deg) | normal err. median (deg) | time (s) |"
    )
    print("|---|---|---|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['variant']} | {r['observations']} | {r['options'] or 'defaults'} | {100 * r['accuracy']:.4f} "
            f"| {100 * r['signed_offset']:+.4f} | {100 * r['completeness']:.4f} "
            f"| {r['normal_error']:.2f} | {r['normal_error_median']:.2f} | {r['time']:.0f} |"
        )


def run(
    capture: Path,
    variants: dict[str, dict],
    *,
    subdivide: int,
    iterations: int,
    samples: int,
    offset: float = 0.0,
    observations: list[str] | tuple[str, ...] = ("decoded",),
) -> list[dict]:
    """Refine every variant from the capture's true surface (moved ``offset`` GT diagonals along its
    vertex normals); one row per variant, the unrefined start first."""
    truth = read_mesh(capture / "gt" / "mesh.ply")
    vertices, faces = truth.vertices.astype(np.float64), truth.faces.astype(np.int64)
    for _ in range(subdivide):
        step = sqrt3_subdivide(vertices, faces)
        vertices, faces = step.vertices, step.faces
    if offset:
        vertices = vertices + offset * bbox_diagonal(truth.vertices) * vertex_normals(vertices, faces)
    config = PipelineConfig()
    with open_capture(capture) as cap:
        known = [frame.camera for frame in cap.frames]
        cameras = [cam for cam in known if cam is not None]
        if len(cameras) < len(known):
            raise PmvirError(f"{capture}: every frame needs intrinsics and a pose (the true ones)")
        masks = [cap.read_mask(i) for i in range(len(cap.frames))]
        stems = [Path(frame.file).stem for frame in cap.frames]
        views = decode_views(cap, config)
    vis_opts = config.geometry.visibility
    visibility = vertex_visibility(
        vertices, faces, cameras, masks, min_cos=vis_opts.min_cos, rel_tol=vis_opts.rel_tol
    )
    visibility_fn = make_visibility_fn(cameras, masks, min_cos=vis_opts.min_cos, rel_tol=vis_opts.rel_tol)
    start = evaluate(Mesh(vertices, faces), truth, n_samples=samples)
    rows = [
        {
            "variant": "start",
            "observations": "-",
            "options": "(not refined)",
            "vertices": len(vertices),
            "accuracy": start.accuracy,
            "signed_offset": start.signed_offset,
            "completeness": start.completeness,
            "normal_error": start.normal_error,
            "normal_error_median": start.normal_error_median,
            "time": 0.0,
        }
    ]
    for kind, (name, overrides) in ((k, v) for k in observations for v in variants.items()):
        opts = RefineOptions.model_validate(
            merge_options(config.refine.model_dump(), merge_options({"solver": {"max_iterations": iterations}}, overrides))
        )
        with open_capture(capture) as cap:  # refine.demosaic may decode the frames once more
            fitted = refinement_observations(cap, views, list(range(len(views))), config.decode, opts)
        if kind != "decoded":
            fitted = noise_free(capture, stems, fitted, kind, opts.pho.intensity)
        t0 = time.perf_counter()
        refined = refine_surface(
            vertices,
            faces,
            cameras,
            fitted,
            visibility,
            options=opts,
            visibility_fn=visibility_fn,
            masks=masks,
        )
        elapsed = time.perf_counter() - t0
        ev = evaluate(Mesh(refined.vertices, faces), truth, n_samples=samples)
        rows.append(
            {
                "variant": name,
                "observations": kind,
                "options": " ".join(f"{k}={v}" for k, v in overrides.items()),
                "vertices": len(vertices),
                "accuracy": ev.accuracy,
                "signed_offset": ev.signed_offset,
                "completeness": ev.completeness,
                "normal_error": ev.normal_error,
                "normal_error_median": ev.normal_error_median,
                "time": elapsed,
            }
        )
        print(
            f"{name} ({kind}): accuracy {100 * ev.accuracy:.4f}e-2, normal error {ev.normal_error:.2f} deg, {elapsed:.0f} s",
            flush=True,
        )
    return rows


if __name__ == "__main__":
    main()
