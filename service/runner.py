"""What a worker does with a job: claim it, run the pipeline, publish the result.

The Celery task stays thin and calls :func:`run_job`, which

1. *claims* a job (:meth:`JobStore.claim_next`): the message only wakes the
   worker, which takes the next job in fair order across tenants (the oldest
   ready job of the tenant served least recently); a fresh run id becomes the
   job's owner, its delivery counter goes up (a job started more than
   ``max_deliveries`` times - its worker keeps dying - is failed instead of
   looping), and a heartbeat lease starts;
2. calls ``pmvir.pipeline.run(config, capture, out, progress=Progress(...))``
   with ``out`` a folder private to this run (``runs/<run id>``);
3. zips the run's folder and renames it to ``result/`` (so a repeated run
   replaces a result whole, never mixes with it), then marks the job succeeded.

The pipeline's progress callback feeds the job's stage, monotonic progress,
per-stage timings and log; its ``should_cancel`` answers True when the job is
canceled, deleted, or taken over by another run, and the pipeline raises
:class:`pmvir.errors.CanceledError` at its next stage or iteration boundary.

The lease is extended by a thread of the job's process and by a keeper process
of its own (:mod:`service.lease_keeper`), which a native call holding the GIL
for longer than the lease cannot starve. A *reaper* thread in every worker
requeues running jobs whose lease lapsed (their worker was killed), so a job
survives a ``kill -9`` of its worker within about ``lease_seconds``, not only
after Redis's visibility timeout.
"""

from __future__ import annotations

import logging
import subprocess
import threading
import time
import uuid
from collections.abc import Callable

from celery.exceptions import SoftTimeLimitExceeded

from pmvir.config import PipelineConfig
from pmvir.errors import CanceledError, PmvirError
from service import lease_keeper, limits, metrics, observability
from service.queue import RUN_JOB
from service.settings import Settings
from service.storage import JobFiles
from service.storage_s3 import open_storage
from service.store import Claim, Job, JobStatus, JobStore

log = logging.getLogger("pmvir.worker")

_CANCEL_POLL = 0.2
_WRITE_EVERY = 0.2


class _Run:
    """One run of a job: callbacks for the pipeline, heartbeat, timings."""

    def __init__(self, store: JobStore, job: Job, run_id: str, settings: Settings):
        self.store = store
        self.job = job
        self.run_id = run_id
        self.settings = settings
        self.stage: str | None = None
        self.stage_t0 = time.monotonic()
        self.timings: dict[str, float] = dict(job.stage_timings)
        self._last_check = 0.0
        self._last_write = 0.0
        self._stop_cached = False
        self._beat_stop = threading.Event()
        self._beat = threading.Thread(target=self._heartbeat, name=f"lease-{job.id[:8]}", daemon=True)
        self._keeper: subprocess.Popen | None = None

    # -- lease

    def _heartbeat(self) -> None:
        interval = max(self.settings.lease_seconds / 3.0, 0.2)
        while not self._beat_stop.wait(interval):
            try:
                if not self.store.heartbeat(
                    self.job.id, self.run_id, lease_seconds=self.settings.lease_seconds
                ):
                    self._stop_cached = True
                    return
            except Exception as exc:  # noqa: BLE001 - Redis away: keep trying; the lease may lapse meanwhile
                log.warning("job %s: heartbeat failed: %s", self.job.id, exc)

    def __enter__(self) -> _Run:
        self._beat.start()
        self._keeper = lease_keeper.start(
            self.settings.redis_url, self.settings.key_prefix, self.job.id, self.run_id, self.settings.lease_seconds
        )
        return self

    def __exit__(self, *exc: object) -> None:
        lease_keeper.stop(self._keeper)
        self._beat_stop.set()
        self._beat.join(timeout=5)

    # -- pipeline callbacks

    def _close_stage(self) -> None:
        if self.stage is not None:
            self.timings[self.stage] = round(
                self.timings.get(self.stage, 0.0) + time.monotonic() - self.stage_t0, 4
            )

    def progress(self, stage: str, fraction: float, message: str = "") -> None:
        """The pipeline's progress callback: (stage, overall fraction 0..1, message).

        Written to Redis at most every 0.2 s (always at a new stage and at the end); the
        messages of skipped calls are not logged, so a tight iteration loop cannot flood Redis.
        """
        now = time.monotonic()
        new_stage = stage != self.stage
        if new_stage:
            self._close_stage()
            self.stage, self.stage_t0 = stage, now
            self.store.log(self.job.id, f"stage {stage}", max_lines=self.settings.max_log_lines)
            self.timings.setdefault(stage, 0.0)
        elif fraction < 1.0 and now - self._last_write < _WRITE_EVERY:
            return
        self._last_write = now
        timings = dict(self.timings)
        timings[stage] = round(timings.get(stage, 0.0) + time.monotonic() - self.stage_t0, 4)
        try:
            if not self.store.progress(
                self.job.id, self.run_id, stage=stage, fraction=fraction, stage_timings=timings
            ):
                self._stop_cached = True
            if message:
                self.store.log(self.job.id, f"{stage}: {message}", max_lines=self.settings.max_log_lines)
        except SoftTimeLimitExceeded:  # the time limit's signal landed in the Redis call: the job ends
            raise
        except Exception as exc:  # noqa: BLE001 - progress is best effort; the job goes on
            log.warning("job %s: progress not recorded: %s", self.job.id, exc)

    def should_cancel(self) -> bool:
        """The pipeline's cancellation check (Redis is asked at most every 0.2 s)."""
        if self._stop_cached:
            return True
        now = time.monotonic()
        if now - self._last_check >= _CANCEL_POLL:
            self._last_check = now
            try:
                self._stop_cached = self.store.should_stop(self.job.id, self.run_id)
            except SoftTimeLimitExceeded:  # as in progress(): not a Redis failure to ride out
                raise
            except Exception as exc:  # noqa: BLE001 - keep the last known flag
                log.warning("job %s: cancel flag not readable: %s", self.job.id, exc)
        return self._stop_cached

    def final_timings(self) -> dict[str, float]:
        self._close_stage()
        self.stage = None
        return self.timings


