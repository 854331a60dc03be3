"""What the job routes do: create (with idempotency), start, rerun, cancel, delete.

The routes parse a request, call one function here with keyword arguments and
turn the job it returns into a response model. Every check of a job's state is
the store's (:class:`service.store.JobStore`, one Lua script per change); the
functions here put those steps in order and say, as an :class:`ApiError`, why a
request cannot go ahead.
"""

from __future__ import annotations

import hashlib
import json
import logging
import uuid
import zipfile
from typing import Any, BinaryIO
from urllib.parse import urlsplit

from pydantic import ValidationError

from pmvir.capture import open_capture, validate_capture
from pmvir.config import PipelineConfig, merge_options
from pmvir.errors import CaptureError
from pmvir.stages import AVAILABLE_STAGES, Stage, stages_through
from service import observability
from service.deps import Services
from service.errors import ApiError, ErrorItem, conflict, invalid, not_found
from service.models import JobCreate
from service.queue import RUN_JOB
from service.store import Gate, Job, JobStatus, JobStore
from service.zipped import ignored_member, import_zip, save_upload

log = logging.getLogger("pmvir.api")


def fingerprint(spec: JobCreate, capture: BinaryIO | None = None) -> str:
    """What an Idempotency-Key is bound to: the options, the label, and a zipped capture's contents.

    A zip is fingerprinted by its members' names, sizes and CRC-32s (read from its
    central directory, nothing is inflated), not by its bytes: a rig that retries
    by zipping the same frames again writes new timestamps, and that is the same
    request; so is one that adds the members the import skips (``__MACOSX/``,
    ``.DS_Store``). A file that is not a readable zip falls back to its bytes (the
    import rejects it anyway).
    """
    h = hashlib.sha256(spec.model_dump_json().encode())
    if capture is not None:
        capture.seek(0)
        try:
            with zipfile.ZipFile(capture) as zf:
                kept = [i for i in zf.infolist() if not i.is_dir() and not ignored_member(i.filename)]
            members = sorted((i.filename, i.file_size, i.CRC) for i in kept)
            h.update(b"zip-members\0")
            for name, size, crc in members:
                h.update(f"{name}\0{size}\0{crc:08x}\n".encode())
        except (zipfile.BadZipFile, OSError, ValueError, EOFError):
            capture.seek(0)
            h.update(b"raw-bytes\0")
            while chunk := capture.read(1 << 20):
                h.update(chunk)
        capture.seek(0)
    return h.hexdigest()


def create_job(
    svc: Services,
    *,
    owner: str,
    spec: JobCreate,
    idempotency_key: str | None = None,
    capture: BinaryIO | None = None,
    extra: dict[str, str] | None = None,
) -> tuple[Job, bool]:
    """Create a job (with its files when ``capture`` is a zipped capture), or find the one
    this Idempotency-Key made.

    Returns:
        (the job, True when it was created now).

    Raises:
        ApiError: 409 (key reused with another request), 429 (too many unfinished jobs),
            413/422 (the zip breaks a limit or the capture layout; nothing is kept).
    """
    check_callback(svc, spec.callback_url)
    key_hash = hashlib.sha256(idempotency_key.encode()).hexdigest() if idempotency_key else None
    fp = fingerprint(spec, capture)
    job_id = uuid.uuid4().hex
    if key_hash:
        bound = svc.store.bind_idempotency_key(owner, key_hash, job_id, ttl=svc.settings.idempotency_ttl)
        if bound is not None:
            if bound.fingerprint and bound.fingerprint != fp:
                raise conflict("this Idempotency-Key was used with a different request")
            return _get(svc, bound.job_id), False
    n_open = svc.store.create(
        job_id,
        owner,
        options=spec.options.model_dump(mode="json"),
        label=spec.label,
        max_open=svc.settings.max_jobs_in_flight,
        extra={
            "idem_fp": fp,
            "idem_key": key_hash or "",
            "ttl": str(svc.settings.result_ttl if spec.result_ttl is None else spec.result_ttl),
            "callback_url": spec.callback_url or "",
            **(extra or {}),
        },
    )
    if n_open is not None:
        if key_hash:
            svc.store.forget_idempotency(owner, key_hash)
        raise ApiError(
            429,
            "too_many_jobs",
            f"this key has {n_open} unfinished jobs, the limit is "
            f"{svc.settings.max_jobs_in_flight}; finish, cancel or delete some first",
            headers={"Retry-After": "30"},
        )
    svc.files.create(job_id)
    svc.store.log(job_id, "job created")
    if capture is not None:
        try:
            _import_capture(svc, job_id, capture)
        except BaseException:
            _discard(svc, owner, job_id, key_hash)
            raise
    return _get(svc, job_id), True


