"""File downloads with HTTP Range support (RFC 9110 section 14).

One byte range per request (``bytes=a-b``, ``bytes=a-``, ``bytes=-n``) is
answered 206 with ``Content-Range``; a range that starts past the end is 416
with a JSON body and ``Content-Range: bytes */size``. Several ranges, or a
Range header this server does not parse, are ignored and the whole file is
sent (200), which the RFC allows. ``If-Range`` with a stale ETag also gets the
whole file, so a resumed download never splices two versions.
"""

from __future__ import annotations

import re
from collections.abc import Iterator

from fastapi import Request
from fastapi.responses import JSONResponse, StreamingResponse

from service.errors import ErrorBody
from service.storage import Blob

_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")


def parse_range(header: str | None, size: int) -> tuple[int, int] | str | None:
    """The inclusive byte range a Range header asks for.

    Returns:
        (first, last) inclusive; None to send the whole file; "unsatisfiable" for a 416.
    """
    if not header:
        return None
    m = _RANGE.match(header.strip().replace(" ", ""))
    if not m:
        return None
    a, b = m.groups()
    if a == "" and b == "":
        return None
    if a == "":
        n = int(b)
        if n == 0:
            return "unsatisfiable"
        return (max(size - n, 0), size - 1) if size else "unsatisfiable"
    first = int(a)
    last = int(b) if b else size - 1
    if b and last < first:
        return None
    if first >= size:
        return "unsatisfiable"
    return first, min(last, size - 1)


def file_response(request: Request, blob: Blob, *, media_type: str, filename: str):
    """A 200/206/416 answer for a stored file, honouring Range and If-Range (streamed from its storage)."""
    size, etag = blob.size, blob.etag
    headers = {
        "Accept-Ranges": "bytes",
        "ETag": etag,
        "Content-Disposition": f'attachment; filename="{filename}"',
    }
    wanted = parse_range(request.headers.get("range"), size)
    if_range = request.headers.get("if-range")
    if wanted is not None and if_range is not None and if_range.strip() != etag:
        wanted = None
    if isinstance(wanted, str):  # "unsatisfiable"
        body = ErrorBody(error="range_not_satisfiable", message=f"the file has {size} bytes")
        return JSONResponse(
            status_code=416,
            content=body.model_dump(exclude_none=True),
            headers={"Content-Range": f"bytes */{size}"},
        )
    if wanted is None:
        headers["Content-Length"] = str(size)
        return StreamingResponse(_whole(blob), media_type=media_type, headers=headers)
    first, last = wanted
    headers["Content-Range"] = f"bytes {first}-{last}/{size}"
    headers["Content-Length"] = str(last - first + 1)
    return StreamingResponse(
        blob.read(first, last), status_code=206, media_type=media_type, headers=headers
    )


def _whole(blob: Blob) -> Iterator[bytes]:
    return blob.read(0, blob.size - 1) if blob.size else iter(())
