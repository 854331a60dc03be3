"""``pmvir reconstruct CAPTURE --out DIR``: capture to result folder (spec section 3).

Options: see :mod:`pmvir.commands.options` (shared with ``pmvir submit``).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pmvir.commands.bar import progress_bar
from pmvir.commands.options import add_option_arguments, build_config


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="run the pipeline on a capture and write the result folder",
        description="Capture to result: decode, geometry (poses, dense stereo, initial surface, "
        "subdivision) and polarimetric refinement. Writes mesh.ply, initial.ply, illumination.json, "
        "report.json and poses/ into DIR.",
    )
    p.add_argument("capture", type=Path, help="capture folder, its capture.json, or a .zip")
    p.add_argument("--out", type=Path, required=True, help="result folder (created)")
    add_option_arguments(p)
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pmvir.pipeline import run as run_pipeline

    config = build_config(args)
    with progress_bar("reconstruct", quiet=args.quiet) as progress:
        result = run_pipeline(config, args.capture, args.out, progress=progress)
    timings = ", ".join(f"{k} {v:.1f} s" for k, v in result.timings.items())
    print(f"{result.out}: {', '.join(result.stages_run)} ({timings})", file=sys.stderr)
    for warning in result.warnings:
        print(f"pmvir: warning: {warning}", file=sys.stderr)
    return 0