def run_job(
    job_id: str, *, settings: Settings, hostname: str = "", store: JobStore | None = None, task_id: str = ""
) -> str:
    """Run the next job's pipeline once (one delivery of a task; ``job_id`` is the message's job,
    run when no job is ready in fair order).

    Returns:
        What happened: 'succeeded', 'failed', 'canceled', 'superseded', or why nothing ran
        ('gone', 'done', 'not_queued', 'busy', 'exhausted').
    """
    from pmvir import pipeline  # the library's entry point; imported here so the API never loads it
    from pmvir.progress import Progress

    store = store or JobStore.from_url(settings.redis_url, prefix=settings.key_prefix)
    files = open_storage(settings)
    run_id = uuid.uuid4().hex
    what, job_id, n = store.claim_next(
        job_id,
        run_id,
        lease_seconds=settings.lease_seconds,
        max_deliveries=settings.max_deliveries,
        task_id=task_id,
    )
    observability.job_id.set(job_id)
    if what is not Claim.OK:
        log.info("job %s: nothing to run (%s)", job_id, what)
        if what is Claim.EXHAUSTED:
            store.log(job_id, f"failed: started {n - 1} times, its worker died each time")
            _record(store, JobStatus.FAILED, {}, "the job was started too often")
        return what
    job = store.get(job_id)
    if job is None:
        return "gone"
    store.log(
        job_id,
        f"run {run_id[:8]} started on {hostname or 'a worker'} (delivery {n})",
        max_lines=settings.max_log_lines,
    )
    out = files.run_dir(job_id, run_id)

    def end(run: _Run, status: JobStatus, error: str | None = None) -> str:
        # The run's scratch folder goes before the job turns terminal: a client that sees
        # "canceled" or "failed" never finds the run's files still there.
        files.remove_tree(out)
        if status is JobStatus.CANCELED:
            return _end_canceled(store, files, job, run_id, run.final_timings())
        return _end(store, job, run_id, status, run.final_timings(), error)

    try:
        with _Run(store, job, run_id, settings) as run:
            try:
                config = PipelineConfig.model_validate(job.options)
                capture, cache = files.checkout(job_id)
                out.mkdir(parents=True, exist_ok=False)
                outcome = pipeline.run(
                    config,
                    capture,
                    out,
                    progress=Progress(run.progress, should_cancel=run.should_cancel),
                    cache=cache,
                    resume_from=job.resume_from,
                )
                for warning in outcome.warnings:
                    store.log(job_id, f"warning: {warning}")
                if run.should_cancel():  # canceled after the last boundary: honour it
                    raise CanceledError("canceled after the last stage")
                files.publish_result(job_id, out)
                files.push_cache(job_id, cache)
            except CanceledError:
                return end(run, JobStatus.CANCELED)
            except SoftTimeLimitExceeded:
                return end(run, JobStatus.FAILED, f"time limit exceeded ({settings.job_soft_time_limit} s)")
            except PmvirError as exc:
                return end(run, JobStatus.FAILED, f"{type(exc).__name__}: {exc}")
            except Exception as exc:
                if limits.out_of_memory(exc):
                    cap = f"PMVIR_JOB_MEMORY={settings.job_memory} bytes" if settings.job_memory else "the host's"
                    return end(run, JobStatus.FAILED, f"out of memory ({cap}): {type(exc).__name__}: {exc}")
                log.exception("job %s: unexpected error", job_id)
                return end(run, JobStatus.FAILED, f"internal error: {type(exc).__name__}: {exc}")
            return end(run, JobStatus.SUCCEEDED)
    finally:
        files.remove_tree(out)
        files.release(job_id)
        if store.get(job_id) is None:  # deleted while running: leave nothing behind
            files.delete(job_id)


