"""The job record's types: its status, the store's answers, and the job as stored."""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any


class JobStatus(StrEnum):
    """Where a job is in its life: created -> validating -> queued -> running -> one of the terminal states."""

    CREATED = "created"
    VALIDATING = "validating"
    QUEUED = "queued"
    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"
    CANCELED = "canceled"

    @property
    def terminal(self) -> bool:
        """The job has ended (succeeded, failed or canceled) and never changes again."""
        return self in TERMINAL


TERMINAL = frozenset({JobStatus.SUCCEEDED, JobStatus.FAILED, JobStatus.CANCELED})


class Gate(StrEnum):
    """The store's answer when an upload or a start asks to go ahead (else the job's status)."""

    OK = "ok"
    GONE = "gone"
    UPLOADING = "uploading"
    STARTING = "starting"


class Claim(StrEnum):
    """What a delivery of a job's task found (:meth:`JobStore.claim`)."""

    OK = "ok"
    GONE = "gone"
    DONE = "done"
    NOT_QUEUED = "not_queued"
    BUSY = "busy"
    EXHAUSTED = "exhausted"


def gate(answer: str) -> Gate | JobStatus:
    return Gate(answer) if answer in Gate.__members__.values() else JobStatus(answer)


@dataclass(frozen=True)
class IdempotentJob:
    """The job an Idempotency-Key was already bound to, and the fingerprint of the request that made it."""

    job_id: str
    fingerprint: str


@dataclass(frozen=True)
class FileInfo:
    """A complete capture file of a job."""

    path: str
    size: int
    sha256: str


@dataclass
class Job:
    """A job as stored (times are Unix seconds)."""

    id: str
    owner: str
    status: JobStatus
    options: dict[str, Any]
    created_at: float
    updated_at: float
    label: str | None = None
    stage: str | None = None
    progress: float = 0.0
    queued_at: float | None = None
    started_at: float | None = None
    finished_at: float | None = None
    error: str | None = None
    cancel_requested: bool = False
    deliveries: int = 0
    run_id: str = ""
    stage_timings: dict[str, float] = field(default_factory=dict)
    source_job: str | None = None
    resume_from: str | None = None
    ttl: int = 0
    callback_url: str | None = None
    problems: list[dict[str, Any]] = field(default_factory=list)

    @classmethod
    def from_hash(cls, h: dict[str, str]) -> Job:
        def opt_float(name: str) -> float | None:
            v = h.get(name)
            return float(v) if v not in (None, "") else None

        return cls(
            id=h["id"],
            owner=h["owner"],
            status=JobStatus(h["status"]),
            options=json.loads(h.get("options") or "{}"),
            created_at=float(h["created_at"]),
            updated_at=float(h.get("updated_at") or h["created_at"]),
            label=h.get("label") or None,
            stage=h.get("stage") or None,
            progress=float(h.get("progress") or 0.0),
            queued_at=opt_float("queued_at"),
            started_at=opt_float("started_at"),
            finished_at=opt_float("finished_at"),
            error=h.get("error") or None,
            cancel_requested=h.get("cancel") == "1",
            deliveries=int(h.get("deliveries") or 0),
            run_id=h.get("run_id") or "",
            stage_timings=json.loads(h.get("stage_timings") or "{}"),
            source_job=h.get("source_job") or None,
            resume_from=h.get("resume_from") or None,
            ttl=int(h.get("ttl") or 0),
            callback_url=h.get("callback_url") or None,
            problems=json.loads(h.get("problems") or "[]"),
        )
