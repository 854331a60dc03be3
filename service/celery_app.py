"""The Celery application of the worker: ``celery -A service.celery_app worker`` (``pmvir worker``).

Redis is the broker; there is no result backend (job state is the service's
own, :mod:`service.store`). The configuration and its crash-safety settings
are in :mod:`service.queue`; the task is thin and calls :mod:`service.runner`.
"""

from __future__ import annotations

import sys

from celery import signals
from celery.exceptions import TimeLimitExceeded

from service import limits
from service.observability import configure_logging
from service.queue import RUN_JOB, make_celery
from service.settings import get_settings

settings = get_settings()
app = make_celery(settings)


def _concurrency(argv: list[str]) -> int:
    """The worker's --concurrency from its command line (``pmvir worker`` passes it; default 1)."""
    for i, arg in enumerate(argv):
        if arg.startswith("--concurrency="):
            return int(arg.split("=", 1)[1])
        if arg in ("--concurrency", "-c") and i + 1 < len(argv):
            return int(argv[i + 1])
    return 1


#: Threads of each job; the pools' environment is set before numpy, torch and OpenCV load.
JOB_THREADS = limits.job_threads(settings.job_threads, _concurrency(sys.argv))
limits.set_thread_environment(JOB_THREADS)

# The library's pipeline, loaded once in the worker's main process (pool processes inherit it).
import pmvir.pipeline  # noqa: E402,F401


@app.task(name=RUN_JOB, bind=True, acks_late=True, reject_on_worker_lost=True)
def run_job(self, job_id: str) -> None:
    """Run one job's pipeline (thin: everything is in service.runner)."""
    from service.runner import run_job as run

    run(job_id, settings=settings, hostname=self.request.hostname or "", task_id=self.request.id or "")


if settings.log_format == "json":

    @signals.setup_logging.connect
    def _json_logs(**_: object) -> None:
        """JSON lines for the worker's own log (Celery's logging set-up is skipped)."""
        configure_logging("json")


@signals.worker_process_init.connect
def _bound_the_job_process(**_: object) -> None:
    """Each pool process: its job's threads and memory cap."""
    limits.apply_threads(JOB_THREADS)
    limits.apply_memory(settings.job_memory)


@signals.task_failure.connect
def _hard_time_limit(sender=None, task_id=None, exception=None, **_: object) -> None:
    """A job whose process Celery killed at the hard time limit fails now (its lease would requeue it)."""
    if isinstance(exception, TimeLimitExceeded) and task_id:
        from service.runner import fail_now

        fail_now(
            str(task_id),
            settings,
            f"hard time limit exceeded ({settings.job_hard_time_limit} s): the job's process was killed",
        )


@signals.worker_ready.connect
def _start_reaper(sender=None, **_: object) -> None:
    from service import housekeeping
    from service.runner import start_reaper

    start_reaper(settings)
    housekeeping.start(settings, name=getattr(sender, "hostname", None))


@signals.worker_shutdown.connect
def _stop_reaper(sender=None, **_: object) -> None:
    from service import housekeeping
    from service.runner import stop_reaper

    stop_reaper()
    housekeeping.stop()
