"""File downloads with HTTP Range support (RFC 9110 section 14).

One byte range per request (``bytes=a-b``, ``bytes=a-``, ``bytes=-n``) is
answered 206 with ``Content-Range``; a range that starts past the end is 416
with a JSON body and ``Content-Range: bytes */size``. Several ranges, or a
Range header this server does not parse, are ignored and the whole file is
sent (200), which the RFC allows. ``If-Range`` with a stale ETag also gets the
whole file, so a resumed download never splices two versions.
"""

from __future__ import annotations

import os
import re
from collections.abc import AsyncIterator
from pathlib import Path

import anyio
from fastapi import Request
from fastapi.responses import JSONResponse, StreamingResponse

from service.errors import ErrorBody

_RANGE = re.compile(r"^bytes=(\d*)-(\d*)$")
_CHUNK = 1 << 20


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


async def _stream(path: Path, first: int, last: int) -> AsyncIterator[bytes]:
    remaining = last - first + 1
    async with await anyio.open_file(path, "rb") as f:
        await f.seek(first)
        while remaining > 0:
            chunk = await f.read(min(_CHUNK, remaining))
            if not chunk:
                break
            remaining -= len(chunk)
            yield chunk


def file_response(request: Request, path: Path, *, media_type: str, filename: str):
    """A 200/206/416 answer for ``path``, honouring Range and If-Range."""
    st = os.stat(path)
    size = st.st_size
    etag = f'"{size:x}-{st.st_mtime_ns:x}"'
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
        return StreamingResponse(_stream(path, 0, size - 1), media_type=media_type, headers=headers)
    first, last = wanted
    headers["Content-Range"] = f"bytes {first}-{last}/{size}"
    headers["Content-Length"] = str(last - first + 1)
    return StreamingResponse(
        _stream(path, first, last), status_code=206, media_type=media_type, headers=headers
    )
