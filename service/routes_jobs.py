"""Job routes: create, list, read, start, cancel, delete, log."""

from __future__ import annotations

from functools import partial
from typing import Annotated, Any

from fastapi import APIRouter, BackgroundTasks, Depends, Header, Path, Query, Request, Response
from pydantic import ValidationError
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.requests import ClientDisconnect
from starlette.requests import Request as StarletteRequest
from starlette.types import Message

from pmvir.io import json_limits
from service import jobs
from service.auth import require_owner
from service.deps import Services, job_out, owned_job, reject_unknown_query, services
from service.errors import ApiError, ErrorBody, ErrorItem, invalid, too_large
from service.models import JobCreate, JobList, JobOut, JobRerun, JobSummary, LogLine, LogOut
from service.store import Job
from service.uploads import check_free_disk

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
                        "description": "A zipped capture (capture.json at the root or in one folder), "
                        "or a zip of bare frames whose capture.json is inferred.",
                    },
                    "options": {
                        "type": "string",
                        "description": "JSON of the pipeline options (PipelineConfig), as in JobCreate.",
                    },
                    "label": {"type": "string", "maxLength": 200},
                    "callback_url": {
                        "type": "string",
                        "description": "As in JobCreate: the webhook URL told of every terminal state.",
                    },
                    "result_ttl": {
                        "type": "string",
                        "description": "As in JobCreate: seconds after it finished that the job is deleted.",
                    },
                },
            }
        },
    },
}


def _parse_json(data: bytes | str, loc: list[str | int], what: str) -> Any:
    """A JSON document from the request: 422 naming ``loc`` when malformed, too deep or too big a number."""
    try:
        return json_limits.loads(data, source=what)
    except json_limits.JsonError as exc:
        raise ApiError(
            422,
            "validation_error",
            str(exc),
            errors=[ErrorItem(loc=loc, msg=exc.problem, type="json_invalid")],
        ) from None


def _job_spec(data: Any, loc: tuple[str, ...]) -> JobCreate:
    try:
        return JobCreate.model_validate(data)
    except ValidationError as exc:
        raise invalid(exc, loc) from exc


async def _read_json_body(request: Request) -> Any:
    body = bytearray()
    async for chunk in request.stream():
        body += chunk
        if len(body) > _JSON_BODY_LIMIT:
            raise too_large(f"a JSON body is limited to {_JSON_BODY_LIMIT} bytes")
    if not body.strip():
        return {}
    return _parse_json(bytes(body), ["body"], "the body")


def _create_from_json(svc: Services, owner: str, data: Any, idempotency_key: str | None) -> tuple[Job, bool]:
    spec = _job_spec(data, ("body",))
    return jobs.create_job(svc, owner=owner, spec=spec, idempotency_key=idempotency_key)


async def _create_from_zip(
    request: Request, svc: Services, owner: str, idempotency_key: str | None
) -> tuple[Job, bool]:
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
        form = await form_request.form(max_files=1, max_fields=6, max_part_size=1 << 20)
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
        text: dict[str, str] = {}
        for name in ("options", "label", "callback_url", "result_ttl"):
            value = form.get(name)
            if isinstance(value, UploadFile):
                raise ApiError(422, "validation_error", f"multipart field {name!r} must be text, not a file")
            if value:
                text[name] = value
        raw_options = text.pop("options", None)
        options = _parse_json(raw_options, ["body", "options"], "field 'options'") if raw_options else {}
        spec = _job_spec({"options": options, **text}, ("body",))  # JobCreate reads result_ttl's text as int
        return await run_in_threadpool(
            partial(
                jobs.create_job,
                svc,
                owner=owner,
                spec=spec,
                idempotency_key=idempotency_key,
                capture=capture.file,
            )
        )
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
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype == "multipart/form-data":
        job, created = await _create_from_zip(request, svc, owner, idempotency_key)
    elif ctype in ("", "application/json"):
        data = await _read_json_body(request)
        job, created = await run_in_threadpool(_create_from_json, svc, owner, data, idempotency_key)
    else:
        raise ApiError(
            415,
            "unsupported_media_type",
            f"Content-Type {ctype!r}: send application/json or multipart/form-data",
        )
    response.status_code = 201 if created else 200
    response.headers["Location"] = f"/v1/jobs/{job.id}"
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


@router.post(
    "/{job_id}/start",
    summary="Start the job: its capture is validated, then the job is queued",
    description="Answers at once with the job in status validating. Every file is then checked (each "
    "frame decoded): a valid capture moves the job to queued; a capture with problems sends it back to "
    "created with error and problems naming each file (fix them, start again).",
    response_model=JobOut,
    status_code=202,
    responses={
        **_JOB_ERRORS,
        202: {"description": "Validating (the job moves on to queued, or back to created with problems)."},
        409: {**_E, "description": "Not in status created, or uploads still in progress."},
        422: {**_E, "description": "The options name a stage this build lacks."},
    },
)
def start_job(job_id: JobId, owner: Owner, svc: Svc, background: BackgroundTasks) -> JobOut:
    job = owned_job(svc, job_id, owner)
    jobs.start_job(svc, job=job)
    background.add_task(jobs.validate_and_queue, svc, job.id)
    return job_out(svc, owned_job(svc, job_id, owner))


@router.post(
    "/{job_id}/rerun",
    summary="Rerun a finished job with changed options, from a stage on (no re-upload)",
    description="Creates and queues a new job on the same capture. Its options are the source job's with "
    "the given changes merged in; the stages before from_stage are not computed again: their outputs "
    "come from the source job's cache (which must have been made with the same options for them).",
    response_model=JobOut,
    status_code=201,
    openapi_extra={
        "requestBody": {
            "required": False,
            "content": {"application/json": {"schema": {"$ref": "#/components/schemas/JobRerun"}}},
        }
    },
    responses={
        **_JOB_ERRORS,
        201: {"description": "Created and queued."},
        413: {**_E, "description": "The body is over 1 MiB."},
        409: {**_E, "description": "The source has not finished, or lacks a cached stage for these options."},
        429: {**_E, "description": "Too many unfinished jobs for this key."},
    },
)
async def rerun_job(request: Request, job_id: JobId, response: Response, owner: Owner, svc: Svc) -> JobOut:
    data = await _read_json_body(request)
    try:
        body = JobRerun.model_validate(data)
    except ValidationError as exc:
        raise invalid(exc, ("body",)) from exc
    source = await run_in_threadpool(owned_job, svc, job_id, owner)
    job = await run_in_threadpool(
        partial(
            jobs.rerun_job,
            svc,
            owner=owner,
            source=source,
            changes=body.options,
            from_stage=body.from_stage,
            label=body.label,
        )
    )
    response.headers["Location"] = f"/v1/jobs/{job.id}"
    return await run_in_threadpool(job_out, svc, job)


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
    jobs.cancel_job(svc, job=owned_job(svc, job_id, owner))
    return job_out(svc, owned_job(svc, job_id, owner))


@router.delete(
    "/{job_id}",
    summary="Delete a job and its files (a running job is canceled)",
    status_code=204,
    response_class=Response,
    responses={**_JOB_ERRORS, 204: {"description": "Deleted."}},
)
def delete_job(job_id: JobId, owner: Owner, svc: Svc) -> Response:
    jobs.delete_job(svc, job=owned_job(svc, job_id, owner))
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
