"""``pmvir synth (--mesh MESH | --shape NAME) --out CAPTURE [options]``: render a synthetic capture.

Writes a capture that follows shared/spec/capture-format.md (raw IMX250MYR
12-bit mosaics, capture.json with intrinsics and poses, masks) plus ground truth
under gt/; see :mod:`pmvir.synth.generate`. Every option is a field of
:class:`pmvir.synth.options.SynthOptions` (defaults and meanings come from there).
Progress goes to stderr, a one-line summary to stdout.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

from pmvir.synth.options import SynthOptions
from pmvir.synth.shapes import SHAPES

#: (flag, field, argparse keywords) for every option; defaults are shown from SynthOptions.
_FLAGS: tuple[tuple[str, str, dict[str, Any]], ...] = (
    ("--views", "views", {"type": int, "metavar": "N"}),
    ("--size", "size", {"metavar": "WxH"}),
    ("--material", "material", {"choices": ["lambert", "plastic", "conductor"]}),
    ("--lighting", "lighting", {"choices": ["sh", "envmap"]}),
    ("--texture", "texture", {"choices": ["procedural", "uniform"]}),
    ("--noise", "noise", {"type": float, "metavar": "SIGMA"}),
    ("--seed", "seed", {"type": int, "metavar": "S"}),
    ("--renderer", "renderer", {"choices": ["builtin", "mitsuba"]}),
    ("--ior", "ior", {"type": float, "metavar": "N"}),
    ("--extinction", "extinction", {"type": float, "metavar": "K"}),
    ("--specular", "specular", {"type": float, "metavar": "X"}),
    ("--full-well", "full_well", {"type": float, "metavar": "E"}),
    ("--black-level", "black_level", {"type": int, "metavar": "DN"}),
    ("--exposure", "exposure", {"type": float, "metavar": "GAIN"}),
    ("--supersample", "supersample", {"type": int, "metavar": "N"}),
    ("--aop-frame", "aop_frame", {"choices": ["ray", "normal"]}),
    ("--spp", "spp", {"type": int, "metavar": "N"}),
    ("--max-depth", "max_depth", {"type": int, "metavar": "N"}),
    ("--roughness", "roughness", {"type": float, "metavar": "R"}),
    ("--mesh-up", "mesh_up", {"choices": ["x", "y", "z"]}),
    ("--focal-factor", "focal_factor", {"type": float, "metavar": "F"}),
    ("--rig", "rig", {"choices": ["rings", "turntable"]}),
    ("--scene", "scene", {"choices": ["object", "table", "turntable"]}),
)


def _default_text(field: str) -> str:
    value = SynthOptions.model_fields[field].default
    if field == "size":
        return f"{value[0]}x{value[1]}"
    return "auto" if value is None else str(value)


def add_parser(subparsers: argparse._SubParsersAction) -> None:
    p = subparsers.add_parser(
        "synth",
        help="render a synthetic polarization capture with ground truth",
        description="Render a synthetic capture of a mesh (PLY/OBJ, normalized to bounding-box diagonal 1) "
        "or a built-in shape: raw IMX250MYR 12-bit mosaics with shot and read noise, capture.json with "
        "intrinsics and cam_from_world poses, masks, and gt/ (mesh.ply with the true albedo, "
        "illumination.json with the true per-view lighting, views/<stem>.npz with depth, normals and "
        "noise-free AoP/DoP/I_int).",
    )
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--mesh", type=Path, metavar="MESH", help="PLY or OBJ mesh file")
    src.add_argument("--shape", metavar="NAME", help=f"built-in shape: {', '.join(SHAPES)}")
    p.add_argument("--out", required=True, type=Path, metavar="CAPTURE", help="capture folder to create")
    fields = SynthOptions.model_fields
    for flag, field, kwargs in _FLAGS:
        text = f"{fields[field].description} (default {_default_text(field)})".replace("%", "%%")
        p.add_argument(flag, dest=field, default=None, help=text, **kwargs)
    p.add_argument(
        "--no-gt-views",
        dest="gt_views",
        action="store_false",
        default=None,
        help="do not write gt/views/<stem>.npz",
    )
    p.add_argument(
        "--no-masks",
        dest="masks",
        action="store_false",
        default=None,
        help="write no masks/ (the true object masks go to gt/masks/)",
    )
    p.add_argument(
        "--save-stokes",
        dest="save_stokes",
        action="store_true",
        default=None,
        help="also store the noise-free per-pixel Stokes image (s0, s1, s2 per colour) as 'stokes' "
        "in gt/views/<stem>.npz",
    )
    p.add_argument("--force", action="store_true", help="replace the capture files in a non-empty CAPTURE")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from pmvir.synth.generate import ViewDone, synthesize

    options = {field: getattr(args, field) for _, field, _ in _FLAGS if getattr(args, field) is not None}
    if args.gt_views is not None:
        options["gt_views"] = args.gt_views
    if args.masks is not None:
        options["masks"] = args.masks
    if args.save_stokes is not None:
        options["save_stokes"] = args.save_stokes
    bars: list[Any] = []

    def progress(v: ViewDone) -> None:
        if args.quiet:
            return
        if not bars:
            from tqdm import tqdm

            bars.append(tqdm(total=v.total, unit="view", file=sys.stderr, desc="synth"))
        bars[0].update(1)

    t0 = time.perf_counter()
    try:
        out = synthesize(
            args.out, mesh=args.mesh, shape=args.shape, overwrite=args.force, progress=progress, **options
        )
    finally:
        for bar in bars:
            bar.close()
    n = options.get("views", SynthOptions.model_fields["views"].default)
    print(f"wrote {out} ({n} views) in {time.perf_counter() - t0:.1f} s")
    return 0
