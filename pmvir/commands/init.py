"""``pmvir init DIR``: write the capture.json inferred from a folder of frames, for editing.

The manifest is inferred as ``pmvir reconstruct DIR`` infers it
(:mod:`pmvir.io.inference`: frame size and bit depth from the files, layout,
black level, EXIF intrinsics) and written to ``DIR/capture.json``; each inferred
value is printed with what it came from. An existing capture.json is kept
unless ``--force`` is given. :func:`add_inference_arguments` and
:func:`inference_options` are the options both commands share.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from pmvir.errors import ConfigError
from pmvir.io.inference import LAYOUTS, InferOptions, parse_frame_size


def add_inference_arguments(p: argparse.ArgumentParser) -> None:
    """--layout, --black-level and --frame-size: what a folder of frames cannot say about itself."""
    p.add_argument(
        "--layout",
        choices=LAYOUTS,
        default=None,
        help=f"sensor mosaic layout of a folder of frames without capture.json (default {LAYOUTS[0]})",
    )
    p.add_argument(
        "--black-level",
        type=float,
        default=None,
        metavar="DN",
        help="black level in raw sample units (>= 0), subtracted first; default: the DNG's, else 0",
    )
    p.add_argument(
        "--frame-size",
        default=None,
        metavar="WxH",
        help="width x height in pixels of headerless .raw/.bin frames, e.g. 2448x2048",
    )


def inference_options(args: argparse.Namespace) -> InferOptions | None:
    """The InferOptions the flags give, or None when none was given."""
    if args.layout is None and args.black_level is None and args.frame_size is None:
        return None
    return InferOptions(
        layout=args.layout or LAYOUTS[0],
        black_level=args.black_level,
        frame_size=None if args.frame_size is None else parse_frame_size(args.frame_size),
    )


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "init",
        help="infer capture.json for a folder of frames and write it there for editing",
        description="Infer the manifest of a folder of frames (PNG, TIFF, DNG, or headerless with "
        "--frame-size): frame size and bit depth from the files, the layout, the black level, EXIF "
        "intrinsics where present (else SfM estimates them) and no poses (SfM estimates them). "
        "Writes DIR/capture.json and prints what was inferred.",
    )
    p.add_argument("folder", metavar="DIR", type=Path, help="folder holding the frames (directly or in frames/)")
    add_inference_arguments(p)
    p.add_argument("--force", action="store_true", help="replace an existing DIR/capture.json")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pmvir.io.inference import infer_manifest
    from pmvir.io.manifest import MANIFEST_NAME, write_capture_manifest

    folder: Path = args.folder
    if not folder.is_dir():
        raise ConfigError(f"{folder}: not a folder")
    target = folder / MANIFEST_NAME
    if target.exists() and not args.force:
        raise ConfigError(f"{target} exists; --force replaces it")
    inferred = infer_manifest(folder, inference_options(args))
    write_capture_manifest(folder, inferred.manifest)
    for note in inferred.notes:
        print(f"  {note}", file=sys.stderr)
    print(f"wrote {target}")
    return 0
