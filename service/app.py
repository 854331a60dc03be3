"""The FastAPI application: ``create_app(settings)``.

Run it with ``pmvir serve --host H --port P`` (uvicorn with
``service.app:create_app`` as factory). Nothing connects at creation: Redis is
reached on the first request, so the app starts while Redis is still coming up
(``/readyz`` says when it is there).
"""

from __future__ import annotations

import logging
from typing import Any

from fastapi import FastAPI
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse, PlainTextResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest
from starlette.concurrency import run_in_threadpool

import pmvir
from service import console, routes_files, routes_info, routes_jobs
from service.deps import Services
from service.errors import install_error_handlers
from service.metrics import ServiceCollector
from service.models import Health, JobCreate, JobRerun, Ready
from service.observability import RequestIdMiddleware, configure_logging
from service.queue import make_celery
from service.settings import Settings, get_settings
from service.storage_s3 import open_storage
from service.store import JobStore

log = logging.getLogger("pmvir.service")

DESCRIPTION = """\
Capture-processing service of pmvir: capture rigs upload raw polarization frames, workers run the
pipeline, clients poll and download the result.

Flow: `POST /v1/jobs` (options) -> `PUT /v1/jobs/{id}/files/{path}` for capture.json, each frame and
mask -> `POST /v1/jobs/{id}/start` -> poll `GET /v1/jobs/{id}` -> `GET /v1/jobs/{id}/result/result.zip`.
Every endpoint under /v1 needs `Authorization: Bearer <API key>`. Errors are JSON (`ErrorBody`).
"""


def create_app(settings: Settings | None = None) -> FastAPI:
    """The API, configured by ``settings`` (default: from the PMVIR_* environment)."""
    settings = settings or get_settings()
    configure_logging(settings.log_format)
    app = FastAPI(
        title="pmvir capture-processing service",
        version=pmvir.__version__,
        description=DESCRIPTION,
        openapi_url="/openapi.json",
        docs_url=None,  # /docs and /redoc come from service.console, with their scripts served locally
        redoc_url=None,
    )
    app.state.settings = settings
    app.state.services = Services(
        settings=settings,
        store=JobStore.from_url(settings.redis_url, prefix=settings.key_prefix),
        files=open_storage(settings),
        celery=make_celery(settings),
    )
    if not settings.api_keys:
        log.warning("PMVIR_API_KEYS is empty: every /v1 request will be refused (401)")
    install_error_handlers(app)
    app.include_router(routes_jobs.router)
    app.include_router(routes_files.router)
    app.include_router(routes_info.router)
    app.include_router(console.api)
    app.include_router(console.pages)

    @app.get("/healthz", tags=["health"], summary="The process is up", response_model=Health)
    def healthz() -> Health:
        return Health()

    @app.get(
        "/readyz",
        tags=["health"],
        summary="Redis and storage are reachable",
        response_model=Ready,
        responses={503: {"model": Ready, "description": "Redis or storage is not reachable."}},
    )
    async def readyz() -> Any:
        svc: Services = app.state.services

        def probe() -> Ready:
            try:
                redis_ok = svc.store.ping()
            except Exception:  # noqa: BLE001 - any failure to answer means not ready
                redis_ok = False
            storage_ok = svc.files.writable()
            return Ready(
                status="ok" if redis_ok and storage_ok else "unavailable", redis=redis_ok, storage=storage_ok
            )

        ready = await run_in_threadpool(probe)
        return JSONResponse(status_code=200 if ready.status == "ok" else 503, content=ready.model_dump())

    @app.get(
        "/metrics",
        tags=["health"],
        summary="Prometheus metrics: jobs by state, queue, stage durations, failures, workers, storage",
        response_class=PlainTextResponse,
        responses={200: {"content": {CONTENT_TYPE_LATEST: {"schema": {"type": "string"}}}}},
    )
    def metrics() -> Response:
        return Response(generate_latest(registry), media_type=CONTENT_TYPE_LATEST)

    registry = CollectorRegistry(auto_describe=False)
    registry.register(ServiceCollector(app.state.services))
    app.add_middleware(RequestIdMiddleware)
    app.openapi = lambda: openapi_document(app)  # type: ignore[method-assign]  # FastAPI's override
    return app


def openapi_document(app: FastAPI) -> dict[str, Any]:
    """The app's OpenAPI document, with JobCreate (read by hand in POST /v1/jobs) in its components."""
    if app.openapi_schema:
        return app.openapi_schema
    doc = get_openapi(title=app.title, version=app.version, description=app.description, routes=app.routes)
    schemas = doc.setdefault("components", {}).setdefault("schemas", {})
    for model in (JobCreate, JobRerun):  # bodies the routes read by hand
        schema = model.model_json_schema(ref_template="#/components/schemas/{model}")
        for name, sub in schema.pop("$defs", {}).items():
            schemas.setdefault(name, sub)
        schemas[model.__name__] = schema
    doc["components"]["schemas"] = dict(sorted(schemas.items()))
    app.openapi_schema = doc
    return doc
