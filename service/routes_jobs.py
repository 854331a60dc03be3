"""Job routes: create, list, read, start, cancel, delete, log."""

from __future__ import annotations

import hashlib
import json
import time
import uuid
from typing import Annotated, Any

from fastapi import APIRouter, Depends, Header, Path, Query, Request, Response
from fastapi.exceptions import RequestValidationError
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.requests import ClientDisconnect
from starlette.requests import Request as StarletteRequest
from starlette.types import Message

from pmvir.capture import open_capture, validate_capture
from pmvir.config import PipelineConfig
from pmvir.errors import CaptureError
from service.auth import require_owner
from service.deps import Services, job_out, owned_job, reject_unknown_query, services
from service.errors import ApiError, ErrorBody, ErrorItem, conflict, not_found, too_large
from service.models import JobCreate, JobList, JobOut, JobSummary, LogLine, LogOut
from service.queue import RUN_JOB
from service.store import Job
from service.uploads import check_free_disk
from service.zipped import import_zip, save_upload

router = APIRouter(prefix="/v1/jobs", tags=["jobs"], dependencies=[Depends(reject_unknown_query)])

_E = {"model": ErrorBody}
_COMMON: dict[int | str, dict[str, Any]] = {
    401: {**_E, "description": "Missing or invalid API key."},
    422: {**_E, "description": "Invalid request; each problem is named in errors."},
    503: {**_E, "description": "The job store is unreachable."},
}
_JOB_ERRORS: dict[int | str, dict[str, Any]] = {
    **_COMMON,
    404: {**_E, "description": "No such job (for this key)."},
}
_JSON_BODY_LIMIT = 1 << 20

JobId = Annotated[str, Path(description="The job id (32 hex digits).")]
Owner = Annotated[str, Depends(require_owner)]
Svc = Annotated[Services, Depends(services)]

_CREATE_BODY = {
    "required": False,
    "content": {
        "application/json": {"schema": {"$ref": "#/components/schemas/JobCreate"}},
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "required": ["capture"],
                "properties": {
                    "capture": {
                        "type": "string",
                        "format": "binary",
                        "description": "A zipped capture (capture.json at the root or in one folder).",
                    },
                    "options": {
                        "type": "string",
                        "description": "JSON of the pipeline options (PipelineConfig), as in JobCreate.",
                    },
                    "label": {"type": "string", "maxLength": 200},
                },
            }
        },
    },
}


def _validation_error(exc: ValidationError, prefix: tuple[str, ...]) -> RequestValidationError:
    errors = []
    for e in exc.errors(include_url=False):
        errors.append({"loc": (*prefix, *e["loc"]), "msg": e["msg"], "type": e["type"]})
    return RequestValidationError(errors)


async def _read_json_body(request: Request) -> Any:
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > _JSON_BODY_LIMIT:
            raise too_large(f"a JSON body is limited to {_JSON_BODY_LIMIT} bytes")
    if not body.strip():
        return {}
    try:
        return json.loads(body)
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise ApiError(
            422,
            "validation_error",
            f"the body is not valid JSON: {exc}",
            errors=[ErrorItem(loc=["body"], msg=f"not valid JSON: {exc}", type="json_invalid")],
        ) from exc


def _fingerprint(spec: JobCreate, upload: Any = None) -> str:
    """What an Idempotency-Key is bound to: the options, the label, and a zipped capture's bytes."""
    h = hashlib.sha256(spec.model_dump_json().encode())
    if upload is not None:
        upload.seek(0)
        while chunk := upload.read(1 << 20):
            h.update(chunk)
        upload.seek(0)
    return h.hexdigest()


