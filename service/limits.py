"""Bounds of one job in a worker process: its threads and its memory.

A worker runs ``concurrency`` jobs at once, each in its own pool process. Each
job gets ``PMVIR_JOB_THREADS`` threads (default: the cores this process may use,
from its CPU affinity and its cgroup's ``cpu.max`` quota, divided by the
concurrency), set for OpenMP, BLAS (threadpoolctl), torch and OpenCV, so two
jobs on one host do not oversubscribe it. ``PMVIR_JOB_MEMORY`` caps the pool
process's address space (``RLIMIT_AS``): an allocation past it raises
``MemoryError`` (torch and OpenCV raise their own "cannot allocate" errors),
which :func:`out_of_memory` recognises so the job fails at once with that reason.
"""

from __future__ import annotations

import logging
import math
import os
import resource
from pathlib import Path

log = logging.getLogger("pmvir.worker")

#: Environment variables the thread pools read when they start (set before the libraries load them).
THREAD_VARIABLES = (
    "OMP_NUM_THREADS",
    "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS",
    "BLIS_NUM_THREADS",
    "VECLIB_MAXIMUM_THREADS",
    "NUMEXPR_NUM_THREADS",
)

_OOM_MESSAGES = ("can't allocate memory", "cannot allocate memory", "insufficient memory", "out of memory")


def allowed_cores(cgroup_root: Path = Path("/sys/fs/cgroup")) -> int:
    """Cores this process may use: its CPU affinity, lowered to its cgroup v2 ``cpu.max`` quota."""
    try:
        cores = len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        cores = os.cpu_count() or 1
    try:
        quota, period = (cgroup_root / "cpu.max").read_text().split()[:2]
        if quota != "max":
            cores = min(cores, max(1, math.floor(int(quota) / int(period))))
    except (OSError, ValueError):
        pass
    return max(cores, 1)


def job_threads(configured: int, concurrency: int) -> int:
    """Threads of one job: ``configured`` when set, else the allowed cores split between the jobs.

    >>> job_threads(3, 4)
    3
    """
    if configured > 0:
        return configured
    return max(1, allowed_cores() // max(concurrency, 1))


def set_thread_environment(threads: int) -> None:
    """Set the pools' environment variables (inherited by the pool processes forked afterwards)."""
    for name in THREAD_VARIABLES:
        os.environ[name] = str(threads)
    os.environ["PMVIR_JOB_THREADS_APPLIED"] = str(threads)


def apply_threads(threads: int) -> dict[str, int]:
    """Bound every thread pool of this process to ``threads``; returns what each library reports."""
    set_thread_environment(threads)
    seen: dict[str, int] = {}
    try:
        from threadpoolctl import threadpool_limits

        threadpool_limits(limits=threads)
        seen["blas_openmp"] = threads
    except ImportError:
        pass
    try:
        import torch

        torch.set_num_threads(threads)
        seen["torch"] = torch.get_num_threads()
    except ImportError:
        pass
    try:
        import cv2

        cv2.setNumThreads(threads)
        seen["opencv"] = cv2.getNumThreads()
    except ImportError:
        pass
    return seen


def apply_memory(limit: int) -> None:
    """Cap this process's address space at ``limit`` bytes (0: leave it as it is)."""
    if limit <= 0:
        return
    _, hard = resource.getrlimit(resource.RLIMIT_AS)
    if hard != resource.RLIM_INFINITY:
        limit = min(limit, hard)
    resource.setrlimit(resource.RLIMIT_AS, (limit, hard))


def out_of_memory(exc: BaseException) -> bool:
    """Whether ``exc`` says an allocation failed (Python, numpy, torch or OpenCV)."""
    if isinstance(exc, MemoryError):
        return True
    allocator = isinstance(exc, RuntimeError | OSError) or type(exc).__name__ == "error"  # cv2.error
    return allocator and any(m in str(exc).lower() for m in _OOM_MESSAGES)
