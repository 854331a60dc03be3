"""``pmvir decode CAPTURE --out DIR``: raw frames to I_int, I_min, AoP, DoP files and previews.

Writes ``DIR/<stem>.npz`` per frame (spec section 2) and PNG previews beside
it; see :mod:`pmvir.decode`. A folder of frames without capture.json is decoded
with the manifest inferred as ``pmvir init`` infers it (same options). Progress goes to stderr (tqdm), a one-line
summary to stdout.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import get_args

from pydantic import ValidationError

from pmvir.commands.init import add_inference_arguments, inference_options
from pmvir.config import DecodeOptions
from pmvir.errors import ConfigError


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    defaults = DecodeOptions()
    fields = DecodeOptions.model_fields
    p = subparsers.add_parser(
        "decode",
        help="demosaic raw frames to I_int, I_min, AoP, DoP (.npz) and PNG previews",
        description="Decode the frames of a capture (folder, .zip or capture.json): for each frame "
        "write DIR/<stem>.npz with i_int, i_min (H, W, 3 float32, linear normalized units), aop "
        "(radians in [0, pi), ccw from image +x toward image up), dop ([0, 1]) and valid (bool), "
        "plus <stem>_int.png, _min.png (auto-exposed sRGB), _dop.png (grey) and _aop.png "
        "(hue = AoP, saturation = DoP / 0.5).",
    )
    p.add_argument("capture", metavar="CAPTURE", type=Path, help="capture folder, .zip or capture.json")
    p.add_argument("--out", required=True, type=Path, metavar="DIR", help="output folder (created)")
    p.add_argument(
        "--frames",
        nargs="+",
        metavar="FRAME",
        help="frames to decode, by file stem (e.g. 003) or 0-based index; default: all",
    )
    p.add_argument(
        "--demosaic",
        choices=list(get_args(DecodeOptions.model_fields["demosaic"].annotation)),
        default=defaults.demosaic,
        help=f"{fields['demosaic'].description} (default {defaults.demosaic})",
    )
    p.add_argument(
        "--noise-floor",
        type=float,
        default=defaults.noise_floor,
        metavar="X",
        help=f"{fields['noise_floor'].description} (default {defaults.noise_floor})",
    )
    add_inference_arguments(p)
    p.add_argument("--compress", action="store_true", help="zlib-compress the .npz files (slower)")
    p.add_argument("--no-previews", action="store_true", help="write only the .npz files")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pmvir.capture import open_capture
    from pmvir.commands.bar import progress_bar
    from pmvir.decode import decode_capture

    try:
        options = DecodeOptions(demosaic=args.demosaic, noise_floor=args.noise_floor)
    except ValidationError as exc:
        problems = "; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in exc.errors())
        raise ConfigError(f"invalid decode options: {problems}") from None

    with open_capture(args.capture, infer=inference_options(args)) as cap, progress_bar(
        "decode", quiet=args.quiet
    ) as progress:
        written = decode_capture(
            cap,
            args.out,
            options=options,
            frames=args.frames,
            previews=not args.no_previews,
            compress=args.compress,
            progress=progress,
        )
    print(f"decoded {len(written)} frame(s) to {args.out}")
    return 0
