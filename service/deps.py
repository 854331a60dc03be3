"""Shared pieces of the route handlers: the app's state and job lookup."""

from __future__ import annotations

import re
from dataclasses import dataclass

from celery import Celery
from fastapi import Request

from pmvir.result import downloadable_names
from service.errors import ApiError, ErrorItem, not_found
from service.models import JobOut, PartialOut
from service.settings import Settings
from service.storage import JobFiles
from service.store import Job, JobStore

_JOB_ID = re.compile(r"^[0-9a-f]{32}$")


@dataclass
class Services:
    """What the handlers work with (one per app, in ``app.state.services``)."""

    settings: Settings
    store: JobStore
    files: JobFiles
    celery: Celery


def services(request: Request) -> Services:
    return request.app.state.services


def reject_unknown_query(request: Request) -> None:
    """422 for query parameters the route does not declare (like unknown options: named, not ignored)."""
    route = request.scope.get("route")
    dependant = getattr(route, "dependant", None)
    if dependant is None or not request.query_params:
        return
    known = {p.alias for p in _all_query_params(dependant)}
    unknown = sorted(set(request.query_params.keys()) - known)
    if unknown:
        raise ApiError(
            422,
            "validation_error",
            f"unknown query parameter(s): {', '.join(unknown)}",
            errors=[
                ErrorItem(loc=["query", u], msg="unknown query parameter", type="extra_forbidden")
                for u in unknown
            ],
        )


def _all_query_params(dependant):
    yield from dependant.query_params
    for sub in dependant.dependencies:
        yield from _all_query_params(sub)


def owned_job(svc: Services, job_id: str, owner: str) -> Job:
    """The caller's job, or 404 (also for another key's job: its existence is not revealed)."""
    if not _JOB_ID.match(job_id):
        raise not_found("job")
    job = svc.store.get(job_id)
    if job is None or job.owner != owner:
        raise not_found("job")
    return job


def job_out(svc: Services, job: Job) -> JobOut:
    files = list(svc.store.files(job.id).values())
    partial = []
    for path, total in sorted(svc.store.partials(job.id).items()):
        p = svc.files.partial_path(job.id, path)
        received = p.stat().st_size if p.exists() else 0
        partial.append(PartialOut(path=path, received=received, total=total))
    present = svc.files.result_files(job.id)
    results = [n for n in downloadable_names() if n in present]
    deliveries = svc.store.deliveries(job.id) if job.callback_url else None
    return JobOut.of(job, files=files, partial=partial, results=results, deliveries=deliveries)


def path_error(path: str, problem: str) -> ApiError:
    return ApiError(
        422,
        "invalid_path",
        f"path {path!r} {problem}",
        errors=[ErrorItem(file=path, msg=problem, type="invalid_path")],
    )
