"""GET /v1/info: what the service is, its limits, its queue, its workers and its disk."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Depends

import pmvir
from pmvir.config import OPTION_MAGNITUDE_LIMIT
from pmvir.io.frames import MAX_FRAME_PIXELS
from service.auth import require_owner
from service.deps import Services, reject_unknown_query, services
from service.models import DiskOut, InfoOut, WorkerOut
from service.presigned import downloads_redirected, uploads_offered
from service.routes_jobs import _COMMON

router = APIRouter(prefix="/v1", tags=["info"], dependencies=[Depends(reject_unknown_query)])

#: The settings a client may want to know before sending a capture.
LIMITS = (
    "max_frame_bytes",
    "max_frames",
    "max_job_bytes",
    "max_jobs_in_flight",
    "max_manifest_bytes",
    "max_zip_bytes",
    "max_zip_members",
    "max_zip_ratio",
    "min_free_bytes",
    "job_soft_time_limit",
    "result_ttl",
    "max_log_lines",
)


@router.get(
    "/info",
    summary="Version, stages and limits; for an admin key also the queue, workers, CUDA and storage use",
    response_model=InfoOut,
    responses=_COMMON,
)
def info(
    owner: Annotated[str, Depends(require_owner)], svc: Annotated[Services, Depends(services)]
) -> InfoOut:
    from pmvir.stages import STAGES

    s = svc.settings
    limits: dict[str, float] = {name: getattr(s, name) for name in LIMITS}
    limits["max_frame_pixels"] = MAX_FRAME_PIXELS
    limits["option_magnitude"] = OPTION_MAGNITUDE_LIMIT
    out = InfoOut(
        version=pmvir.__version__,
        stages=[str(st) for st in STAGES],
        limits=limits,
        queue=s.queue,
        webhooks_enabled=bool(s.webhook_hosts),
        presigned_uploads=uploads_offered(svc),
        presigned_downloads=downloads_redirected(svc),
    )
    if owner not in s.keyring.admins:  # the service-wide figures are the operator's
        return out
    workers = [WorkerOut.model_validate(w) for w in svc.store.workers()]
    return out.model_copy(
        update={
            "admin": True,
            "queue_length": svc.store.queue_length(s.queue),
            "workers_online": len(workers),
            "workers": workers,
            "cuda_available": any(w.cuda for w in workers),
            "disk": DiskOut(**svc.files.usage()),
        }
    )