def _create(
    svc: Services, owner: str, spec: JobCreate, idem_hash: str | None, fingerprint: str
) -> tuple[str, bool]:
    """Create the job, or find the one this Idempotency-Key made. Returns (job id, created)."""
    job_id = uuid.uuid4().hex
    if idem_hash:
        deadline = time.monotonic() + 2.0
        while existing := svc.store.idempotent_job(owner, idem_hash, job_id, svc.settings.idempotency_ttl):
            fp = svc.store.r.hget(svc.store.key(existing), "idem_fp")
            if fp is not None:
                if fp and fingerprint and fp != fingerprint:
                    raise conflict("this Idempotency-Key was used with a different request")
                return existing, False
            if time.monotonic() > deadline:  # its creator failed or died: take the key over
                svc.store.forget_idempotency(owner, idem_hash)
            time.sleep(0.05)
    n_open = svc.store.create(
        job_id,
        owner,
        options=spec.options.model_dump(mode="json"),
        label=spec.label,
        max_open=svc.settings.max_jobs_in_flight,
        extra={"idem_fp": fingerprint, "idem_key": idem_hash or ""},
    )
    if n_open is not None:
        if idem_hash:
            svc.store.forget_idempotency(owner, idem_hash)
        raise ApiError(
            429,
            "too_many_jobs",
            f"this key has {n_open} unfinished jobs, the limit is "
            f"{svc.settings.max_jobs_in_flight}; finish, cancel or delete some first",
            headers={"Retry-After": "30"},
        )
    svc.files.create(job_id)
    svc.store.log(job_id, "job created")
    return job_id, True


def _discard(svc: Services, owner: str, job_id: str, idem_hash: str | None) -> None:
    job = svc.store.get(job_id)
    if job is not None:
        svc.store.delete(job)
    svc.files.delete(job_id)
    if idem_hash:
        svc.store.forget_idempotency(owner, idem_hash)


async def _create_from_zip(
    request: Request, svc: Services, owner: str, idem_hash: str | None
) -> tuple[str, bool]:
    s = svc.settings
    length = request.headers.get("content-length")
    if length and length.isdigit() and int(length) > s.max_zip_bytes + (1 << 20):
        raise too_large(f"a zipped capture is limited to {s.max_zip_bytes} bytes")
    await run_in_threadpool(check_free_disk, svc, int(length) if length and length.isdigit() else 0)
    received = 0

    async def limited_receive() -> Message:
        nonlocal received
        message = await request.receive()
        if message["type"] == "http.request":
            received += len(message.get("body", b""))
            if received > s.max_zip_bytes + (1 << 20):
                raise too_large(f"a zipped capture is limited to {s.max_zip_bytes} bytes")
        return message

    form_request = StarletteRequest(request.scope, receive=limited_receive)
    try:
        form = await form_request.form(max_files=1, max_fields=4, max_part_size=1 << 20)
    except ClientDisconnect as exc:
        raise ApiError(400, "client_disconnected", "the client went away mid-upload") from exc
    except ApiError:
        raise
    except Exception as exc:  # starlette's MultiPartException and parser errors
        raise ApiError(400, "bad_multipart", f"the multipart body could not be read: {exc}") from exc
    try:
        capture = form.get("capture")
        if not isinstance(capture, UploadFile):
            raise ApiError(
                422,
                "validation_error",
                "multipart field 'capture' (a zip file) is required",
                errors=[ErrorItem(loc=["body", "capture"], msg="field required", type="missing")],
            )
        raw_options = form.get("options")
        label = form.get("label")
        if isinstance(raw_options, UploadFile) or isinstance(label, UploadFile):
            raise ApiError(422, "validation_error", "'options' and 'label' are text fields")
        try:
            options = json.loads(raw_options) if raw_options else {}
        except json.JSONDecodeError as exc:
            raise ApiError(
                422,
                "validation_error",
                f"field 'options' is not valid JSON: {exc}",
                errors=[ErrorItem(loc=["body", "options"], msg="not valid JSON", type="json_invalid")],
            ) from exc
        try:
            spec = JobCreate.model_validate({"options": options, **({"label": label} if label else {})})
        except ValidationError as exc:
            raise _validation_error(exc, ("body",)) from exc
        fingerprint = await run_in_threadpool(_fingerprint, spec, capture.file)
        job_id, created = await run_in_threadpool(_create, svc, owner, spec, idem_hash, fingerprint)
        if not created:
            return job_id, False
        try:
            zip_path = svc.files.job_dir(job_id) / "incoming" / f"{uuid.uuid4().hex}.zip"
            zip_path.parent.mkdir(parents=True, exist_ok=True)
            await run_in_threadpool(save_upload, capture.file, zip_path, s.max_zip_bytes)
            files = await run_in_threadpool(import_zip, svc, job_id, zip_path)
            await run_in_threadpool(svc.store.log, job_id, f"zipped capture imported: {len(files)} files")
        except BaseException:
            await run_in_threadpool(_discard, svc, owner, job_id, idem_hash)
            raise
        return job_id, True
    finally:
        await form.close()


