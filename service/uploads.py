"""Receiving one capture file: streamed to disk, bounded, hashed, resumable.

``PUT /v1/jobs/{id}/files/{path}`` streams the body to a temporary file in
1 MiB writes (never the whole file in memory), hashing as it goes, and
renames it into the capture when complete. With ``Content-Range: bytes
a-b/total`` the body is one part of a resumable upload: part ``a == 0``
(re)starts the partial file, a later part must start where the partial file
ends (else 409 with ``received``), and the part that brings the file to
``total`` bytes completes it.

Limits (413): the file size (``max_manifest_bytes`` for capture.json,
``max_frame_bytes`` otherwise), the job's bytes (``max_job_bytes``) and frame
count (``max_frames``); 507 when the disk would keep less than
``min_free_bytes`` free.
"""

from __future__ import annotations

import hashlib
import os
import re
import time
import uuid
from dataclasses import dataclass
from pathlib import Path

from fastapi import Request
from starlette.concurrency import run_in_threadpool
from starlette.requests import ClientDisconnect

from pmvir.errors import ManifestError
from pmvir.io.manifest import parse_manifest
from service.deps import Services, path_error
from service.errors import ApiError, ErrorItem, conflict, not_found, too_large
from service.models import UploadOut
from service.storage import capture_path_problem, is_frame, sha256_file
from service.store import FileInfo, Gate, Job

_CONTENT_RANGE = re.compile(r"^bytes (\d+)-(\d+)/(\d+)$")
_FLUSH = 1 << 20
_TOUCH_EVERY = 10.0


@dataclass(frozen=True)
class ContentRange:
    first: int
    last: int
    total: int


def parse_content_range(value: str) -> ContentRange:
    """``bytes a-b/total`` (inclusive a..b, total known) or 400."""
    m = _CONTENT_RANGE.match(value.strip())
    if not m:
        raise ApiError(400, "bad_content_range", f"Content-Range {value!r} is not 'bytes first-last/total'")
    first, last, total = (int(g) for g in m.groups())
    if last < first or last >= total:
        raise ApiError(400, "bad_content_range", f"Content-Range {value!r}: need first <= last < total")
    return ContentRange(first, last, total)


def file_limit(svc: Services, path: str) -> int:
    s = svc.settings
    return s.max_manifest_bytes if path == "capture.json" else s.max_frame_bytes


def check_job_limits(svc: Services, job: Job, path: str, incoming: int) -> None:
    """413 when ``incoming`` bytes at ``path`` break the job's byte or frame limits; 507 on low disk."""
    s = svc.settings
    files = svc.store.files(job.id)
    others = sum(f.size for p, f in files.items() if p != path)
    if others + incoming > s.max_job_bytes:
        raise too_large(
            f"the job would hold {others + incoming} bytes, more than the limit of {s.max_job_bytes}"
        )
    if is_frame(path) and path not in files:
        frames = {p for p in files if is_frame(p)} | {p for p in svc.store.partials(job.id) if is_frame(p)}
        frames.discard(path)
        if len(frames) >= s.max_frames:
            raise too_large(f"the job already has {len(frames)} frames, the limit is {s.max_frames}")
    check_free_disk(svc, incoming)


def check_free_disk(svc: Services, incoming: int) -> None:
    free = svc.files.free_bytes()
    if free - incoming < svc.settings.min_free_bytes:
        raise ApiError(
            507,
            "insufficient_storage",
            f"the storage disk has {free} bytes free; uploads need {svc.settings.min_free_bytes} "
            "to stay free",
        )


class _Sink:
    """Writes buffered chunks to an open file (in a worker thread), hashing when asked to."""

    def __init__(self, path: Path, mode: str, *, hash_it: bool):
        self.path = path
        self.f = open(path, mode)  # noqa: SIM115 - the sink owns the file until close()
        self.h = hashlib.sha256() if hash_it else None
        self.buf = bytearray()
        self.n = 0

    def hexdigest(self) -> str:
        """SHA-256 of what was written (hex); only for a sink opened with ``hash_it``."""
        if self.h is None:
            raise RuntimeError(f"{self.path}: this sink was opened without hashing")
        return self.h.hexdigest()

    def _write(self, data: bytes) -> None:
        self.f.write(data)
        if self.h is not None:
            self.h.update(data)

    async def add(self, chunk: bytes) -> None:
        self.buf += chunk
        self.n += len(chunk)
        if len(self.buf) >= _FLUSH:
            data, self.buf = bytes(self.buf), bytearray()
            await run_in_threadpool(self._write, data)

    async def close(self, *, sync: bool) -> None:
        data, self.buf = bytes(self.buf), bytearray()

        def finish() -> None:
            if data:
                self._write(data)
            self.f.flush()
            if sync:
                os.fsync(self.f.fileno())
            self.f.close()

        await run_in_threadpool(finish)

    def abort(self) -> None:
        if not self.f.closed:
            self.f.close()


