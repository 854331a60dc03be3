"""File routes: capture uploads and result downloads."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, Depends, Header, Path, Request, Response
from fastapi.responses import JSONResponse, RedirectResponse
from starlette.concurrency import run_in_threadpool

from pmvir.result import RESULT_ZIP, downloadable_names, result_file
from service.auth import require_owner
from service.deps import Services, owned_job, reject_unknown_query, services
from service.errors import ApiError
from service.models import ResultName, UploadOfferIn, UploadOfferOut, UploadOut
from service.presigned import complete_upload, offer_upload, result_redirect
from service.ranges import file_response
from service.routes_jobs import _E, _JOB_ERRORS, JobId
from service.uploads import receive_file

router = APIRouter(prefix="/v1/jobs", tags=["files"], dependencies=[Depends(reject_unknown_query)])

Owner = Annotated[str, Depends(require_owner)]
Svc = Annotated[Services, Depends(services)]

_BINARY = {"schema": {"type": "string", "format": "binary"}}
#: The capture layout as a pattern, for the document (the handler checks it itself, naming the problem).
CAPTURE_PATH_PATTERN = (
    r"^(capture\.json|gt/mesh\.ply|gt/illumination\.json"
    r"|frames/[A-Za-z0-9_][A-Za-z0-9_.+-]{0,127}"
    r"\.([Pp][Nn][Gg]|[Tt][Ii][Ff][Ff]?|[Dd][Nn][Gg]|[Rr][Aa][Ww]|[Bb][Ii][Nn])"
    r"|masks/[A-Za-z0-9_][A-Za-z0-9_.+-]{0,127}\.[Pp][Nn][Gg])$"
)
_RESULT_CONTENT = {
    "application/octet-stream": _BINARY,
    "application/zip": _BINARY,
    "application/json": {"schema": {}},
}


@router.put(
    "/{job_id}/files/{path:path}",
    summary="Upload capture.json, a frame or a mask (streamed; resumable with Content-Range)",
    description="The body is the file's bytes. The path must be capture.json, "
    "frames/<name>.<png|tif|tiff|dng|raw|bin>, masks/<name>.png, gt/mesh.ply or gt/illumination.json. "
    "Re-uploading a path replaces the file. With Content-Range: bytes first-last/total the body is one "
    "part of a resumable upload: the part that completes the file answers 200 with its sha256, earlier "
    "parts 202; a part that does not continue the partial file is 409 with the bytes received.",
    response_model=UploadOut,
    openapi_extra={"requestBody": {"required": True, "content": {"application/octet-stream": _BINARY}}},
    responses={
        **_JOB_ERRORS,
        202: {"model": UploadOut, "description": "A part of a resumable upload was stored."},
        400: {**_E, "description": "Malformed Content-Range, or body longer than it."},
        409: {**_E, "description": "The job takes no uploads now, or the part does not continue the file."},
        413: {**_E, "description": "The file or the job is over a size or count limit."},
        507: {**_E, "description": "Not enough free disk."},
    },
)
async def upload_file(
    request: Request,
    job_id: JobId,
    path: Annotated[
        str,
        Path(
            description="Path inside the capture, e.g. frames/000.png.",
            json_schema_extra={"pattern": CAPTURE_PATH_PATTERN},
        ),
    ],
    owner: Owner,
    svc: Svc,
    content_range: Annotated[
        str | None,
        Header(
            description="bytes first-last/total, for a resumable upload.",
            max_length=100,
            pattern=r"^bytes [0-9]{1,15}-[0-9]{1,15}/[0-9]{1,15}$",
        ),
    ] = None,
) -> JSONResponse:
    job = await run_in_threadpool(owned_job, svc, job_id, owner)
    status, body = await receive_file(request, svc, job, path, content_range)
    return JSONResponse(status_code=status, content=body.model_dump(mode="json"))


@router.post(
    "/{job_id}/uploads",
    status_code=201,
    summary="Ask for a presigned PUT of the bucket for one capture file (S3 storage, when offered)",
    description="The body names the file's path, size and (optionally) sha256; they are checked as a "
    "PUT of the file would be checked first. The answer's url takes the bytes (PUT, with the answer's "
    "headers and without this API's Authorization); then POST the answer's complete path. "
    "GET /v1/info says whether this server offers it (presigned_uploads); 409 not_offered when not.",
    response_model=UploadOfferOut,
    responses={
        **_JOB_ERRORS,
        400: {**_E, "description": "A body that is not readable JSON."},
        409: {**_E, "description": "Not offered by this server, or the job takes no uploads now."},
        413: {**_E, "description": "The file or the job would be over a size or count limit."},
    },
)
def offer(job_id: JobId, spec: Annotated[UploadOfferIn, Body()], owner: Owner, svc: Svc) -> UploadOfferOut:
    return offer_upload(svc, owned_job(svc, job_id, owner), spec)


@router.post(
    "/{job_id}/uploads/{upload_id}/complete",
    summary="Check a presigned upload's bytes and put them in the capture",
    description="The file that landed at the offer's URL must have the size (and sha256) the offer "
    "named, and capture.json must be a valid manifest; then it is the job's file as after a PUT. "
    "404 for an unknown or expired offer (ask again), 409 while nothing landed.",
    response_model=UploadOut,
    responses={
        **_JOB_ERRORS,
        409: {**_E, "description": "Nothing landed yet, it changed while checked, or the job takes no uploads now."},
        413: {**_E, "description": "The job would be over a size or count limit."},
    },
)
def complete(
    job_id: JobId,
    upload_id: Annotated[str, Path(description="The offer's id.", pattern=r"^[0-9a-f]{32}$")],
    owner: Owner,
    svc: Svc,
) -> UploadOut:
    return complete_upload(svc, owned_job(svc, job_id, owner), upload_id)


@router.get(
    "/{job_id}/result/{name}",
    summary="Download a result file (HTTP Range supported)",
    description=f"{', '.join(downloadable_names()[:-1])}, or {RESULT_ZIP} (every file the run wrote); "
    "a result folder is served as <folder>.zip. "
    "404 while the job has no such file (not finished, or the stage that writes it did not run).",
    response_class=Response,
    responses={
        **_JOB_ERRORS,
        200: {"description": "The whole file.", "content": _RESULT_CONTENT},
        206: {
            "description": "The requested byte range (Content-Range says which); a JSON file's "
            "range is a fragment, not a JSON document.",
            "content": _RESULT_CONTENT,
        },
        307: {
            "description": "With PMVIR_S3_PRESIGN_DOWNLOADS: Location is a presigned GET of the file in "
            "the bucket (send Range there, not the Authorization header)."
        },
        416: {**_E, "description": "The range starts past the end of the file."},
    },
)
def get_result(
    job_id: JobId,
    name: Annotated[ResultName, Path(description="Which result file.")],
    request: Request,
    owner: Owner,
    svc: Svc,
    range_: Annotated[
        str | None,
        Header(
            alias="Range",
            max_length=200,
            description="bytes=first-last, bytes=first- or bytes=-n; "
            "one range (several: the whole file is sent).",
        ),
    ] = None,
):
    job = owned_job(svc, job_id, owner)
    media = "application/zip" if name == RESULT_ZIP else result_file(name).media_type
    url = result_redirect(svc, job, str(name), media_type=media)
    if url is not None:
        return RedirectResponse(url, status_code=307)
    blob = svc.files.result_blob(job.id, name)
    if blob is None:
        raise ApiError(404, "not_found", f"{name} is not available (job {job.status})")
    return file_response(request, blob, media_type=media, filename=str(name))
