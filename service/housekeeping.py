"""What every worker does beside running jobs: webhooks, retention, and saying it is alive.

Two daemon threads per worker process (started by :mod:`service.celery_app`):

* ``pmvir-webhooks`` delivers the event of every job that ended with a
  ``callback_url``. The store schedules it in the same Lua script that ends
  the job; one worker claims it (``ZREM``), POSTs the signed JSON event
  (:func:`sign`), records the attempt on the job, and on failure schedules the
  next attempt after ``webhook_backoff * 2**(attempt - 1)`` seconds, up to
  ``webhook_attempts``. Redirects are not followed.
* ``pmvir-janitor`` deletes finished jobs whose ttl ran out (record and
  folder; each deletion logged) every ``janitor_interval`` seconds, and
  renews the worker's heartbeat key: name, version, whether CUDA is available
  (what ``GET /v1/info`` reports).
"""

from __future__ import annotations

import hashlib
import hmac
import json
import logging
import os
import socket
import threading
import time
from typing import Any

import httpx

import pmvir
from pmvir.result import downloadable_names
from service.jobs import interrupted_validations
from service.settings import Settings
from service.storage import JobFiles
from service.storage_s3 import open_storage
from service.store import Job, JobStore

log = logging.getLogger("pmvir.worker")

#: The header carrying ``t=<unix seconds>,v1=<hex HMAC-SHA256 of "<t>." + body>``.
SIGNATURE_HEADER = "X-Pmvir-Signature"
EVENT = "job.finished"


def sign(secret: str, body: bytes, *, timestamp: int) -> str:
    """The signature header's value for ``body`` sent at ``timestamp`` (Unix seconds)."""
    mac = hmac.new(secret.encode(), f"{timestamp}.".encode() + body, hashlib.sha256).hexdigest()
    return f"t={timestamp},v1={mac}"


def event_body(job: Job, files: JobFiles, *, attempt: int) -> bytes:
    """The JSON event of a job that ended (compact, UTF-8)."""
    present = files.result_files(job.id)
    results = [n for n in downloadable_names() if n in present]
    doc = {
        "type": EVENT,
        "attempt": attempt,
        "sent_at": time.time(),
        "job": {
            "id": job.id,
            "status": str(job.status),
            "label": job.label,
            "error": job.error,
            "created_at": job.created_at,
            "finished_at": job.finished_at,
            "stage_timings": job.stage_timings,
            "results": results,
            "source_job": job.source_job,
        },
    }
    return json.dumps(doc, separators=(",", ":")).encode()


def deliver(
    store: JobStore, files: JobFiles, settings: Settings, job_id: str, *, client: httpx.Client
) -> bool:
    """One delivery attempt of a claimed webhook event; schedules the next on failure.

    Returns:
        True when the receiver answered 2xx.
    """
    job = store.get(job_id)
    if job is None or not job.callback_url:
        return False
    attempt = len(store.deliveries(job_id)) + 1
    body = event_body(job, files, attempt=attempt)
    headers = {
        "Content-Type": "application/json",
        SIGNATURE_HEADER: sign(settings.webhook_secret, body, timestamp=int(time.time())),
        "X-Pmvir-Event": EVENT,
        "X-Pmvir-Delivery": f"{job_id}-{attempt}",
    }
    record: dict[str, Any] = {"attempt": attempt, "time": time.time(), "ok": False}
    try:
        r = client.post(job.callback_url, content=body, headers=headers)
        record["status_code"] = r.status_code
        record["ok"] = 200 <= r.status_code < 300
        if not record["ok"]:
            record["error"] = f"HTTP {r.status_code}"
    except httpx.HTTPError as exc:
        record["error"] = f"{type(exc).__name__}: {exc}"[:300]
    store.record_delivery(job_id, record)
    if record["ok"]:
        store.log(job_id, f"webhook delivered (attempt {attempt})")
        return True
    if attempt < settings.webhook_attempts:
        delay = settings.webhook_backoff * 2 ** (attempt - 1)
        store.retry_webhook(job_id, at=time.time() + delay)
        store.log(job_id, f"webhook attempt {attempt} failed ({record['error']}); next in {delay:.0f} s")
    else:
        store.log(job_id, f"webhook attempt {attempt} failed ({record['error']}); giving up")
    return False


