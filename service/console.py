"""The web console at ``/ui/``, offline API docs at ``/docs`` and ``/redoc``, and the result listing.

Everything the browser loads is served here: the console's own files from
``service/static/ui/`` and the JavaScript libraries (three.js, Swagger UI,
ReDoc) from ``service/static/node_modules/``, which ``make setup`` fills with
``npm ci`` from the committed ``package-lock.json``. Nothing comes from a CDN.

The console is a static page: it signs in with an API key kept in the tab's
session storage and talks to the public ``/v1`` API with a Bearer header, like
any client. Two ``/v1`` endpoints defined here serve it (and any client):
``GET /v1/jobs/{id}/results`` lists every file of a job's result, and
``GET /v1/jobs/{id}/results/{path}`` serves one of them (previews and
residual images live in folders, so they need a path).
"""

from __future__ import annotations

import functools
import mimetypes
from pathlib import Path
from typing import Annotated

from fastapi import APIRouter, Depends, Request
from fastapi import Path as PathParam
from fastapi.responses import FileResponse, HTMLResponse, Response
from pydantic import BaseModel, Field

from pmvir.result import RESULT_ZIP, result_file
from service.auth import require_owner
from service.deps import Services, owned_job, reject_unknown_query, services
from service.errors import ApiError
from service.ranges import file_response
from service.routes_jobs import _E, _JOB_ERRORS, JobId
from service.storage import registered_results

STATIC = Path(__file__).resolve().parent / "static"
UI = STATIC / "ui"
NODE_MODULES = STATIC / "node_modules"

#: The files of npm packages the pages load, by their path under node_modules (also their URL under
#: /ui/vendor/); three.js modules keep their layout so that their relative imports resolve.
VENDOR_FILES = (
    "three/build/three.module.js",
    "three/examples/jsm/controls/OrbitControls.js",
    "three/examples/jsm/loaders/GLTFLoader.js",
    "three/examples/jsm/loaders/PLYLoader.js",
    "three/examples/jsm/utils/BufferGeometryUtils.js",
    "swagger-ui-dist/swagger-ui-bundle.js",
    "swagger-ui-dist/swagger-ui.css",
    "redoc/bundles/redoc.standalone.js",
)
SWAGGER_JS, REDOC_JS = VENDOR_FILES[5], VENDOR_FILES[7]

Owner = Annotated[str, Depends(require_owner)]
Svc = Annotated[Services, Depends(services)]

api = APIRouter(prefix="/v1/jobs", tags=["files"], dependencies=[Depends(reject_unknown_query)])
pages = APIRouter(include_in_schema=False)


class ResultEntry(BaseModel):
    """One file of a job's result."""

    path: str = Field(description="Path inside the result, e.g. mesh.glb or previews/000_int.png.")
    size: int = Field(ge=0, description="Bytes.")
    media_type: str
    description: str = Field(description="What the file (or the folder it is in) holds.")
    stage: str = Field(description="The pipeline stage that wrote it.")


class ResultListing(BaseModel):
    """GET /v1/jobs/{id}/results: every file of the job's result (empty before it finished)."""

    files: list[ResultEntry]


def _entry_for(path: str) -> tuple[str, str, str]:
    """(media type, description, stage) of a result path (a file of a folder takes its folder's)."""
    if path == RESULT_ZIP:
        return "application/zip", "every file of the result in one zip", "report"
    top = path.split("/")[0] + ("/" if "/" in path else "")
    entry = result_file(top)
    if entry.is_folder:
        media = mimetypes.guess_type(path)[0] or "application/octet-stream"
        return media, entry.description, entry.stage
    return entry.media_type, entry.description, entry.stage


def result_paths(svc: Services, job_id: str) -> list[str]:
    """Every file of the job's published result (registered in RESULT_FILES), and result.zip."""
    present = svc.files.result_files(job_id)
    paths = registered_results(list(present))
    if RESULT_ZIP in present:
        paths.append(RESULT_ZIP)
    return paths


@api.get(
    "/{job_id}/results",
    summary="List every file of a job's result",
    description="Each file the finished run wrote (files inside previews/, residuals/, poses/ singly) with its "
    "size and media type; GET /v1/jobs/{id}/results/{path} downloads one. Empty while the job has no result.",
    response_model=ResultListing,
    responses=_JOB_ERRORS,
)
def list_results(job_id: JobId, owner: Owner, svc: Svc) -> ResultListing:
    job = owned_job(svc, job_id, owner)
    sizes = svc.files.result_files(job.id)
    files = []
    for path in result_paths(svc, job.id):
        media, description, stage = _entry_for(path)
        size = sizes[path]
        files.append(
            ResultEntry(path=path, size=size, media_type=media, description=description, stage=stage)
        )
    return ResultListing(files=files)