async def _pump(
    request: Request,
    sink: _Sink,
    *,
    limit: int,
    job_room: int,
    path: str,
    svc: Services,
    job_id: str,
    token: str,
    over_limit: str | None = None,
) -> None:
    """Copy the request body into ``sink``; 413 past ``limit`` bytes or the job's remaining room."""
    last_touch = time.monotonic()
    async for chunk in request.stream():
        if not chunk:
            continue
        if sink.n + len(chunk) > limit:
            if over_limit:
                raise ApiError(400, "bad_content_range", f"{path}: {over_limit}")
            raise too_large(f"{path}: more than the limit of {limit} bytes")
        if sink.n + len(chunk) > job_room:
            raise too_large(f"{path}: the job would exceed its limit of {svc.settings.max_job_bytes} bytes")
        await sink.add(chunk)
        if time.monotonic() - last_touch > _TOUCH_EVERY:
            await run_in_threadpool(svc.store.upload_touch, job_id, token)
            last_touch = time.monotonic()


def _job_room(svc: Services, job_id: str, path: str) -> int:
    files = svc.store.files(job_id)
    return svc.settings.max_job_bytes - sum(f.size for p, f in files.items() if p != path)


def begin_upload(svc: Services, job: Job, token: str) -> None:
    """Register an upload in progress (the job cannot start meanwhile); 404 or 409 when it takes none."""
    why = svc.store.upload_begin(job.id, token)
    if why is Gate.OK:
        return
    if why is Gate.GONE:
        raise not_found("job")
    if why is Gate.STARTING:
        raise conflict("the job is being started; it takes no more uploads")
    raise conflict(f"the job is {why}; files can only be uploaded while it is created")


def check_manifest(data: bytes | Path) -> None:
    """422 naming the problem when capture.json (its bytes, or the file holding them) is invalid."""
    try:
        parse_manifest(data.read_bytes() if isinstance(data, Path) else data)
    except ManifestError as exc:
        raise ApiError(
            422,
            "invalid_manifest",
            str(exc),
            errors=[ErrorItem(file="capture.json", msg=exc.problem, type="ManifestError")],
        ) from exc


def _commit(svc: Services, job: Job, token: str, tmp: Path, info: FileInfo) -> None:
    """Record the file and rename it into the capture, one upload of a path at a time."""
    with svc.store.path_lock(job.id, info.path):
        why = svc.store.upload_commit(job.id, token, info)
        if why is not Gate.OK:
            tmp.unlink(missing_ok=True)
            if why is Gate.GONE:
                raise not_found("job")
            raise conflict(f"the job is {why}; the upload was discarded")
        try:
            svc.files.place(job.id, tmp, info.path)
        except FileNotFoundError as exc:  # the job was deleted meanwhile: leave nothing behind
            if svc.store.get(job.id) is None:
                svc.files.delete(job.id)
            raise not_found("job") from exc
        svc.files.partial_path(job.id, info.path).unlink(missing_ok=True)
        svc.store.upload_end(job.id, token)


