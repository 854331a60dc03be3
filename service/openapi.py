"""The committed OpenAPI document: ``python -m service.openapi --write`` regenerates it.

``openapi/openapi.json`` is generated from the app (never edited by hand); a
test fails when it drifts from what the app serves, e.g. after a change to the
routes, the models, or the pipeline options (:mod:`pmvir.config`) that job
requests carry. ``--check`` exits 1 when the file is stale.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

DOCUMENT = Path(__file__).resolve().parents[1] / "openapi" / "openapi.json"


def generate() -> dict[str, Any]:
    """The OpenAPI document of the app (independent of the runtime settings)."""
    import logging

    from service.app import create_app
    from service.settings import Settings

    quiet = logging.getLogger("pmvir.service")
    level = quiet.level
    quiet.setLevel(logging.ERROR)  # no "no API keys" warning for an app that is never served
    try:
        return create_app(Settings(api_keys=())).openapi()
    finally:
        quiet.setLevel(level)


def render(doc: dict[str, Any]) -> str:
    return json.dumps(doc, indent=2, ensure_ascii=False) + "\n"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m service.openapi", description=__doc__.splitlines()[0])
    g = p.add_mutually_exclusive_group()
    g.add_argument("--write", action="store_true", help=f"write {DOCUMENT}")
    g.add_argument("--check", action="store_true", help="exit 1 when the committed document is stale")
    args = p.parse_args(argv)
    text = render(generate())
    if args.write:
        DOCUMENT.parent.mkdir(parents=True, exist_ok=True)
        DOCUMENT.write_text(text)
        print(f"wrote {DOCUMENT}")
        return 0
    if args.check:
        current = DOCUMENT.read_text() if DOCUMENT.exists() else ""
        if current != text:
            print(f"{DOCUMENT} is stale: run python -m service.openapi --write", file=sys.stderr)
            return 1
        return 0
    sys.stdout.write(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