@api.get(
    "/{job_id}/results/{path:path}",
    summary="Download one file of a job's result by its path (HTTP Range supported)",
    description="Any path GET /v1/jobs/{id}/results lists, e.g. mesh.glb, textured.obj, previews/000_aop.png.",
    response_class=Response,
    responses={
        **_JOB_ERRORS,
        200: {"description": "The whole file.", "content": {"application/octet-stream": {}}},
        206: {"description": "The requested byte range.", "content": {"application/octet-stream": {}}},
        416: {**_E, "description": "The range starts past the end of the file."},
    },
)
def get_result_path(
    job_id: JobId,
    path: Annotated[str, PathParam(description="A path from the listing.", max_length=300)],
    request: Request,
    owner: Owner,
    svc: Svc,
) -> Response:
    job = owned_job(svc, job_id, owner)
    if path not in result_paths(svc, job.id):  # the listing is the allow-list: no traversal, no stray files
        raise ApiError(404, "not_found", f"the result has no file {path!r} (job {job.status})")
    media, _, _ = _entry_for(path)
    blob = svc.files.result_blob(job.id, path)
    if blob is None:
        raise ApiError(404, "not_found", f"the result has no file {path!r} (job {job.status})")
    return file_response(request, blob, media_type=media, filename=path.split("/")[-1])


def _missing_assets(what: str) -> HTMLResponse:
    return HTMLResponse(
        f"<!doctype html><title>pmvir</title><p>{what} is not installed on this server: run "
        "<code>make setup</code> (it runs <code>npm ci</code> in service/static).</p>",
        status_code=503,
    )


def _vendor(path: Path, media_type: str) -> Response:
    if not path.is_file():
        return Response(f"{path.name} is not installed: run make setup (npm ci in service/static)", 503)
    return FileResponse(path, media_type=media_type, headers={"Cache-Control": "public, max-age=86400"})


@pages.get("/ui", response_class=HTMLResponse)
@pages.get("/ui/", response_class=HTMLResponse)
@pages.get("/ui/jobs/{job_id}", response_class=HTMLResponse)
def console_page(job_id: str | None = None) -> Response:
    """The console's one page; the script reads the job id from the address."""
    return FileResponse(UI / "index.html", media_type="text/html", headers={"Cache-Control": "no-cache"})


@pages.get("/ui/static/{name}")
def console_asset(name: str) -> Response:
    path = UI / name
    if "/" in name or name.startswith(".") or not path.is_file():
        return Response("not found", 404)
    media = mimetypes.guess_type(name)[0] or "application/octet-stream"
    if name.endswith(".js"):
        media = "text/javascript"
    return FileResponse(path, media_type=media, headers={"Cache-Control": "no-cache"})


#: ReDoc's sidebar shows a logo loaded from Redocly's CDN; it is served pointing at an empty image instead.
_REDOC_CDN_LOGO = b"https://cdn.redoc.ly/redoc/logo-mini.svg"
_EMPTY_SVG = b"data:image/svg+xml,%3Csvg xmlns='http://www.w3.org/2000/svg'/%3E"


@functools.lru_cache(maxsize=1)
def _redoc_bundle(mtime_ns: int) -> bytes:
    """The ReDoc bundle with its one CDN address replaced (cached per file version)."""
    return (NODE_MODULES / REDOC_JS).read_bytes().replace(_REDOC_CDN_LOGO, _EMPTY_SVG)


@pages.get("/ui/vendor/{path:path}")
def vendor_file(path: str) -> Response:
    if path not in VENDOR_FILES:
        return Response("not found", 404)
    if path == REDOC_JS and (NODE_MODULES / path).is_file():
        body = _redoc_bundle((NODE_MODULES / path).stat().st_mtime_ns)
        return Response(
            body, media_type="text/javascript", headers={"Cache-Control": "public, max-age=86400"}
        )
    return _vendor(NODE_MODULES / path, "text/css" if path.endswith(".css") else "text/javascript")


_SWAGGER = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{title} - Swagger UI</title>
<link rel="stylesheet" href="/ui/vendor/swagger-ui-dist/swagger-ui.css"></head>
<body><div id="swagger-ui"></div>
<script src="/ui/vendor/swagger-ui-dist/swagger-ui-bundle.js"></script>
<script src="/ui/static/docs.js"></script>
</body></html>
"""

_REDOC = """<!doctype html>
<html lang="en"><head><meta charset="utf-8"><title>{title} - ReDoc</title>
<meta name="viewport" content="width=device-width, initial-scale=1"></head>
<body><redoc spec-url="/openapi.json" disable-search="false"></redoc>
<script src="/ui/vendor/redoc/bundles/redoc.standalone.js"></script>
</body></html>
"""


@pages.get("/docs", response_class=HTMLResponse)
def swagger_ui(request: Request) -> Response:
    """Swagger UI from the swagger-ui-dist npm package (no CDN)."""
    if not (NODE_MODULES / SWAGGER_JS).is_file():
        return _missing_assets("Swagger UI")
    return HTMLResponse(_SWAGGER.format(title=request.app.title))


@pages.get("/redoc", response_class=HTMLResponse)
def redoc(request: Request) -> Response:
    """ReDoc from the redoc npm package (no CDN)."""
    if not (NODE_MODULES / REDOC_JS).is_file():
        return _missing_assets("ReDoc")
    return HTMLResponse(_REDOC.format(title=request.app.title))
