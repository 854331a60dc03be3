"""How many threads a run's own parallel work may use.

The service caps every job at ``PMVIR_JOB_THREADS`` threads by setting ``OMP_NUM_THREADS`` (and
the other pools' variables, :mod:`service.limits`); outside the service the cores this process
may use.
"""

from __future__ import annotations

import os


def configured_threads() -> int | None:
    """``OMP_NUM_THREADS`` when it holds a positive integer, else None."""
    value = os.environ.get("OMP_NUM_THREADS", "").strip()
    return int(value) if value.isdigit() and int(value) > 0 else None


def usable_threads() -> int:
    """:func:`configured_threads`, else the cores this process may use (its CPU affinity)."""
    configured = configured_threads()
    if configured is not None:
        return configured
    try:
        return max(len(os.sched_getaffinity(0)), 1)
    except (AttributeError, OSError):  # no affinity on this platform
        return os.cpu_count() or 1
