"""Request ids and structured logs.

Each HTTP request gets an id: the client's ``X-Request-ID`` when it is a short
token (1-128 of ``A-Z a-z 0-9 . _ -``), else a fresh one; the answer echoes it
in ``X-Request-ID``. The id, and the id of the job being worked on, ride in
context variables, so every log line written while handling the request or
running the job carries them. With ``PMVIR_LOG_FORMAT=json`` the API and the
workers log one JSON object per line: ``time``, ``level``, ``logger``,
``message``, ``request_id``, ``job_id`` (and ``exc`` for a traceback).
"""

from __future__ import annotations

import contextvars
import json
import logging
import re
import time
import uuid
from typing import Any

request_id: contextvars.ContextVar[str] = contextvars.ContextVar("request_id", default="")
job_id: contextvars.ContextVar[str] = contextvars.ContextVar("job_id", default="")

HEADER = "X-Request-ID"
_TOKEN = re.compile(r"^[A-Za-z0-9._-]{1,128}$")


def incoming_request_id(value: str | None) -> str:
    """The client's request id when it is a short token, else a fresh one.

    >>> incoming_request_id("abc-123")
    'abc-123'
    >>> len(incoming_request_id("no spaces allowed"))
    32
    """
    return value if value and _TOKEN.match(value) else uuid.uuid4().hex


class RequestIdMiddleware:
    """ASGI middleware: sets :data:`request_id` for the request and echoes it in the answer."""

    def __init__(self, app: Any):
        self.app = app

    async def __call__(self, scope: dict[str, Any], receive: Any, send: Any) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        given = None
        for name, value in scope.get("headers", []):
            if name == b"x-request-id":
                given = value.decode("latin-1")
                break
        rid = incoming_request_id(given)
        token = request_id.set(rid)

        async def send_with_id(message: dict[str, Any]) -> None:
            if message["type"] == "http.response.start":
                headers = [(k, v) for k, v in message.get("headers", []) if k.lower() != b"x-request-id"]
                message = {**message, "headers": [*headers, (b"x-request-id", rid.encode())]}
            await send(message)

        try:
            await self.app(scope, receive, send_with_id)
        finally:
            request_id.reset(token)


class ContextFilter(logging.Filter):
    """Adds ``request_id`` and ``job_id`` from the context to every record."""

    def filter(self, record: logging.LogRecord) -> bool:
        record.request_id = getattr(record, "request_id", "") or request_id.get()
        record.job_id = getattr(record, "job_id", "") or job_id.get()
        return True


class JsonFormatter(logging.Formatter):
    """One JSON object per line."""

    def format(self, record: logging.LogRecord) -> str:
        doc: dict[str, Any] = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created))
            + f".{int(record.msecs):03d}Z",
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
            "request_id": getattr(record, "request_id", "") or request_id.get(),
            "job_id": getattr(record, "job_id", "") or job_id.get(),
        }
        if record.exc_info:
            doc["exc"] = self.formatException(record.exc_info)
        return json.dumps(doc, ensure_ascii=False)


def configure_logging(fmt: str) -> None:
    """With ``fmt == "json"``, send every record (root, uvicorn's and Celery's loggers) through one
    JSON-lines handler on stderr; with ``text`` leave logging as the servers set it up."""
    if fmt != "json":
        return
    handler = logging.StreamHandler()
    handler.addFilter(ContextFilter())
    handler.setFormatter(JsonFormatter())
    root = logging.getLogger()
    for h in list(root.handlers):
        root.removeHandler(h)
    root.addHandler(handler)
    if root.level == logging.NOTSET or root.level > logging.INFO:
        root.setLevel(logging.INFO)
    for name in ("uvicorn", "uvicorn.error", "uvicorn.access", "celery"):
        lg = logging.getLogger(name)
        lg.handlers = []
        lg.propagate = True
