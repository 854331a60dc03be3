"""HTTP errors: every failure is a proper status code with a JSON :class:`ErrorBody`.

The service raises :class:`ApiError` (with the status it means); library errors
(:mod:`pmvir.errors`) and request validation errors are mapped here too, so no
handler ever answers 200 with an error inside, and no error escapes as HTML or
plain text.
"""

from __future__ import annotations

import logging
from typing import Any

import redis
from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, Field, ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.requests import ClientDisconnect

from pmvir.errors import CanceledError, CaptureError, ConfigError, PmvirError

log = logging.getLogger("pmvir.service")


class ErrorItem(BaseModel):
    """One problem: a request field (``loc``) or a capture file (``file``)."""

    loc: list[str | int] | None = Field(
        default=None, description='Where in the request, e.g. ["body", "options", "decode", "noise_floor"].'
    )
    file: str | None = Field(default=None, description="The capture file the problem is in.")
    msg: str = Field(description="What was expected and what came.")
    type: str | None = Field(default=None, description="Machine-readable kind of problem.")


class ErrorBody(BaseModel):
    """The body of every error response."""

    error: str = Field(description='Machine-readable error code, e.g. "not_found", "validation_error".')
    message: str = Field(description="Human-readable summary.")
    errors: list[ErrorItem] = Field(default_factory=list, description="Each problem, when there are several.")
    received: int | None = Field(
        default=None,
        description="For a resumable upload whose Content-Range "
        "does not continue the partial file: bytes the server holds.",
    )


class ApiError(Exception):
    """An error answer: ``status`` with an :class:`ErrorBody`."""

    def __init__(
        self,
        status: int,
        code: str,
        message: str,
        *,
        errors: list[ErrorItem] | None = None,
        headers: dict[str, str] | None = None,
        received: int | None = None,
    ):
        super().__init__(message)
        self.status = status
        self.body = ErrorBody(error=code, message=message, errors=errors or [], received=received)
        self.headers = headers


def invalid(exc: ValidationError, prefix: tuple[str, ...], message: str = "invalid request") -> ApiError:
    """A 422 naming every field pydantic refused, under ``prefix`` (e.g. ("body", "options"))."""
    items = [
        ErrorItem(loc=[*prefix, *e["loc"]], msg=e["msg"], type=e["type"])
        for e in exc.errors(include_url=False)
    ]
    names = ", ".join(".".join(str(p) for p in i.loc or ()) for i in items)
    return ApiError(422, "validation_error", f"{message}: {names}", errors=items)


def not_found(what: str) -> ApiError:
    return ApiError(404, "not_found", f"{what} not found")


def conflict(message: str, **kw: Any) -> ApiError:
    return ApiError(409, "conflict", message, **kw)


def too_large(message: str) -> ApiError:
    return ApiError(413, "too_large", message)


def unprocessable(message: str, errors: list[ErrorItem] | None = None) -> ApiError:
    return ApiError(422, "validation_error", message, errors=errors)


def _json(status: int, body: ErrorBody, headers: dict[str, str] | None = None) -> JSONResponse:
    return JSONResponse(
        status_code=status, content=body.model_dump(mode="json", exclude_none=True), headers=headers
    )


def _field_errors(exc: RequestValidationError) -> list[ErrorItem]:
    items = []
    for err in exc.errors():
        items.append(
            ErrorItem(
                loc=[p if isinstance(p, (str, int)) else str(p) for p in err.get("loc", ())],
                msg=str(err.get("msg", "invalid")),
                type=str(err.get("type", "value_error")),
            )
        )
    return items


_STATUS_CODES = {
    400: "bad_request",
    401: "unauthorized",
    403: "forbidden",
    404: "not_found",
    405: "method_not_allowed",
    406: "not_acceptable",
    409: "conflict",
    411: "length_required",
    413: "too_large",
    415: "unsupported_media_type",
    416: "range_not_satisfiable",
    422: "validation_error",
    429: "too_many_requests",
    503: "unavailable",
}


def unmatched_route_message(method: str, path: str) -> str:
    """Why no route matches: the path as received, and the likely cause."""
    shown = repr(path[:200])
    if any(ord(c) < 0x20 or ord(c) == 0x7F for c in path):
        why = "it contains a control character (a newline, tab, ...), which no route or file name accepts"
    elif path.startswith("/v1/jobs/") and "/files/" in path:
        why = "a capture file path is capture.json, frames/<name>.<ext>, masks/<name>.png or gt/..."
    elif path.startswith("/v1/"):
        why = "see /docs or /openapi.json for the routes"
    else:
        why = "the API lives under /v1 (see /docs)"
    return f"no route matches {method} {shown}: {why}"


def install_error_handlers(app: FastAPI) -> None:
    """Map ApiError, request validation, library errors and stray exceptions to JSON answers."""

    @app.exception_handler(ApiError)
    async def _api_error(request: Request, exc: ApiError) -> JSONResponse:
        return _json(exc.status, exc.body, exc.headers)

    @app.exception_handler(RequestValidationError)
    async def _validation(request: Request, exc: RequestValidationError) -> JSONResponse:
        items = _field_errors(exc)
        names = ", ".join(".".join(str(p) for p in i.loc or ()) for i in items)
        return _json(
            422, ErrorBody(error="validation_error", message=f"invalid request: {names}", errors=items)
        )

    @app.exception_handler(StarletteHTTPException)
    async def _http(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        code = _STATUS_CODES.get(exc.status_code, "error")
        message = str(exc.detail)
        if exc.status_code == 404 and message == "Not Found":  # the router found no route
            message = unmatched_route_message(request.method, request.scope.get("path", ""))
        return _json(exc.status_code, ErrorBody(error=code, message=message), getattr(exc, "headers", None))

    @app.exception_handler(ClientDisconnect)
    async def _disconnect(request: Request, exc: ClientDisconnect) -> JSONResponse:
        # A malformed body (e.g. a bad chunk size) ends the request as a disconnect: no traceback.
        log.info("client went away on %s %s", request.method, request.url.path)
        return _json(400, ErrorBody(error="client_disconnected", message="the request body ended early"))

    @app.exception_handler(ConfigError)
    async def _config(request: Request, exc: ConfigError) -> JSONResponse:
        return _json(422, ErrorBody(error="config_error", message=str(exc)))

    @app.exception_handler(CaptureError)
    async def _capture(request: Request, exc: CaptureError) -> JSONResponse:
        return _json(
            422,
            ErrorBody(
                error="capture_error",
                message=str(exc),
                errors=[ErrorItem(file=exc.path, msg=exc.problem, type=type(exc).__name__)],
            ),
        )

    @app.exception_handler(CanceledError)
    async def _canceled(request: Request, exc: CanceledError) -> JSONResponse:
        return _json(409, ErrorBody(error="canceled", message=str(exc)))

    @app.exception_handler(PmvirError)
    async def _pmvir(request: Request, exc: PmvirError) -> JSONResponse:
        return _json(422, ErrorBody(error=type(exc).__name__, message=str(exc)))

    @app.exception_handler(redis.ConnectionError)
    @app.exception_handler(redis.TimeoutError)
    async def _redis_down(request: Request, exc: Exception) -> JSONResponse:
        log.warning("job store unreachable on %s %s: %s", request.method, request.url.path, exc)
        return _json(
            503,
            ErrorBody(error="unavailable", message="job store unreachable; retry later"),
            {"Retry-After": "5"},
        )

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s %s", request.method, request.url.path)
        return _json(500, ErrorBody(error="internal_error", message="internal server error"))
