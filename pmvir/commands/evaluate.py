"""``pmvir evaluate RESULT_DIR|MESH --gt CAPTURE/gt``: metrics against ground truth (spec section 5).

One JSON object goes to stdout (and to ``--out FILE`` when asked), a
human-readable table to stderr.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from pmvir.evaluate import N_GT_SAMPLES, EvaluationResult, evaluate_paths


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "evaluate",
        help="accuracy, completeness, normal, albedo and lighting errors against ground truth",
        description="Compare a result folder (mesh.ply, illumination.json, poses/) or a bare mesh file "
        "with a synthetic capture's ground truth. Distances are in units of the ground-truth "
        "bounding-box diagonal. Prints one JSON object on stdout and a table on stderr.",
    )
    p.add_argument("estimate", metavar="RESULT_DIR|MESH", type=Path, help="result folder or .ply/.obj mesh")
    p.add_argument(
        "--gt",
        required=True,
        type=Path,
        metavar="CAPTURE/gt",
        help="ground-truth folder: mesh.ply (with albedo), optional illumination.json; "
        "its parent holds capture.json (true poses, for --align)",
    )
    p.add_argument("--out", type=Path, metavar="FILE", help="also write the JSON object to FILE")
    p.add_argument(
        "--align",
        action="store_true",
        help="fit a similarity (Umeyama, with scale) from the estimated camera centres "
        "(RESULT_DIR/poses/images.txt) to the true ones and apply it before measuring",
    )
    p.add_argument(
        "--icp",
        action="store_true",
        help="with --align: refine the similarity by ICP against the true surface (pairs within 1 %% of "
        "the diagonal), to measure the surface apart from the camera fit's error",
    )
    p.add_argument(
        "--samples",
        type=int,
        default=N_GT_SAMPLES,
        metavar="N",
        help=f"ground-truth surface samples for completeness (default {N_GT_SAMPLES:,})",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="sampling seed (default 0)")
    p.set_defaults(func=run)


def _fmt(x: float | None, spec: str = ".6g") -> str:
    return "n/a" if x is None else format(x, spec)


def format_table(result: EvaluationResult) -> str:
    """The human-readable summary printed on stderr."""
    r = result
    rows = [
        (
            "accuracy (mean / median / p90)",
            f"{_fmt(r.accuracy)} / {_fmt(r.accuracy_median)} / {_fmt(r.accuracy_p90)}",
        ),
        (
            "completeness (mean / median / p90)",
            f"{_fmt(r.completeness)} / {_fmt(r.completeness_median)} / {_fmt(r.completeness_p90)}",
        ),
        (
            "normal error, degrees (mean / median)",
            f"{_fmt(r.normal_error, '.3f')} / {_fmt(r.normal_error_median, '.3f')}",
        ),
        (
            "signed offset (mean / median; < 0: inside)",
            f"{_fmt(r.signed_offset)} / {_fmt(r.signed_offset_median)}",
        ),
        ("albedo RMSE (scale-corrected)", _fmt(r.albedo_rmse)),
        ("illumination error (relative)", _fmt(r.illumination_error)),
        ("estimated vertices", f"{r.n_vertices:,}"),
        ("ground-truth samples", f"{r.n_gt_samples:,}"),
        ("GT bbox diagonal (world units)", f"{r.gt_diagonal:.6g}"),
    ]
    if r.albedo_scale is not None:
        rows.append(("albedo scale (R, G, B)", ", ".join(f"{s:.4g}" for s in r.albedo_scale)))
    rows.append(("aligned", "yes" if r.aligned else "no"))
    if r.aligned and r.alignment is not None:
        rows.append(("alignment RMSE (camera centres)", _fmt(r.alignment_rmse)))
        rows.append(("alignment scale", f"{r.alignment['scale']:.6g}"))
        if r.alignment_refine_shift is not None:
            rows.append(("alignment refined on the surface: largest move", _fmt(r.alignment_refine_shift)))
    for name, err in r.illumination_per_frame.items():
        rows.append((f"  illumination {name}", _fmt(err)))
    width = max(len(k) for k, _ in rows)
    lines = ["metric".ljust(width) + "  value", "-" * (width + 24)]
    lines += [k.ljust(width) + "  " + v for k, v in rows]
    lines.append("(distances in units of the ground-truth bounding-box diagonal)")
    lines += [f"note: {n}" for n in r.notes]
    return "\n".join(lines)


def run(args: argparse.Namespace) -> int:
    result = evaluate_paths(
        args.estimate, args.gt, align=args.align, icp=args.icp, n_samples=args.samples, seed=args.seed
    )
    text = json.dumps(result.to_dict(), indent=2)
    if args.out is not None:
        args.out.parent.mkdir(parents=True, exist_ok=True)
        tmp = args.out.with_name(args.out.name + ".tmp")
        tmp.write_text(text + "\n")
        os.replace(tmp, args.out)
    print(format_table(result), file=sys.stderr)
    print(text)
    return 0
