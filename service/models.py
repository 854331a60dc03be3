"""Request and response bodies of the HTTP API (they make the OpenAPI document)."""

from __future__ import annotations

from datetime import UTC, datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from pmvir.config import PipelineConfig
from service.store import FileInfo, Job

Status = Literal["created", "queued", "running", "succeeded", "failed", "canceled"]
ResultName = Literal["mesh.ply", "illumination.json", "report.json", "result.zip"]


class JobCreate(BaseModel):
    """POST /v1/jobs (JSON): a new, empty job."""

    model_config = ConfigDict(extra="forbid")

    options: PipelineConfig = Field(
        default_factory=PipelineConfig,
        description="Pipeline options: the same typed configuration the CLI uses. Unknown keys and "
        "out-of-range values are 422 errors naming each field.",
    )
    label: str | None = Field(default=None, max_length=200, description="Free text shown in job lists.")


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


def _dt(t: float | None) -> datetime | None:
    return None if t is None else datetime.fromtimestamp(t, tz=UTC)


class JobOut(BaseModel):
    """A job: its state, progress and files."""

    id: str
    status: Status = Field(description="created, queued, running, succeeded, failed or canceled.")
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
    error: str | None = Field(default=None, description="Why the job failed.")
    cancel_requested: bool = False
    deliveries: int = Field(ge=0, description="How many times a worker started the job.")
    files: list[FileOut] = Field(default_factory=list, description="Complete capture files.")
    partial_uploads: list[PartialOut] = Field(default_factory=list)
    results: list[ResultName] = Field(default_factory=list, description="Result files ready to download.")

    @classmethod
    def of(cls, job: Job, *, files: list[FileInfo], partial: list[PartialOut], results: list[str]) -> JobOut:
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
            cancel_requested=job.cancel_requested,
            deliveries=job.deliveries,
            files=[FileOut.of(f) for f in files],
            partial_uploads=partial,
            results=results,
        )


class JobSummary(BaseModel):
    """A job in a list."""

    id: str
    status: Status
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


class Health(BaseModel):
    status: Literal["ok"] = "ok"


class Ready(BaseModel):
    status: Literal["ok", "unavailable"]
    redis: bool = Field(description="Redis answered PING.")
    storage: bool = Field(description="The storage root is writable.")