def check_callback(svc: Services, url: str | None) -> None:
    """422 unless ``url`` is None or an http(s) URL on one of the allowed webhook hosts."""
    if url is None:
        return
    try:
        parts = urlsplit(url)
        scheme, host = parts.scheme, (parts.hostname or "").lower()
        hostport = f"{host}:{parts.port}" if parts.port else host
    except ValueError:  # a port out of range, a malformed IPv6 literal
        scheme = host = hostport = ""
    allowed = {h.lower() for h in svc.settings.webhook_hosts}
    if scheme not in ("http", "https") or not host or (host not in allowed and hostport not in allowed):
        shown = ", ".join(sorted(allowed)) or "none: PMVIR_WEBHOOK_HOSTS is empty"
        raise ApiError(
            422,
            "validation_error",
            f"callback_url host {host or '(none)'!r} is not an allowed webhook host ({shown})",
            errors=[ErrorItem(loc=["body", "callback_url"], msg="host not allowed", type="value_error")],
        )


def _get(svc: Services, job_id: str) -> Job:
    job = svc.store.get(job_id)
    if job is None:
        raise not_found("job")
    return job


def _import_capture(svc: Services, job_id: str, capture: BinaryIO) -> None:
    zip_path = svc.files.job_dir(job_id) / "incoming" / f"{uuid.uuid4().hex}.zip"
    zip_path.parent.mkdir(parents=True, exist_ok=True)
    save_upload(capture, zip_path, svc.settings.max_zip_bytes)
    files = import_zip(svc, job_id, zip_path)
    svc.store.log(job_id, f"zipped capture imported: {len(files)} files")


def _discard(svc: Services, owner: str, job_id: str, key_hash: str | None) -> None:
    job = svc.store.get(job_id)
    if job is not None:
        svc.store.delete(job)
    svc.files.delete(job_id)
    if key_hash:
        svc.store.forget_idempotency(owner, key_hash)


def start_job(svc: Services, *, job: Job) -> None:
    """Check the options and move the job to validating; :func:`validate_and_queue`, run after the
    answer, checks the capture and queues the job (or puts it back to created with its problems).

    Raises:
        ApiError: 404 (gone), 409 (not created, uploads in progress, being started),
            422 (the options name a stage this build lacks).
    """
    why = svc.store.start_lock(job.id)
    if why is Gate.GONE:
        raise not_found("job")
    if why is Gate.UPLOADING:
        raise conflict("uploads to this job are still in progress")
    if why is Gate.STARTING:
        raise conflict("the job is already being started")
    if why is not Gate.OK:
        raise conflict(f"the job is {why}; only a created job can be started")
    try:
        items = stage_problems(job)
        if items:
            svc.store.log(job.id, "start refused: the options name an unavailable stage")
            raise ApiError(422, "invalid_options", f"the job cannot start: {len(items)} problem(s)", errors=items)
        check_queue_room(svc)
        ok, before = svc.store.transition(job, (JobStatus.CREATED,), JobStatus.VALIDATING, problems="[]", error="")
        if not ok:
            raise conflict(f"the job is {before or 'gone'}; only a created job can be started")
        svc.store.validating_begin(job.id)
        svc.store.log(job.id, "validating the capture")
    finally:
        svc.store.start_unlock(job.id)


