"""The ``pmvir`` command.

Each sub-command lives in ``pmvir/commands/<name>.py`` and exposes
``add_parser(subparsers)`` (which sets ``func``). Library errors become a one-line
message on stderr and exit status 2; nothing here prints a traceback for them.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from pmvir import __version__
from pmvir.errors import PmvirError

#: Sub-command modules under pmvir.commands, in the order ``--help`` lists them.
COMMANDS: tuple[str, ...] = ("decode", "evaluate", "reconstruct", "synth", "serve", "worker", "submit")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pmvir",
        description="Polarimetric multi-view inverse rendering: raw colour-polarization "
        "captures to a refined mesh with albedo and per-image lighting.",
    )
    parser.add_argument("--version", action="version", version=f"pmvir {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        importlib.import_module(f"pmvir.commands.{name}").add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 1
    try:
        return int(args.func(args) or 0)
    except PmvirError as exc:
        print(f"pmvir {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"pmvir {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
