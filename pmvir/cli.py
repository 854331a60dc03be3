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
COMMANDS: tuple[str, ...] = (
    "init", "decode", "evaluate", "reconstruct", "options", "synth", "serve", "worker", "submit", "remote",
)
#: The extra each module's commands need (``pip install 'pmvir[<extra>]'``).
EXTRAS: dict[str, str] = {
    "init": "full",
    "decode": "full",
    "evaluate": "full",
    "reconstruct": "full",
    "options": "client",
    "synth": "full",
    "serve": "service",
    "worker": "service",
    "submit": "client",
    "remote": "client",
}


def _missing_extra(module: str, exc: ModuleNotFoundError) -> str:
    extra = EXTRAS.get(module, "full")
    return f"needs the Python package {exc.name!r}: install the extra with pip install 'pmvir[{extra}]'"


def _add_unavailable(sub: argparse._SubParsersAction, module: str, exc: ModuleNotFoundError) -> None:
    """A command whose module cannot be imported here: it says which extra to install."""
    why = _missing_extra(module, exc)
    p = sub.add_parser(module, help=f"(unavailable: {why})", add_help=False)
    p.add_argument("rest", nargs=argparse.REMAINDER)

    def run(args: argparse.Namespace) -> int:
        print(f"pmvir {module}: {why}", file=sys.stderr)
        return 2

    p.set_defaults(func=run)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="pmvir",
        description="Polarimetric multi-view inverse rendering: raw colour-polarization "
        "captures to a refined mesh with albedo and per-image lighting.",
    )
    parser.add_argument("--version", action="version", version=f"pmvir {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"pmvir.commands.{name}")
        except ModuleNotFoundError as exc:  # an extra is not installed
            _add_unavailable(sub, name, exc)
            continue
        module.add_parser(sub)
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
    except ModuleNotFoundError as exc:  # a command that imports its heavy dependencies when run
        module = next((m for m in COMMANDS if args.func.__module__.endswith(f".{m}")), args.command)
        print(f"pmvir {args.command}: {_missing_extra(module, exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"pmvir {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
