"""Prometheus metrics (``GET /metrics``), read from Redis at each scrape.

Every API process answers the same figures: they come from the job store, not
from per-process counters. Workers add what only they see when a job ends
(:func:`record_end`): each stage's duration into a histogram kept in Redis,
and a failure's error class into a counter.

Metrics::

    pmvir_jobs{status}                          jobs by state
    pmvir_queue_depth                           messages waiting in the Celery queue
    pmvir_oldest_queued_age_seconds             age of the job queued longest (0: none queued)
    pmvir_stage_duration_seconds{stage}         histogram of the stages' durations (finished runs)
    pmvir_job_failures_total{error_class}       failed jobs by error class
    pmvir_worker_last_heartbeat_seconds{worker} Unix time of each live worker's last heartbeat
    pmvir_workers_online                        workers with a live heartbeat
    pmvir_storage_bytes{kind}                   job bytes in the storage, and the scratch disk's free bytes
    pmvir_storage_jobs                          jobs with files in the storage
"""

from __future__ import annotations

import math
import time
from collections.abc import Iterator
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily, Metric
from prometheus_client.registry import Collector

from service.store import JobStatus, JobStore

#: Upper bounds (seconds) of the stage-duration histogram's buckets.
STAGE_BUCKETS = (1.0, 2.0, 5.0, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0, 1800.0, 3600.0, 7200.0, math.inf)
_SCAN_EVERY = 5.0


def _le(bound: float) -> str:
    return "+Inf" if math.isinf(bound) else repr(bound)


def error_class(error: str | None) -> str:
    """A failure's class from its message: the exception's name, or the kind of limit it hit.

    >>> error_class("CaptureError: frames/001.png: not a PNG")
    'CaptureError'
    >>> error_class("time limit exceeded (60 s)")
    'time_limit'
    """
    text = error or ""
    for prefix, name in (
        ("time limit", "time_limit"),
        ("hard time limit", "time_limit"),
        ("out of memory", "out_of_memory"),
        ("the job was started", "worker_lost"),
        ("internal error", "internal"),
    ):
        if text.startswith(prefix):
            return name
    head = text.split(":", 1)[0]
    return head if head.isidentifier() else "other"


def record_end(store: JobStore, status: JobStatus, timings: dict[str, float], error: str | None) -> None:
    """A worker's record of a job that ended: its stage durations, and its failure's class."""
    pipe = store.r.pipeline(transaction=False)
    for stage, seconds in timings.items():
        key = f"{store.p}:metrics:stage:{stage}"
        for bound in STAGE_BUCKETS:
            if seconds <= bound:
                pipe.hincrby(key, _le(bound), 1)
        pipe.hincrbyfloat(key, "sum", float(seconds))
        pipe.sadd(f"{store.p}:metrics:stages", stage)
    if status is JobStatus.FAILED:
        pipe.hincrby(f"{store.p}:metrics:failures", error_class(error), 1)
    pipe.execute()


class ServiceCollector(Collector):
    """Collects the service's figures from Redis (and the storage's use) at each scrape."""

    def __init__(self, svc: Any):
        self.svc = svc
        self._jobs: tuple[float, dict[str, int], float] | None = None

    def _job_counts(self) -> tuple[dict[str, int], float]:
        """Jobs by status and the oldest queued job's queued_at (scanned at most every 5 s)."""
        if self._jobs is not None and time.monotonic() - self._jobs[0] < _SCAN_EVERY:
            return self._jobs[1], self._jobs[2]
        store: JobStore = self.svc.store
        counts = {str(s): 0 for s in JobStatus}
        oldest = math.inf
        for owner_key in store.r.scan_iter(match=f"{store.p}:owner:*:jobs", count=500):
            ids = store.r.zrange(owner_key, 0, -1)
            pipe = store.r.pipeline(transaction=False)
            for job_id in ids:
                pipe.hmget(store.key(job_id), "status", "queued_at")
            for status, queued_at in pipe.execute():
                if status in counts:
                    counts[status] += 1
                    if status == JobStatus.QUEUED and queued_at:
                        oldest = min(oldest, float(queued_at))
        self._jobs = (time.monotonic(), counts, oldest)
        return counts, oldest

    def collect(self) -> Iterator[Metric]:
        store: JobStore = self.svc.store
        counts, oldest = self._job_counts()
        jobs = GaugeMetricFamily("pmvir_jobs", "Jobs by state.", labels=["status"])
        for status, n in counts.items():
            jobs.add_metric([status], n)
        yield jobs
        yield GaugeMetricFamily(
            "pmvir_queue_depth",
            "Messages waiting in the Celery queue.",
            value=store.queue_length(self.svc.settings.queue),
        )
        age = time.time() - oldest if math.isfinite(oldest) else 0.0
        yield GaugeMetricFamily(
            "pmvir_oldest_queued_age_seconds",
            "Seconds the job queued longest has waited.",
            value=max(age, 0.0),
        )
        yield from self._stages(store)
        failures = CounterMetricFamily(
            "pmvir_job_failures", "Failed jobs by error class.", labels=["error_class"]
        )
        for name, n in sorted(store.r.hgetall(f"{store.p}:metrics:failures").items()):
            failures.add_metric([name], float(n))
        yield failures
        workers = store.workers()
        beats = GaugeMetricFamily(
            "pmvir_worker_last_heartbeat_seconds",
            "Unix time of a live worker's last heartbeat.",
            labels=["worker"],
        )
        for w in workers:
            beats.add_metric([str(w.get("name", ""))], float(w.get("seen_at", 0.0)))
        yield beats
        yield GaugeMetricFamily("pmvir_workers_online", "Workers with a live heartbeat.", value=len(workers))
        usage = self.svc.files.usage()
        use = GaugeMetricFamily(
            "pmvir_storage_bytes",
            "Bytes of the jobs in the storage (disk or bucket), and the local disk's free bytes.",
            labels=["kind"],
        )
        use.add_metric(["jobs"], usage["jobs_bytes"])
        use.add_metric(["disk_free"], usage["free"])
        yield use
        yield GaugeMetricFamily("pmvir_storage_jobs", "Jobs with files in the storage.", value=usage["jobs"])

    def _stages(self, store: JobStore) -> Iterator[Metric]:
        hist = HistogramMetricFamily(
            "pmvir_stage_duration_seconds", "Seconds per pipeline stage of finished runs.", labels=["stage"]
        )
        for stage in sorted(store.r.smembers(f"{store.p}:metrics:stages")):
            h = store.r.hgetall(f"{store.p}:metrics:stage:{stage}")
            buckets = [(_le(b), float(h.get(_le(b), 0))) for b in STAGE_BUCKETS]
            hist.add_metric([stage], buckets, sum_value=float(h.get("sum", 0.0)))
        yield hist