@router.post(
    "",
    status_code=201,
    summary="Create a job (empty, or from a zipped capture)",
    description="JSON body (JobCreate): an empty job to upload files into. multipart/form-data with a "
    "zipped capture in 'capture' (and optional 'options' JSON, 'label'): the job with its files, for small "
    "captures. With an Idempotency-Key header a retried create answers the job the first one made (200).",
    openapi_extra={"requestBody": _CREATE_BODY},
    response_model=JobOut,
    responses={
        200: {"model": JobOut, "description": "The job an earlier request with this Idempotency-Key made."},
        201: {"description": "Created."},
        **_COMMON,
        400: {**_E, "description": "Unreadable multipart body."},
        409: {**_E, "description": "Idempotency-Key reused with another request, or still in progress."},
        413: {**_E, "description": "The zip or a member is over a limit."},
        415: {**_E, "description": "Neither JSON nor multipart/form-data."},
        429: {**_E, "description": "Too many unfinished jobs for this key."},
        507: {**_E, "description": "Not enough free disk."},
    },
)
async def create_job(
    request: Request,
    response: Response,
    owner: Owner,
    svc: Svc,
    idempotency_key: Annotated[
        str | None,
        Header(max_length=200, description="Makes a retried create return the same job (remembered 24 h)."),
    ] = None,
) -> JobOut:
    idem_hash = hashlib.sha256(idempotency_key.encode()).hexdigest() if idempotency_key else None
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype == "multipart/form-data":
        job_id, created = await _create_from_zip(request, svc, owner, idem_hash)
    elif ctype in ("", "application/json"):
        data = await _read_json_body(request)
        try:
            spec = JobCreate.model_validate(data)
        except ValidationError as exc:
            raise _validation_error(exc, ("body",)) from exc
        fingerprint = _fingerprint(spec)
        job_id, created = await run_in_threadpool(_create, svc, owner, spec, idem_hash, fingerprint)
    else:
        raise ApiError(
            415,
            "unsupported_media_type",
            f"Content-Type {ctype!r}: send application/json or multipart/form-data",
        )
    job = await run_in_threadpool(owned_job, svc, job_id, owner)
    response.status_code = 201 if created else 200
    response.headers["Location"] = f"/v1/jobs/{job_id}"
    return await run_in_threadpool(job_out, svc, job)


@router.get("", summary="List the caller's jobs, newest first", response_model=JobList, responses=_COMMON)
def list_jobs(
    owner: Owner,
    svc: Svc,
    offset: Annotated[int, Query(ge=0, le=1_000_000)] = 0,
    limit: Annotated[int, Query(ge=1, le=500)] = 50,
) -> JobList:
    jobs, total = svc.store.list_for(owner, offset=offset, limit=limit)
    return JobList(jobs=[JobSummary.of(j) for j in jobs], total=total, offset=offset, limit=limit)


@router.get(
    "/{job_id}",
    summary="A job's status, stage, progress, timings and files",
    response_model=JobOut,
    responses=_JOB_ERRORS,
)
def get_job(job_id: JobId, owner: Owner, svc: Svc) -> JobOut:
    return job_out(svc, owned_job(svc, job_id, owner))


def _stage_problems(job: Job) -> list[ErrorItem]:
    """A stop_after naming a stage this build cannot run (the pipeline would fail at once)."""
    from pmvir import pipeline

    config = PipelineConfig.model_validate(job.options)
    available = getattr(pipeline, "AVAILABLE_STAGES", None)
    if available is None:
        return []
    missing = [s for s in pipeline.stages_for(config) if s not in available]
    if not missing:
        return []
    return [
        ErrorItem(
            loc=["options", "stop_after"],
            type="unavailable_stage",
            msg=f"stage(s) {', '.join(missing)} are not available in this build; "
            f"available: {', '.join(available)}",
        )
    ]


