"""Presigned URLs of the bucket: capture bytes and result bytes go between the client and the
bucket, not through the API.

* Downloads (``PMVIR_S3_PRESIGN_DOWNLOADS``): ``GET /v1/jobs/{id}/result/{name}`` answers 307 to a
  presigned GET of the result file; the client follows it (with its ``Range``, without its key).
* Uploads (``PMVIR_S3_PRESIGN_UPLOADS``): ``POST /v1/jobs/{id}/uploads`` with the file's path and
  size (and sha256) checks them against the limits as a PUT would and answers a presigned PUT of
  ``jobs/<id>/incoming/<upload id>``; the client PUTs the bytes there, then ``POST
  .../uploads/{upload id}/complete``. Only then does the API look at what landed: the size the
  offer named, the sha256 (computed from the bucket's copy, and the one the client named if
  any), the manifest for ``capture.json``, the job's limits; a file that passes is copied into
  the capture and recorded as a PUT's would be. Nothing in ``incoming/`` is ever read by a
  validation or a worker, so a PUT to an offer's URL after the job started changes nothing.

A client that PUTs again while the API checks cannot slip other bytes in: the checked version
is copied (conditional on its ETag) to ``incoming/<upload id>.checked``, which the offer's URL
cannot write, before it is recorded and copied into the capture.
"""

from __future__ import annotations

import hashlib
import time
import uuid
from datetime import UTC, datetime

from service.deps import Services, path_error
from service.errors import ApiError, ErrorItem, conflict, not_found, too_large
from service.models import UploadOfferIn, UploadOfferOut, UploadOut
from service.storage import capture_path_problem
from service.storage_s3 import S3JobFiles
from service.store import FileInfo, Gate, Job, JobStatus
from service.uploads import begin_upload, check_job_limits, check_manifest, file_limit


def _bucket(svc: Services, enabled: bool) -> S3JobFiles | None:
    return svc.files if enabled and isinstance(svc.files, S3JobFiles) else None


def uploads_offered(svc: Services) -> bool:
    return _bucket(svc, svc.settings.s3_presign_uploads) is not None


def downloads_redirected(svc: Services) -> bool:
    return _bucket(svc, svc.settings.s3_presign_downloads) is not None


def result_redirect(svc: Services, job: Job, name: str, *, media_type: str) -> str | None:
    """A presigned GET of the job's result file, when downloads are redirected and the file exists."""
    bucket = _bucket(svc, svc.settings.s3_presign_downloads)
    if bucket is None:
        return None
    return bucket.result_url(job.id, name, filename=name, media_type=media_type, ttl=svc.settings.s3_presign_ttl)


def offer_upload(svc: Services, job: Job, spec: UploadOfferIn) -> UploadOfferOut:
    """A presigned PUT for one capture file, after the checks a PUT of that size would pass first.

    Raises:
        ApiError: 409 (not offered by this server, or the job takes no uploads), 413, 422 (path).
    """
    bucket = _bucket(svc, svc.settings.s3_presign_uploads)
    if bucket is None:
        raise ApiError(
            409,
            "not_offered",
            "this server takes uploads through PUT /v1/jobs/{id}/files/{path} only",
        )
    problem = capture_path_problem(spec.path)
    if problem:
        raise path_error(spec.path, problem)
    if job.status is not JobStatus.CREATED:
        raise conflict(f"the job is {job.status}; files can only be uploaded while it is created")
    limit = file_limit(svc, spec.path)
    if spec.size > limit:
        raise too_large(f"{spec.path}: {spec.size} bytes, more than the limit of {limit}")
    check_job_limits(svc, job, spec.path, spec.size)
    upload_id = uuid.uuid4().hex
    ttl = svc.settings.s3_presign_ttl
    expires_at = time.time() + ttl
    svc.store.offer_upload(
        job.id, upload_id, {"path": spec.path, "size": spec.size, "sha256": spec.sha256, "expires_at": expires_at}
    )
    return UploadOfferOut(
        id=upload_id,
        url=bucket.upload_url(job.id, upload_id, ttl=ttl),
        headers={"Content-Type": "application/octet-stream"},
        complete=f"/v1/jobs/{job.id}/uploads/{upload_id}/complete",
        expires_at=datetime.fromtimestamp(expires_at, tz=UTC),
    )


def complete_upload(svc: Services, job: Job, upload_id: str) -> UploadOut:
    """Check what landed at an offer's URL and put it in the capture (one offer, one file).

    Raises:
        ApiError: 404 (no such offer, or it expired), 409 (nothing landed yet, it changed while
            checked, or the job takes no uploads now), 413 (job limits), 422 (size, sha256 or
            manifest not as offered).
    """
    bucket = _bucket(svc, svc.settings.s3_presign_uploads)
    spec = svc.store.offer(job.id, upload_id) if bucket is not None else None
    if bucket is None or spec is None:
        raise not_found("upload")
    path = str(spec["path"])
    token = uuid.uuid4().hex
    begin_upload(svc, job, token)  # the job cannot start while the file is checked and placed
    try:
        landed = bucket.landed(job.id, upload_id)
        if landed is None:
            raise conflict(f"{path}: nothing was uploaded to the offer's URL yet")
        size, etag = landed
        if size != int(spec["size"]):
            raise _mismatch(path, f"{size} bytes landed, the offer was for {spec['size']}")
        check_job_limits(svc, job, path, size)
        digest, head = hashlib.sha256(), b""
        for chunk in bucket.landed_bytes(job.id, upload_id, etag):
            digest.update(chunk)
            if path == "capture.json":
                head += chunk
        sha256 = digest.hexdigest()
        if spec.get("sha256") and sha256 != spec["sha256"]:
            raise _mismatch(path, f"sha256 {sha256} landed, the offer named {spec['sha256']}")
        if path == "capture.json":
            check_manifest(head)
        try:
            bucket.freeze_landed(job.id, upload_id, etag)
        except bucket.s3.exceptions.ClientError as exc:
            raise conflict(f"{path}: the upload changed while it was checked; complete it again") from exc
        _place(svc, bucket, job, upload_id, token, FileInfo(path=path, size=size, sha256=sha256))
    finally:
        svc.store.upload_end(job.id, token)
    svc.store.drop_offer(job.id, upload_id)
    return UploadOut(path=path, size=size, complete=True, sha256=sha256)


def _mismatch(path: str, msg: str) -> ApiError:
    return ApiError(
        422, "upload_mismatch", f"{path}: {msg}", errors=[ErrorItem(file=path, msg=msg, type="upload_mismatch")]
    )


def _place(svc: Services, bucket: S3JobFiles, job: Job, upload_id: str, token: str, info: FileInfo) -> None:
    """Record the file and copy the checked version into the capture, one upload of a path at a time."""
    with svc.store.path_lock(job.id, info.path):
        why = svc.store.upload_commit(job.id, token, info)
        if why is Gate.GONE:
            raise not_found("job")
        if why is not Gate.OK:
            bucket.drop_landed(job.id, upload_id)
            raise conflict(f"the job is {why}; the upload was discarded")
        bucket.place_landed(job.id, upload_id, info.path)
        svc.store.clear_partial(job.id, info.path)
