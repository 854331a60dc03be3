"""The Celery application of the worker: ``celery -A service.celery_app worker`` (``pmvir worker``).

Redis is the broker; there is no result backend (job state is the service's
own, :mod:`service.store`). The configuration and its crash-safety settings
are in :mod:`service.queue`; the task is thin and calls :mod:`service.runner`.
"""

from __future__ import annotations

from celery import signals

from service.queue import RUN_JOB, make_celery
from service.settings import get_settings

settings = get_settings()
app = make_celery(settings)

# The library's pipeline, loaded once in the worker's main process (pool processes inherit it).
import pmvir.pipeline  # noqa: E402,F401


@app.task(name=RUN_JOB, bind=True, acks_late=True, reject_on_worker_lost=True)
def run_job(self, job_id: str) -> None:
    """Run one job's pipeline (thin: everything is in service.runner)."""
    from service.runner import run_job as run

    run(job_id, settings=settings, hostname=self.request.hostname or "")


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
