"""Celery configuration shared by the worker (:mod:`service.celery_app`) and the API (to send jobs).

Crash safety:

* ``task_acks_late`` + ``task_reject_on_worker_lost``: a job's message is
  acknowledged only after the job ends, and a pool process that dies mid-job
  puts it back on the queue.
* ``worker_prefetch_multiplier = 1``: a worker holds one job message at a time.
* ``visibility_timeout`` (Redis transport) longer than the hard time limit, so
  Redis never hands a running job to a second worker.
* soft and hard time limits per job.
* Beyond Celery: a running job holds a heartbeat lease in Redis; every worker
  requeues running jobs whose lease lapsed (their worker was killed), and a
  delivery counter fails a job that keeps killing its worker (:mod:`service.runner`).
"""

from __future__ import annotations

from celery import Celery

from service.settings import Settings

#: The task's registered name (the API sends it by name; it never imports the task).
RUN_JOB = "pmvir.run_job"


def make_celery(settings: Settings) -> Celery:
    """A Celery app configured from ``settings`` (used by the worker, and by the API to send jobs)."""
    app = Celery("pmvir", broker=settings.redis_url, set_as_current=False)
    app.conf.update(
        task_default_queue=settings.queue,
        task_acks_late=True,
        task_reject_on_worker_lost=True,
        task_acks_on_failure_or_timeout=True,
        worker_prefetch_multiplier=1,
        task_ignore_result=True,
        result_backend=None,
        task_soft_time_limit=settings.job_soft_time_limit,
        task_time_limit=settings.job_hard_time_limit,
        broker_transport_options={"visibility_timeout": settings.visibility_timeout},
        broker_connection_retry_on_startup=True,
        broker_connection_max_retries=None,
        worker_cancel_long_running_tasks_on_connection_loss=False,
        task_serializer="json",
        accept_content=["json"],
        worker_send_task_events=False,
        worker_hijack_root_logger=False,
        broker_heartbeat=0,
    )
    return app