def _validate(svc: Services, job_id: str) -> list[ErrorItem]:
    root = svc.files.capture_dir(job_id)
    problems: list[CaptureError] = validate_capture(root, decode_frames=True)
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


@router.post(
    "/{job_id}/start",
    summary="Validate the whole capture and queue the job",
    response_model=JobOut,
    status_code=202,
    responses={
        **_JOB_ERRORS,
        202: {"description": "Queued."},
        409: {**_E, "description": "Not in status created, or uploads still in progress."},
        422: {**_E, "description": "The capture is invalid; errors name each file."},
    },
)
def start_job(job_id: JobId, owner: Owner, svc: Svc) -> JobOut:
    job = owned_job(svc, job_id, owner)
    why = svc.store.start_lock(job.id)
    if why == "gone":
        raise not_found("job")
    if why == "uploading":
        raise conflict("uploads to this job are still in progress")
    if why == "starting":
        raise conflict("the job is already being started")
    if why != "ok":
        raise conflict(f"the job is {why}; only a created job can be started")
    try:
        items = _stage_problems(job) or _validate(svc, job.id)
        if items:
            svc.store.log(job.id, f"start refused: {len(items)} problem(s) in the capture")
            code = "invalid_options" if items[0].loc else "invalid_capture"
            raise ApiError(422, code, f"the job cannot start: {len(items)} problem(s)", errors=items)
        ok, before = svc.store.transition(job, ("created",), "queued", cancel=False)
        if not ok:
            raise conflict(f"the job is {before or 'gone'}; only a created job can be started")
        try:
            svc.celery.send_task(RUN_JOB, args=[job.id], queue=svc.settings.queue)
        except Exception as exc:
            svc.store.transition(job, ("queued",), "created", queued_at="")
            raise ApiError(
                503,
                "unavailable",
                f"the job could not be queued ({type(exc).__name__}); retry",
                headers={"Retry-After": "5"},
            ) from exc
        svc.store.log(job.id, "capture valid; job queued")
    finally:
        svc.store.start_unlock(job.id)
    return job_out(svc, owned_job(svc, job_id, owner))


@router.post(
    "/{job_id}/cancel",
    summary="Cancel a job (a running one stops at its next boundary)",
    response_model=JobOut,
    status_code=202,
    responses={
        **_JOB_ERRORS,
        202: {"description": "Canceled, or cancellation requested."},
        409: {**_E, "description": "The job already finished."},
    },
)
def cancel_job(job_id: JobId, owner: Owner, svc: Svc) -> JobOut:
    job = owned_job(svc, job_id, owner)
    after = svc.store.cancel(job)
    if after in ("succeeded", "failed"):
        raise conflict(f"the job already {after}")
    if after == "running":
        svc.store.log(job.id, "cancellation requested")
    elif after == "canceled" and job.status != "canceled":
        svc.store.log(job.id, "job canceled")
    return job_out(svc, owned_job(svc, job_id, owner))


@router.delete(
    "/{job_id}",
    summary="Delete a job and its files (a running job is canceled)",
    status_code=204,
    response_class=Response,
    responses={**_JOB_ERRORS, 204: {"description": "Deleted."}},
)
def delete_job(job_id: JobId, owner: Owner, svc: Svc) -> Response:
    job = owned_job(svc, job_id, owner)
    svc.store.cancel(job)
    svc.store.delete(job)
    svc.files.delete(job.id)
    return Response(status_code=204)


@router.get(
    "/{job_id}/log",
    summary="A job's log lines from index since",
    response_model=LogOut,
    responses=_JOB_ERRORS,
)
def job_log(
    job_id: JobId,
    owner: Owner,
    svc: Svc,
    since: Annotated[int, Query(ge=0, le=10_000_000)] = 0,
    limit: Annotated[int, Query(ge=1, le=1000)] = 200,
) -> LogOut:
    job = owned_job(svc, job_id, owner)
    lines, total = svc.store.read_log(job.id, since, limit)
    out = [LogLine(index=since + i, time=ln["t"], message=ln["msg"]) for i, ln in enumerate(lines)]
    return LogOut(lines=out, next=since + len(out), total=total)
