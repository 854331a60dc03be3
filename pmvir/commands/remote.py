"""The service's jobs from the command line: ``pmvir jobs | status | log | download | cancel | rerun | info``.

Every command talks to a running service (``--server``, default ``$PMVIR_SERVER``)
with an API key (``--api-key``, default ``$PMVIR_API_KEY``) through
:class:`pmvir.client.PmvirClient`; they need only the ``client`` extra
(httpx, pydantic, tqdm). JSON answers are printed as JSON on stdout, so
they can be piped to ``jq``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path
from typing import Any

from pmvir.errors import ConfigError

#: (command, help) of each sub-command this module adds.
COMMANDS = (
    ("jobs", "list your jobs on the service, newest first"),
    ("status", "show a job (status, stage, progress, timings, files, results)"),
    ("log", "print a job's log"),
    ("download", "download a result file of a job"),
    ("cancel", "cancel a job"),
    ("rerun", "rerun a finished job with changed options, from a stage on (no re-upload)"),
    ("info", "the service's version, limits, queue, workers and disk use"),
)


def add_connection_arguments(p: argparse.ArgumentParser) -> None:
    """--server and --api-key (defaults from $PMVIR_SERVER and $PMVIR_API_KEY)."""
    p.add_argument("--server", default=None, help="service base URL (default: $PMVIR_SERVER)")
    p.add_argument("--api-key", default=None, help="API key (default: $PMVIR_API_KEY)")
    p.add_argument("--retries", type=int, default=5, help="retries per request (default 5)")


def connect(args: argparse.Namespace) -> Any:
    """A :class:`~pmvir.client.PmvirClient` from --server / --api-key or the environment."""
    from pmvir.client import PmvirClient

    server = args.server or os.environ.get("PMVIR_SERVER")
    key = args.api_key or os.environ.get("PMVIR_API_KEY")
    if not server:
        raise ConfigError("no server: pass --server or set PMVIR_SERVER")
    if not key:
        raise ConfigError("no API key: pass --api-key or set PMVIR_API_KEY")
    return PmvirClient(server, key, retries=args.retries)


def add_parser(sub: argparse._SubParsersAction) -> None:
    parsers = {name: sub.add_parser(name, help=text, description=text) for name, text in COMMANDS}
    for name, p in parsers.items():
        add_connection_arguments(p)
        if name not in ("jobs", "info"):
            p.add_argument("job", help="the job id")
        p.set_defaults(func=_RUN[name])
    parsers["jobs"].add_argument("--limit", type=int, default=50, help="most jobs to list (default 50)")
    parsers["jobs"].add_argument("--offset", type=int, default=0, help="skip this many (default 0)")
    parsers["log"].add_argument("--since", type=int, default=0, help="first line index (default 0)")
    d = parsers["download"]
    d.add_argument("name", nargs="?", default="result.zip", help="result file (default result.zip)")
    d.add_argument("--out", type=Path, default=None, help="where to write it (default: ./<name>)")
    r = parsers["rerun"]
    r.add_argument(
        "--from",
        dest="from_stage",
        default="refine",
        choices=("decode", "geometry", "refine"),
        help="first stage to compute; earlier ones come from the source job's cache (default refine)",
    )
    r.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="change one option, e.g. --set refine.solver.max_iterations=40 (VALUE is JSON, or a bare string)",
    )
    r.add_argument("--label", default=None, help="label of the new job (default: the source's)")
    r.add_argument("--wait", action="store_true", help="wait for the new job to finish")


def _print(doc: Any) -> None:
    json.dump(doc, sys.stdout, indent=1)
    sys.stdout.write("\n")


def _jobs(args: argparse.Namespace) -> int:
    with connect(args) as c:
        _print(c.jobs(offset=args.offset, limit=args.limit))
    return 0


def _status(args: argparse.Namespace) -> int:
    with connect(args) as c:
        _print(c.job(args.job))
    return 0


def _log(args: argparse.Namespace) -> int:
    with connect(args) as c:
        since = args.since
        while True:
            page = c.log(args.job, since=since)
            for line in page["lines"]:
                print(f"{line['time']}  {line['message']}")
            if page["next"] >= page["total"] or not page["lines"]:
                return 0
            since = page["next"]


def _download(args: argparse.Namespace) -> int:
    out = args.out or Path(args.name)
    with connect(args) as c:
        print(c.download(args.job, args.name, out))
    return 0


def _cancel(args: argparse.Namespace) -> int:
    with connect(args) as c:
        _print(c.cancel(args.job))
    return 0


def _rerun(args: argparse.Namespace) -> int:
    from pmvir.commands.options import parse_overrides

    changes = parse_overrides(args.overrides)
    with connect(args) as c:
        job = c.rerun(args.job, changes, from_stage=args.from_stage, label=args.label)
        print(f"pmvir rerun: job {job['id']} (from {args.from_stage})", file=sys.stderr)
        if args.wait:
            job = c.wait(job["id"])
        _print(job)
    return 0 if not args.wait or job["status"] == "succeeded" else 1


def _info(args: argparse.Namespace) -> int:
    with connect(args) as c:
        _print(c.info())
    return 0


_RUN = {
    "jobs": _jobs,
    "status": _status,
    "log": _log,
    "download": _download,
    "cancel": _cancel,
    "rerun": _rerun,
    "info": _info,
}