async def receive_file(
    request: Request, svc: Services, job: Job, path: str, content_range: str | None
) -> tuple[int, UploadOut]:
    """Handle one PUT of a capture file; returns (status code, body)."""
    problem = capture_path_problem(path)
    if problem:
        raise path_error(path, problem)
    limit = file_limit(svc, path)
    length = request.headers.get("content-length")
    declared = int(length) if length and length.isdigit() else None
    rng = parse_content_range(content_range) if content_range else None
    if rng is not None:
        if rng.total > limit:
            raise too_large(f"{path}: {rng.total} bytes, more than the limit of {limit}")
        if declared is not None and declared > rng.last - rng.first + 1:
            raise ApiError(400, "bad_content_range", "the body is longer than its Content-Range")
        await run_in_threadpool(check_job_limits, svc, job, path, rng.total)
    else:
        if declared is not None and declared > limit:
            raise too_large(f"{path}: {declared} bytes, more than the limit of {limit}")
        await run_in_threadpool(check_job_limits, svc, job, path, declared or 0)

    token = uuid.uuid4().hex
    await run_in_threadpool(begin_upload, svc, job, token)
    try:
        if rng is None:
            return 200, await _whole(request, svc, job, path, limit, token)
        return await _part(request, svc, job, path, rng, token)
    except ClientDisconnect as exc:
        raise ApiError(400, "client_disconnected", f"{path}: the client went away mid-upload") from exc
    finally:
        await run_in_threadpool(svc.store.upload_end, job.id, token)


async def _whole(request: Request, svc: Services, job: Job, path: str, limit: int, token: str) -> UploadOut:
    tmp = await run_in_threadpool(svc.files.incoming_path, job.id)
    sink = _Sink(tmp, "wb", hash_it=True)
    try:
        room = await run_in_threadpool(_job_room, svc, job.id, path)
        await _pump(request, sink, limit=limit, job_room=room, path=path, svc=svc, job_id=job.id, token=token)
        await sink.close(sync=True)
        if path == "capture.json":
            await run_in_threadpool(check_manifest, tmp)
        info = FileInfo(path=path, size=sink.n, sha256=sink.hexdigest())
        await run_in_threadpool(_commit, svc, job, token, tmp, info)
        await run_in_threadpool(svc.store.clear_partial, job.id, path)
    except BaseException:
        sink.abort()
        tmp.unlink(missing_ok=True)
        raise
    return UploadOut(path=path, size=info.size, complete=True, sha256=info.sha256)


def _partial_state(svc: Services, job_id: str, path: str) -> tuple[Path, int, int | None]:
    p = svc.files.partial_path(job_id, path)
    return p, (p.stat().st_size if p.exists() else 0), svc.store.partial_total(job_id, path)


def _reset_partial(svc: Services, job_id: str, path: str, total: int) -> Path:
    p = svc.files.partial_path(job_id, path)
    p.parent.mkdir(parents=True, exist_ok=True)
    p.write_bytes(b"")
    svc.store.set_partial(job_id, path, total)
    return p


async def _part(
    request: Request, svc: Services, job: Job, path: str, rng: ContentRange, token: str
) -> tuple[int, UploadOut]:
    if rng.first == 0:
        part = await run_in_threadpool(_reset_partial, svc, job.id, path, rng.total)
        have = 0
    else:
        part, have, total = await run_in_threadpool(_partial_state, svc, job.id, path)
        if total != rng.total or have != rng.first:
            raise conflict(
                f"{path}: the server holds {have} bytes of this upload"
                + ("" if total in (None, rng.total) else f" of a {total}-byte file")
                + f"; the part must start at byte {have}",
                received=have,
            )
    sink = _Sink(part, "ab", hash_it=False)
    try:
        room = await run_in_threadpool(_job_room, svc, job.id, path)
        await _pump(
            request,
            sink,
            limit=min(rng.last - rng.first + 1, rng.total - have),
            job_room=room - have,
            path=path,
            svc=svc,
            job_id=job.id,
            token=token,
            over_limit="the body is longer than its Content-Range",
        )
    except ClientDisconnect:
        await sink.close(sync=False)  # keep what arrived: the client resumes from there
        raise
    except BaseException:
        sink.abort()
        raise
    await sink.close(sync=True)
    size = have + sink.n
    if size < rng.total:
        return 202, UploadOut(path=path, size=size, complete=False)
    if path == "capture.json":
        await run_in_threadpool(check_manifest, part)
    digest = await run_in_threadpool(sha256_file, part)
    tmp = await run_in_threadpool(svc.files.incoming_path, job.id)
    await run_in_threadpool(part.replace, tmp)
    info = FileInfo(path=path, size=size, sha256=digest)
    await run_in_threadpool(_commit, svc, job, token, tmp, info)
    return 200, UploadOut(path=path, size=size, complete=True, sha256=digest)
