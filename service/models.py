"""Request and response bodies of the HTTP API (they make the OpenAPI document)."""

from __future__ import annotations

from datetime import UTC, datetime
from enum import StrEnum
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from pmvir.config import PipelineConfig
from pmvir.result import downloadable_names
from pmvir.stages import Stage
from service.errors import ErrorItem
from service.store import FileInfo, Job, JobStatus

#: The result files served by name (pmvir.result's table: single files, folders as .zip, result.zip).
ResultName = StrEnum("ResultName", {n: n for n in downloadable_names()})  # type: ignore[misc]  # not literal


class JobCreate(BaseModel):
    """POST /v1/jobs (JSON): a new, empty job."""

    model_config = ConfigDict(extra="forbid")

    options: PipelineConfig = Field(
        default_factory=PipelineConfig,
        description="Pipeline options: the same typed configuration the CLI uses. Unknown keys and "
        "out-of-range values are 422 errors naming each field.",
    )
    label: str | None = Field(default=None, max_length=200, description="Free text shown in job lists.")
    callback_url: str | None = Field(
        default=None,
        max_length=2000,
        pattern=r"^https?://",
        description="http(s) URL POSTed a signed JSON event when the job ends (succeeded, failed or "
        "canceled); its host must be one of the service's PMVIR_WEBHOOK_HOSTS.",
    )
    result_ttl: int | None = Field(
        default=None,
        ge=0,
        le=10 * 365 * 86400,
        description="Seconds after it finished that the job is deleted (0: kept); default PMVIR_RESULT_TTL.",
    )


class JobRerun(BaseModel):
    """POST /v1/jobs/{id}/rerun: a new job on the same capture, from a stage on."""

    model_config = ConfigDict(extra="forbid")

    options: dict[str, Any] = Field(
        default_factory=dict,
        description="Changes to the source job's options, merged into them key by key (nested groups "
        'merged, lists replaced), e.g. {"refine": {"solver": {"max_iterations": 40}}}; the result is validated '
        "as PipelineConfig.",
    )
    from_stage: Stage = Field(
        default=Stage.REFINE,
        description="The first stage to compute. The earlier stages' outputs are reused from the source "
        "job, which must have run them with the same options for them (else 409 naming the group).",
    )
    label: str | None = Field(default=None, max_length=200, description="Default: the source job's label.")


class FileOut(BaseModel):
    """A complete capture file of a job."""

    path: str = Field(description="Path inside the capture, e.g. frames/000.png.")
    size: int = Field(ge=0, description="Bytes.")
    sha256: str = Field(pattern=r"^[0-9a-f]{64}$", description="SHA-256 of the file's bytes (hex).")

    @classmethod
    def of(cls, f: FileInfo) -> FileOut:
        return cls(path=f.path, size=f.size, sha256=f.sha256)


class PartialOut(BaseModel):
    """A resumable upload that is not complete yet."""

    path: str
    received: int = Field(ge=0, description="Bytes the server holds; the next Content-Range starts here.")
    total: int = Field(ge=0, description="The total size the upload declared.")


class UploadOut(BaseModel):
    """PUT /v1/jobs/{id}/files/{path}: what the server now holds for the path."""

    path: str
    size: int = Field(ge=0, description="Bytes received for this path so far (all of it when complete).")
    complete: bool = Field(description="False after a Content-Range part that is not the last.")
    sha256: str | None = Field(
        default=None, description="SHA-256 of the complete file (hex); null while partial."
    )


class UploadOfferIn(BaseModel):
    """POST /v1/jobs/{id}/uploads: the file a presigned upload is asked for."""

    model_config = ConfigDict(extra="forbid")

    path: str = Field(max_length=300, description="Path inside the capture, as for PUT /files/{path}.")
    size: int = Field(ge=0, le=1 << 40, description="The file's size in bytes; what lands must have it.")
    sha256: str | None = Field(
        default=None,
        pattern=r"^[0-9a-f]{64}$",
        description="The file's SHA-256 (hex); when given, what lands must have it.",
    )


