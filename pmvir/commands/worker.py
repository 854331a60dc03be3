"""``pmvir worker``: a Celery worker of the capture-processing service.

It runs ``celery -A service.celery_app worker`` in place of this process
(signals then reach Celery directly: SIGTERM finishes the running job's
acknowledgement cleanly, a second one stops at once). Configuration comes from
the ``PMVIR_*`` environment variables (README, "Service").
"""

from __future__ import annotations

import argparse
import os
import sys

from pmvir.errors import ConfigError

CELERY_APP = "service.celery_app"


def add_parser(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "worker",
        help="run a worker of the capture-processing service (Celery)",
        description="Take jobs from the Redis queue and run the pipeline on them. One job per process "
        "at a time; run more workers (or --concurrency N) for more jobs at once.",
    )
    p.add_argument("--concurrency", type=int, default=1, help="jobs at once (pool processes, default 1)")
    p.add_argument(
        "--pool",
        default="prefork",
        choices=("prefork", "solo"),
        help="prefork (default: time limits enforced, a crashed job does not take the worker "
        "down) or solo (in-process, no hard time limit)",
    )
    p.add_argument("--loglevel", default="INFO", choices=("DEBUG", "INFO", "WARNING", "ERROR"))
    p.add_argument("--hostname", default=None, help="worker name (Celery -n), default pmvir@<host>")
    p.add_argument("--queue", default=None, help="queue to consume (default PMVIR_QUEUE or 'pmvir')")
    p.set_defaults(func=run)


def celery_argv(args: argparse.Namespace) -> list[str]:
    """The celery command line this command runs."""
    if args.concurrency < 1:
        raise ConfigError(f"--concurrency must be at least 1, got {args.concurrency}")
    queue = args.queue or os.environ.get("PMVIR_QUEUE", "pmvir")
    return [
        sys.executable,
        "-m",
        "celery",
        "-A",
        CELERY_APP,
        "worker",
        f"--pool={args.pool}",
        f"--concurrency={args.concurrency}",
        "-Q",
        queue,
        "-n",
        args.hostname or "pmvir@%h",
        f"--loglevel={args.loglevel}",
        "--without-gossip",
        "--without-mingle",
    ]


def run(args: argparse.Namespace) -> int:
    try:
        import celery  # noqa: F401
    except ImportError as exc:
        raise ConfigError("pmvir worker needs the service extras: pip install 'pmvir[service]'") from exc
    argv = celery_argv(args)
    sys.stdout.flush()
    sys.stderr.flush()
    os.execv(argv[0], argv)
    return 0  # not reached