def _end(
    store: JobStore, job: Job, run_id: str, status: JobStatus, timings: dict[str, float], error: str | None
) -> str:
    fields: dict[str, object] = {"stage_timings": timings, "error": error or ""}
    if status is JobStatus.SUCCEEDED:
        fields["progress"] = 1.0
    if not store.finish(job, run_id, status, **fields):
        log.info("job %s: run %s was superseded; its outcome (%s) is dropped", job.id, run_id, status)
        return "superseded"
    store.log(job.id, status if error is None else f"{status}: {error}")
    _record(store, status, timings, error)
    return status


def _record(store: JobStore, status: JobStatus, timings: dict[str, float], error: str | None) -> None:
    try:
        metrics.record_end(store, status, timings, error)
    except Exception as exc:  # noqa: BLE001 - metrics are best effort; the job's outcome is recorded
        log.warning("metrics not recorded: %s", exc)


def _end_canceled(store: JobStore, files: JobFiles, job: Job, run_id: str, timings: dict[str, float]) -> str:
    current = store.get(job.id)
    if current is None:
        return "canceled"
    if current.run_id != run_id or not current.cancel_requested:
        return "superseded"
    return _end(store, job, run_id, JobStatus.CANCELED, timings, None)


def fail_now(task_id: str, settings: Settings, error: str) -> bool:
    """Fail the running job of Celery task ``task_id`` whose process is gone for good (hard time
    limit), so it is not requeued."""
    store = JobStore.from_url(settings.redis_url, prefix=settings.key_prefix)
    job_id = store.running_task(task_id)
    job = store.get(job_id) if job_id else None
    if job is None or job.status is not JobStatus.RUNNING:
        return False
    if store.finish(job, job.run_id, JobStatus.FAILED, error=error):
        store.log(job.id, f"failed: {error}")
        _record(store, JobStatus.FAILED, {}, error)
        log.error("job %s: %s", job.id, error)
        return True
    return False


# ----------------------------------------------------------------------------- reaper

_reaper: tuple[threading.Thread, threading.Event] | None = None


def reap_once(store: JobStore, send: Callable[[str], None]) -> list[str]:
    """Requeue every running job whose lease lapsed; returns their ids."""
    requeued = []
    for job_id in store.lapsed_running():
        if store.requeue_lapsed(job_id):
            store.log(job_id, "its worker stopped (lease lapsed); job requeued")
            send(job_id)
            requeued.append(job_id)
    return requeued


def _reaper_loop(settings: Settings, stop: threading.Event) -> None:
    from service.queue import make_celery

    store = JobStore.from_url(settings.redis_url, prefix=settings.key_prefix)
    sender = make_celery(settings)
    interval = max(settings.lease_seconds / 2.0, 0.25)

    def send(job_id: str) -> None:
        sender.send_task(RUN_JOB, args=[job_id], queue=settings.queue)

    while True:
        try:
            for job_id in reap_once(store, send):
                log.warning("job %s: worker lost, requeued", job_id)
        except Exception as exc:  # noqa: BLE001 - the reaper thread must outlive any one failure
            log.warning("reaper: %s", exc)
        if stop.wait(interval):
            return


def start_reaper(settings: Settings) -> None:
    """Start the reaper thread of this worker process (idempotent)."""
    global _reaper  # noqa: PLW0603 - one reaper per worker process
    if _reaper is not None:
        return
    stop = threading.Event()
    t = threading.Thread(target=_reaper_loop, args=(settings, stop), name="pmvir-reaper", daemon=True)
    t.start()
    _reaper = (t, stop)


def stop_reaper() -> None:
    global _reaper  # noqa: PLW0603 - one reaper per worker process
    if _reaper is not None:
        _reaper[1].set()
        _reaper = None