class UploadOfferOut(BaseModel):
    """A presigned upload: PUT the file's bytes to ``url`` with ``headers``, then POST ``complete``."""

    id: str = Field(description="The upload's id.")
    url: str = Field(description="Presigned URL of the bucket; send no Authorization header to it.")
    method: Literal["PUT"] = "PUT"
    headers: dict[str, str] = Field(description="Headers the PUT must carry (they are signed).")
    complete: str = Field(description="Where to POST when the bytes are up (a path of this API).")
    expires_at: datetime = Field(description="When the URL and the offer expire.")


def _dt(t: float | None) -> datetime | None:
    return None if t is None else datetime.fromtimestamp(t, tz=UTC)


class WebhookAttempt(BaseModel):
    """One delivery attempt of a job's webhook event."""

    attempt: int = Field(ge=1)
    time: float = Field(description="Unix seconds when the attempt was made.")
    status_code: int | None = Field(default=None, description="The receiver's HTTP status, if it answered.")
    error: str | None = Field(default=None, description="Why the attempt failed, if it did.")
    ok: bool = Field(description="The receiver answered 2xx.")


class WebhookOut(BaseModel):
    """A job's callback URL and what became of its event."""

    url: str
    deliveries: list[WebhookAttempt] = Field(default_factory=list)


class JobOut(BaseModel):
    """A job: its state, progress and files."""

    id: str
    status: JobStatus = Field(
        description="created, validating (the capture is being checked), queued, running, succeeded, "
        "failed or canceled."
    )
    stage: str | None = Field(default=None, description="The pipeline stage running or last run.")
    progress: float = Field(ge=0.0, le=1.0, description="Overall fraction done, 0..1; never goes backwards.")
    label: str | None = None
    options: dict[str, Any] = Field(description="The validated pipeline options (PipelineConfig).")
    created_at: datetime
    updated_at: datetime
    queued_at: datetime | None = None
    started_at: datetime | None = None
    finished_at: datetime | None = None
    stage_timings: dict[str, float] = Field(default_factory=dict, description="Seconds spent per stage.")
    error: str | None = Field(
        default=None, description="Why the job failed, or why its capture was refused (back to created)."
    )
    problems: list[ErrorItem] = Field(
        default_factory=list,
        description="What the last validation found wrong in the capture, each naming its file; the job "
        "went back to created (fix the files, start again).",
    )
    cancel_requested: bool = False
    deliveries: int = Field(ge=0, description="How many times a worker started the job.")
    files: list[FileOut] = Field(default_factory=list, description="Complete capture files.")
    partial_uploads: list[PartialOut] = Field(default_factory=list)
    results: list[ResultName] = Field(
        default_factory=list, description="Result files ready to download."
    )
    source_job: str | None = Field(default=None, description="For a rerun: the job whose capture it uses.")
    result_ttl: int = Field(ge=0, description="Seconds after it finished that the job is deleted (0: kept).")
    expires_at: datetime | None = Field(default=None, description="When the finished job will be deleted.")
    webhook: WebhookOut | None = Field(default=None, description="The job's callback and its deliveries.")
    resume_from: Stage | None = Field(
        default=None, description="For a rerun: the first stage computed (earlier ones came from the cache)."
    )

    @classmethod
    def of(
        cls,
        job: Job,
        *,
        files: list[FileInfo],
        partial: list[PartialOut],
        results: list[str],
        deliveries: list[dict[str, Any]] | None = None,
    ) -> JobOut:
        expires = job.finished_at + job.ttl if job.ttl and job.finished_at else None
        webhook = None
        if job.callback_url:
            webhook = WebhookOut(
                url=job.callback_url, deliveries=[WebhookAttempt(**d) for d in deliveries or []]
            )
        return cls(
            id=job.id,
            status=job.status,
            stage=job.stage,
            progress=job.progress,
            label=job.label,
            options=job.options,
            created_at=_dt(job.created_at),
            updated_at=_dt(job.updated_at),
            queued_at=_dt(job.queued_at),
            started_at=_dt(job.started_at),
            finished_at=_dt(job.finished_at),
            stage_timings=job.stage_timings,
            error=job.error,
            problems=[ErrorItem.model_validate(p) for p in job.problems],
            cancel_requested=job.cancel_requested,
            deliveries=job.deliveries,
            files=[FileOut.of(f) for f in files],
            partial_uploads=partial,
            results=results,
            source_job=job.source_job,
            result_ttl=job.ttl,
            expires_at=_dt(expires),
            webhook=webhook,
            resume_from=job.resume_from,
        )