def sweep_expired(store: JobStore, files: JobFiles, *, now: float | None = None) -> list[str]:
    """Delete every finished job whose ttl ran out; returns their ids (each deletion is logged)."""
    now = time.time() if now is None else now
    deleted = []
    for job_id in store.expired(now=now):
        job = store.get(job_id)
        if job is not None:
            store.delete(job)
            age = now - (job.finished_at or now)
            log.info("job %s deleted: finished %.0f s ago, ttl %d s", job_id, age, job.ttl)
        else:
            store.delete_expiry(job_id)
        files.delete(job_id)
        deleted.append(job_id)
    return deleted


def sweep_abandoned(store: JobStore, files: JobFiles, *, ttl: float, now: float | None = None) -> list[str]:
    """Delete created jobs nobody touched for ``ttl`` seconds (their uploads stopped, never started),
    which frees their slots of the key's unfinished-jobs limit; returns their ids."""
    if ttl <= 0:
        return []
    deleted = []
    for job in store.abandoned(older_than=ttl, now=now):
        store.delete(job)
        files.delete(job.id)
        log.info("job %s deleted: created and left untouched for %.0f s", job.id, ttl)
        deleted.append(job.id)
    return deleted


def worker_info(name: str) -> dict[str, Any]:
    """What this worker says about itself in its heartbeat."""
    try:
        import torch

        cuda, devices = bool(torch.cuda.is_available()), int(torch.cuda.device_count())
    except Exception:  # noqa: BLE001 - no torch, or a broken CUDA driver: report no CUDA
        cuda, devices = False, 0
    return {
        "name": name,
        "pid": os.getpid(),
        "version": pmvir.__version__,
        "cuda": cuda,
        "cuda_devices": devices,
    }


def _webhook_loop(settings: Settings, stop: threading.Event) -> None:
    store = JobStore.from_url(settings.redis_url, prefix=settings.key_prefix)
    files = open_storage(settings)
    with httpx.Client(timeout=settings.webhook_timeout, follow_redirects=False) as client:
        while not stop.wait(0.25):
            try:
                for job_id in store.due_webhooks(now=time.time()):
                    if store.take_webhook(job_id):
                        deliver(store, files, settings, job_id, client=client)
            except Exception as exc:  # noqa: BLE001 - Redis away: keep trying
                log.warning("webhooks: %s", exc)


def _janitor_loop(settings: Settings, stop: threading.Event, name: str) -> None:
    store = JobStore.from_url(settings.redis_url, prefix=settings.key_prefix)
    files = open_storage(settings)
    info = worker_info(name)
    beat = max(settings.lease_seconds / 2.0, 0.5)
    next_sweep = 0.0
    while True:
        try:
            store.worker_seen(name, {**info, "seen_at": time.time()}, ttl=3 * beat)
            if time.monotonic() >= next_sweep:
                next_sweep = time.monotonic() + settings.janitor_interval
                sweep_expired(store, files)
                sweep_abandoned(store, files, ttl=settings.upload_ttl)
                for job_id in interrupted_validations(store):
                    log.warning("job %s: its validation was interrupted; back to created", job_id)
        except Exception as exc:  # noqa: BLE001 - Redis or the disk away: keep trying
            log.warning("janitor: %s", exc)
        if stop.wait(beat):
            return


_threads: list[tuple[threading.Thread, threading.Event]] = []


def start(settings: Settings, *, name: str | None = None) -> None:
    """Start this worker process's webhook and janitor threads (idempotent)."""
    if _threads:
        return
    name = name or f"{socket.gethostname()}-{os.getpid()}"
    for target, args in ((_webhook_loop, ()), (_janitor_loop, (name,))):
        stop = threading.Event()
        t = threading.Thread(
            target=target, args=(settings, stop, *args), name=f"pmvir-{target.__name__}", daemon=True
        )
        t.start()
        _threads.append((t, stop))


def stop() -> None:
    while _threads:
        _threads.pop()[1].set()
