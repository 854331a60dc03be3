"""``pmvir reconstruct CAPTURE --out DIR``: capture to result folder (spec section 3).

Options: see :mod:`pmvir.commands.options` (shared with ``pmvir submit``). A folder
of frames without capture.json is a capture whose manifest is inferred
(``--layout``, ``--black-level``, ``--frame-size`` as for ``pmvir init``); the
manifest used is written into the result as capture.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pmvir.commands.bar import progress_bar
from pmvir.commands.init import add_inference_arguments, inference_options
from pmvir.commands.options import add_option_arguments, build_config
from pmvir.errors import ConfigError


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "reconstruct",
        help="run the pipeline on a capture and write the result folder",
        description="Capture to result: decode, geometry (poses, dense stereo, initial surface, "
        "subdivision) and polarimetric refinement. Writes mesh.ply, initial.ply, illumination.json, "
        "report.json, capture.json and poses/ into DIR. A folder (or .zip) of frames without capture.json "
        "is a capture: its manifest is inferred as pmvir init infers it.",
    )
    p.add_argument(
        "capture", type=Path, help="capture folder (or a folder of frames), its capture.json, or a .zip"
    )
    p.add_argument("--out", type=Path, required=True, help="result folder (created)")
    add_option_arguments(p)
    add_inference_arguments(p)
    p.add_argument(
        "--max-memory",
        metavar="SIZE",
        help="memory limit of the run, e.g. 12G (K, M, G, T: powers of 1024); a capture estimated to need "
        "more fails before decoding, naming what fits (default: PMVIR_JOB_MEMORY, else none)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pmvir.capture import MANIFEST_NAME, open_capture
    from pmvir.memory import parse_bytes
    from pmvir.pipeline import run as run_pipeline

    config = build_config(args)
    max_memory = None if args.max_memory is None else parse_bytes(args.max_memory)
    infer = inference_options(args)
    with open_capture(args.capture, infer=infer) as cap:
        if infer is not None and cap.inferred is None:
            raise ConfigError(
                f"{args.capture}: --layout, --black-level and --frame-size apply to a folder of frames "
                f"without {MANIFEST_NAME}; this capture has one (edit it instead)"
            )
        if cap.inferred is not None:
            print(f"{args.capture}: no {MANIFEST_NAME}; inferred:", file=sys.stderr)
            for note in cap.inferred:
                print(f"  {note}", file=sys.stderr)
        with progress_bar("reconstruct", quiet=args.quiet) as progress:
            result = run_pipeline(config, cap, args.out, progress=progress, max_memory=max_memory)
    timings = ", ".join(f"{k} {v:.1f} s" for k, v in result.timings.items())
    print(f"{result.out}: {', '.join(result.stages_run)} ({timings})", file=sys.stderr)
    for warning in result.warnings:
        print(f"pmvir: warning: {warning}", file=sys.stderr)
    return 0
