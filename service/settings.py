"""Service configuration, read from ``PMVIR_*`` environment variables.

One :class:`Settings` object configures the API, the Celery worker and the
job store. Every field is an environment variable named ``PMVIR_`` + the field
name in upper case (``PMVIR_REDIS_URL``, ``PMVIR_STORAGE``, ...); byte sizes are
plain integers. The README's "Service" section lists them.
"""

from __future__ import annotations

from functools import cached_property
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from service.keys import KeyRing

MiB = 1024**2
GiB = 1024**3


class Settings(BaseSettings):
    """Everything the API and the worker are told (environment variables ``PMVIR_*``)."""

    model_config = SettingsConfigDict(env_prefix="PMVIR_", extra="ignore", frozen=True)

    redis_url: str = Field(
        default="redis://localhost:6379/0",
        description="Redis: the Celery broker and the job store (the service's own keys under key_prefix).",
    )
    storage: Path = Field(
        default=Path("pmvir-storage"),
        description="Storage root on disk; each job lives in <storage>/jobs/<job id>/.",
    )
    storage_url: str = Field(
        default="",
        description="s3://bucket/prefix: jobs live in an S3-compatible bucket shared by every host "
        "(empty: the local folder PMVIR_STORAGE).",
    )
    s3_endpoint_url: str = Field(
        default="", description="Endpoint of the S3-compatible store (MinIO, Ceph RGW); empty: AWS."
    )
    s3_public_endpoint_url: str = Field(
        default="",
        description="Endpoint of the bucket as clients reach it, for presigned URLs; empty: "
        "PMVIR_S3_ENDPOINT_URL.",
    )
    s3_presign_downloads: bool = Field(
        default=False,
        description="With a bucket: a result download answers 307 to a presigned GET of the bucket, "
        "so the bytes bypass the API (clients must reach the bucket).",
    )
    s3_presign_uploads: bool = Field(
        default=False,
        description="With a bucket: POST /v1/jobs/{id}/uploads offers a presigned PUT of the bucket, "
        "so the bytes bypass the API; the API checks what landed when the upload is completed.",
    )
    s3_presign_ttl: int = Field(
        default=900, ge=60, le=7 * 24 * 3600, description="Seconds a presigned URL is valid."
    )
    scratch: Path | None = Field(
        default=None,
        description="This process's local working folder with a bucket (uploads, a run's inputs and "
        "outputs); default: PMVIR_STORAGE.",
    )
    cache_key: str = Field(
        default="",
        description="Secret the workers sign and verify the stage cache with (HMAC-SHA256); with a "
        "bucket and no key no stage cache is kept.",
    )
    api_keys: Annotated[tuple[str, ...], NoDecode] = Field(
        default=(),
        description="Comma-separated API keys (Authorization: Bearer <key>): tenant=scrypt:<salt>:<hash> "
        "entries (python -m service.keys TENANT), or plain keys. Empty: every request is 401.",
    )
    key_prefix: str = Field(default="pmvir", min_length=1, description="Prefix of the service's Redis keys.")
    queue: str = Field(default="pmvir", min_length=1, description="Celery queue the jobs go to.")

    # -- limits
    max_frame_bytes: int = Field(
        default=256 * MiB, gt=0, description="Largest frame, mask or ground-truth file."
    )
    max_frames: int = Field(default=1000, gt=0, description="Most frame files in one job.")
    max_job_bytes: int = Field(default=16 * GiB, gt=0, description="Most bytes of capture files in one job.")
    max_jobs_in_flight: int = Field(
        default=16, gt=0, description="Most unfinished jobs (created, queued or running) per API key."
    )
    min_free_bytes: int = Field(
        default=2 * GiB,
        ge=0,
        description="Uploads are refused (507) when the storage disk has less free space.",
    )
    max_manifest_bytes: int = Field(default=16 * MiB, gt=0, description="Largest capture.json.")
    max_zip_bytes: int = Field(
        default=512 * MiB, gt=0, description="Largest zipped capture sent to POST /v1/jobs."
    )
    max_zip_members: int = Field(default=2100, gt=0, description="Most members in a zipped capture.")
    max_zip_ratio: float = Field(
        default=200.0,
        gt=1.0,
        description="Largest uncompressed/compressed ratio of a zip member over 1 MiB, and of the whole zip.",
    )

    # -- worker
    job_soft_time_limit: int = Field(
        default=6 * 3600, gt=0, description="Seconds after which a running job is stopped and marked failed."
    )
    job_hard_time_limit: int = Field(
        default=6 * 3600 + 120,
        gt=0,
        description="Seconds after which the worker process running a job is killed.",
    )
    visibility_timeout: int = Field(
        default=7 * 3600,
        gt=0,
        description="Seconds before Redis redelivers an unacknowledged job message "
        "(longer than the hard limit).",
    )
    lease_seconds: float = Field(
        default=30.0,
        gt=0.5,
        description="A running job's heartbeat lease in seconds; a job whose lease lapses "
        "(its worker died) is requeued.",
    )
    max_deliveries: int = Field(
        default=3,
        ge=1,
        description="Most times a worker may start a job; a job whose worker kept dying fails "
        "at the next start.",
    )
    idempotency_ttl: int = Field(
        default=24 * 3600, gt=0, description="Seconds an Idempotency-Key is remembered."
    )
    job_threads: int = Field(
        default=0,
        ge=0,
        description="Threads of one job (torch, OpenMP, BLAS, OpenCV, pycolmap); 0: the cores this "
        "worker may use divided by its concurrency.",
    )
    job_memory: int = Field(
        default=0,
        ge=0,
        description="Bytes of address space one job may use (RLIMIT_AS of its process); 0: no limit.",
    )
    log_format: Literal["text", "json"] = Field(
        default="text",
        description="text, or json: one JSON object per log line with time, level, logger, message, "
        "request_id and job_id.",
    )
    admin_keys: Annotated[tuple[str, ...], NoDecode] = Field(
        default=(),
        description="Comma-separated keys with the admin role (entries as in api_keys): GET /v1/info "
        "shows them the service-wide figures (queue, workers, storage use). They are API keys too.",
    )
    max_log_lines: int = Field(default=10_000, gt=0, description="Most log lines kept per job.")

    # -- retention
    result_ttl: int = Field(
        default=0,
        ge=0,
        le=10 * 365 * 86400,
        description="Seconds after it finished that a job (record, capture, result) is deleted; 0 keeps "
        "jobs until deleted by hand. A job's own result_ttl option overrides it.",
    )
    upload_ttl: int = Field(
        default=24 * 3600,
        ge=0,
        description="Seconds a created job may sit without uploads or a start before it is deleted "
        "(its slot freed); 0: never.",
    )
    max_queued: int = Field(
        default=0,
        ge=0,
        description="Most jobs waiting in the queue; a start beyond it is answered 503 with Retry-After. "
        "0: no cap.",
    )
    janitor_interval: float = Field(
        default=60.0, gt=0.0, le=86400.0, description="Seconds between a worker's retention sweeps."
    )

    # -- webhooks
    webhook_hosts: Annotated[tuple[str, ...], NoDecode] = Field(
        default=(),
        description="Comma-separated host names (or host:port) a job's callback_url may point to. Empty: "
        "callbacks are refused (422).",
    )
    webhook_secret: str = Field(
        default="",
        description="Key of the HMAC-SHA256 signature of every webhook body (X-Pmvir-Signature). Needed "
        "when webhook_hosts is set.",
    )
    webhook_attempts: int = Field(
        default=5, ge=1, le=20, description="Most delivery attempts of one webhook event."
    )
    webhook_backoff: float = Field(
        default=2.0,
        gt=0.0,
        le=3600.0,
        description="Seconds before the second delivery attempt; doubled after each failure.",
    )
    webhook_timeout: float = Field(default=10.0, gt=0.0, le=120.0, description="Seconds per delivery attempt.")

    @field_validator("api_keys", "admin_keys", "webhook_hosts", mode="before")
    @classmethod
    def _split_keys(cls, value: object) -> object:
        if isinstance(value, str):
            return tuple(k.strip() for k in value.split(",") if k.strip())
        return value

    @model_validator(mode="after")
    def _limits_consistent(self) -> Settings:
        if self.job_hard_time_limit <= self.job_soft_time_limit:
            raise ValueError("job_hard_time_limit must be greater than job_soft_time_limit")
        if self.visibility_timeout <= self.job_hard_time_limit:
            raise ValueError("visibility_timeout must be longer than job_hard_time_limit (the longest job)")
        if self.webhook_hosts and not self.webhook_secret:
            raise ValueError("webhook_hosts is set but webhook_secret is empty: webhooks must be signed")
        return self

    @cached_property
    def keyring(self) -> KeyRing:
        """The API and admin keys: which tenant a presented key belongs to (service.keys)."""
        return KeyRing(self.api_keys, self.admin_keys)


def get_settings() -> Settings:
    """Settings from the environment (a new object each call; cheap)."""
    return Settings()