def check_queue_room(svc: Services) -> None:
    """503 with Retry-After when the queue holds PMVIR_MAX_QUEUED jobs already."""
    cap = svc.settings.max_queued
    if cap and (waiting := svc.store.queue_length(svc.settings.queue)) >= cap:
        raise ApiError(
            503,
            "queue_full",
            f"{waiting} jobs are waiting for a worker, the limit is {cap}; start this job later",
            headers={"Retry-After": "30"},
        )


def validate_and_queue(svc: Services, job_id: str) -> JobStatus | None:
    """Check a validating job's capture (each frame decoded) and queue it; a capture with problems
    sends the job back to created with them (``problems``). Returns the job's status after."""
    observability.job_id.set(job_id)
    try:
        return _validate_and_queue(svc, job_id)
    finally:
        svc.store.validating_end(job_id)


def _validate_and_queue(svc: Services, job_id: str) -> JobStatus | None:
    job = svc.store.get(job_id)
    if job is None or job.status is not JobStatus.VALIDATING:
        return job.status if job else None
    try:
        items = capture_problems(svc, job_id)
    except Exception as exc:  # an unreadable capture is a problem of the capture, said as such
        log.exception("job %s: validation failed", job_id)
        items = [ErrorItem(msg=f"the capture could not be read ({type(exc).__name__})", type="internal")]
    if items:
        svc.store.log(job_id, f"start refused: {len(items)} problem(s) in the capture")
        problems = json.dumps([i.model_dump(mode="json", exclude_none=True) for i in items])
        error = f"the capture is invalid: {len(items)} problem(s); fix them and start again"
        svc.store.transition(job, (JobStatus.VALIDATING,), JobStatus.CREATED, problems=problems, error=error)
        return JobStatus.CREATED
    try:
        queue_job(svc, job=job, current=JobStatus.VALIDATING)
    except ApiError as exc:
        svc.store.transition(job, (JobStatus.VALIDATING,), JobStatus.CREATED, error=str(exc))
        return JobStatus.CREATED
    svc.store.log(job_id, "capture valid; job queued")
    return JobStatus.QUEUED


def interrupted_validations(store: JobStore, *, older_than: float = 900.0) -> list[str]:
    """Send jobs whose validation never ended (its API process died) back to created; returns their ids."""
    back = []
    for job_id in store.stale_validating(older_than=older_than):
        job = store.get(job_id)
        error = "the capture's validation was interrupted; start the job again"
        if job is not None and store.transition(job, (JobStatus.VALIDATING,), JobStatus.CREATED, error=error)[0]:
            store.log(job_id, error)
            back.append(job_id)
        store.validating_end(job_id)
    return back


def queue_job(svc: Services, *, job: Job, current: JobStatus = JobStatus.CREATED) -> None:
    """Move a created (or validating) job to queued and send its task (back to created when the
    broker is away)."""
    ok, before = svc.store.transition(job, (current,), JobStatus.QUEUED, cancel=False)
    if not ok:
        raise conflict(f"the job is {before or 'gone'}; only a created job can be started")
    try:
        svc.celery.send_task(RUN_JOB, args=[job.id], queue=svc.settings.queue)
    except Exception as exc:  # the broker's client raises many types when Redis is away
        svc.store.transition(job, (JobStatus.QUEUED,), JobStatus.CREATED, queued_at="")
        raise ApiError(
            503,
            "unavailable",
            f"the job could not be queued ({type(exc).__name__}); retry",
            headers={"Retry-After": "5"},
        ) from exc