class JobSummary(BaseModel):
    """A job in a list."""

    id: str
    status: JobStatus
    stage: str | None = None
    progress: float = Field(ge=0.0, le=1.0)
    label: str | None = None
    created_at: datetime
    updated_at: datetime
    error: str | None = None

    @classmethod
    def of(cls, job: Job) -> JobSummary:
        return cls(
            id=job.id,
            status=job.status,
            stage=job.stage,
            progress=job.progress,
            label=job.label,
            created_at=_dt(job.created_at),
            updated_at=_dt(job.updated_at),
            error=job.error,
        )


class JobList(BaseModel):
    """GET /v1/jobs: the caller's jobs, newest first."""

    jobs: list[JobSummary]
    total: int = Field(ge=0, description="How many jobs the caller has in all.")
    offset: int = Field(ge=0)
    limit: int = Field(ge=1)


class LogLine(BaseModel):
    index: int = Field(ge=0, description="Position in the job's log (use index + 1 as the next since).")
    time: datetime
    message: str


class LogOut(BaseModel):
    """GET /v1/jobs/{id}/log?since=N."""

    lines: list[LogLine]
    next: int = Field(ge=0, description="The since to ask for next.")
    total: int = Field(ge=0, description="Lines in the log so far.")


class WorkerOut(BaseModel):
    """A worker that renewed its heartbeat within the last few seconds."""

    name: str
    pid: int
    version: str
    cuda: bool = Field(description="torch sees a CUDA device in this worker.")
    cuda_devices: int = Field(ge=0)
    seen_at: float = Field(description="Unix seconds of its last heartbeat.")


class DiskOut(BaseModel):
    """The storage disk, in bytes, and what the jobs hold (walked at most every 30 s)."""

    total: int = Field(ge=0)
    used: int = Field(ge=0)
    free: int = Field(ge=0)
    jobs_bytes: int = Field(ge=0, description="Bytes under the job folders (captures, caches, results).")
    jobs: int = Field(ge=0, description="Job folders on disk.")


class InfoOut(BaseModel):
    """GET /v1/info."""

    version: str = Field(description="pmvir's version.")
    stages: list[str] = Field(description="The pipeline's stages, in order.")
    limits: dict[str, float] = Field(description="Size, count, time and retention limits (PMVIR_* settings).")
    queue: str = Field(description="The Celery queue jobs go to.")
    webhooks_enabled: bool = Field(description="Callback URLs are accepted (PMVIR_WEBHOOK_HOSTS is set).")
    presigned_uploads: bool = Field(
        default=False, description="POST /v1/jobs/{id}/uploads offers presigned PUTs of the bucket."
    )
    presigned_downloads: bool = Field(
        default=False, description="Result downloads answer 307 to a presigned GET of the bucket."
    )
    admin: bool = Field(default=False, description="The key has the admin role; the figures below are for it alone.")
    queue_length: int | None = Field(default=None, ge=0, description="Jobs waiting in the queue for a worker (admin).")
    workers_online: int | None = Field(default=None, ge=0, description="Workers with a live heartbeat (admin).")
    workers: list[WorkerOut] | None = Field(default=None, description="The live workers (admin).")
    cuda_available: bool | None = Field(default=None, description="At least one online worker has CUDA (admin).")
    disk: DiskOut | None = Field(default=None, description="The storage's use (admin).")


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class Ready(BaseModel):
    status: Literal["ok", "unavailable"]
    redis: bool = Field(description="Redis answered PING.")
    storage: bool = Field(description="The storage root is writable.")