def rerun_job(
    svc: Services,
    *,
    owner: str,
    source: Job,
    changes: dict[str, Any],
    from_stage: Stage,
    label: str | None = None,
) -> Job:
    """A new job on the source job's capture with changed options, computing stages from ``from_stage`` on.

    The capture and the source's cached stage outputs are shared (hard links), so nothing is
    uploaded again; the job is queued at once (the capture was validated when the source started).

    Raises:
        ApiError: 409 (the source never started or has not finished, or it has no cached output of
            an earlier stage made with these options: the message names the stage and group),
            422 (the merged options are invalid, or from_stage is after stop_after), 429.
    """
    if not source.status.terminal or source.queued_at is None:
        raise conflict(
            f"the source job is {source.status}; a rerun needs a job that was started and finished"
        )
    try:
        config = PipelineConfig.model_validate(merge_options(source.options, changes))
    except ValidationError as exc:
        raise invalid(exc, ("body", "options"), "the merged options are invalid") from exc
    if from_stage.position > Stage(config.stop_after).position:
        raise ApiError(
            422,
            "validation_error",
            f"from_stage {from_stage} is after stop_after {config.stop_after}",
            errors=[ErrorItem(loc=["body", "from_stage"], msg="after stop_after", type="value_error")],
        )
    for stage in (s for s in Stage if s.position < from_stage.position):
        if not svc.files.cache_has_stage(source.id, stage, config):
            raise conflict(
                f"the source job has no cached {stage} output made with these options (it did not run "
                f"{stage}, or options for {stage} or an earlier stage changed); rerun from {stage}"
            )
    check_queue_room(svc)
    spec = JobCreate(
        options=config, label=label or source.label, callback_url=source.callback_url, result_ttl=source.ttl
    )
    job, _ = create_job(
        svc, owner=owner, spec=spec, extra={"source_job": source.id, "resume_from": str(from_stage)}
    )
    try:
        svc.files.share(source.id, job.id)
        n = svc.store.copy_files(source.id, job.id)
        svc.store.log(job.id, f"rerun of job {source.id} from {from_stage}: {n} capture files shared")
        queue_job(svc, job=job)
    except BaseException:
        _discard(svc, owner, job.id, None)
        raise
    return _get(svc, job.id)


def cancel_job(svc: Services, *, job: Job) -> None:
    """Cancel: a created or queued job ends now; a running one stops at its next boundary.

    Raises:
        ApiError: 409 when the job already succeeded or failed.
    """
    after = svc.store.cancel(job)
    if after in (JobStatus.SUCCEEDED, JobStatus.FAILED):
        raise conflict(f"the job already {after}")
    if after is JobStatus.RUNNING:
        svc.store.log(job.id, "cancellation requested")
    elif after is JobStatus.CANCELED and job.status is not JobStatus.CANCELED:
        svc.store.log(job.id, "job canceled")


def delete_job(svc: Services, *, job: Job) -> None:
    """Delete a job's record and files (a running job is canceled first)."""
    svc.store.cancel(job)
    svc.store.delete(job)
    svc.files.delete(job.id)


def stage_problems(job: Job) -> list[ErrorItem]:
    """A stop_after naming a stage this build cannot run (the pipeline would fail at once)."""
    config = PipelineConfig.model_validate(job.options)
    missing = [s for s in stages_through(config.stop_after) if s not in AVAILABLE_STAGES]
    if not missing:
        return []
    return [
        ErrorItem(
            loc=["options", "stop_after"],
            type="unavailable_stage",
            msg=f"stage(s) {', '.join(missing)} are not available in this build; "
            f"available: {', '.join(AVAILABLE_STAGES)}",
        )
    ]


def capture_problems(svc: Services, job_id: str) -> list[ErrorItem]:
    """Every problem of the job's capture, each naming its file (empty when it can run).

    Frame sizes are read from the headers and checked first; frames are decoded (sample
    ranges) only when every header is right, so a frame whose header declares a huge
    image is refused without being decoded.
    """
    with svc.files.capture_view(job_id) as root:
        problems: list[CaptureError] = validate_capture(root, decode_frames=False)
        if not problems:
            problems = validate_capture(root, decode_frames=True)
        hide = (str(root.resolve()), str(root))  # messages must not reveal the storage layout
        items = []
        for p in problems:
            msg = p.problem
            for h in hide:
                msg = msg.replace(h, "the capture")
            items.append(ErrorItem(file=p.path, msg=msg, type=type(p).__name__))
        if not problems:
            with open_capture(root) as cap:
                if len(cap) > svc.settings.max_frames:
                    items.append(
                        ErrorItem(
                            file="capture.json",
                            msg=f"{len(cap)} frames, more than the limit of {svc.settings.max_frames}",
                            type="limit",
                        )
                    )
    return items
