"""A small Python client of the capture-processing service (``pmvir serve``).

Example::

    from pmvir.client import PmvirClient

    with PmvirClient("http://localhost:8000", api_key="...") as c:
        job = c.create_job({"stop_after": "decode"})
        c.upload_capture(job["id"], "captures/cup")
        c.start(job["id"])
        job = c.wait(job["id"])
        c.download(job["id"], "result.zip", "out/result.zip")

Every call is retried on connection errors, timeouts, 429, 502, 503 and 504
(honouring ``Retry-After``, exponential backoff otherwise). Creating a job
sends an ``Idempotency-Key``, so a retried create never makes two jobs.
Files larger than ``chunk_size`` are uploaded in ``Content-Range`` parts; after
a failure the upload resumes where the server's partial file ends. Downloads
resume with ``Range`` into ``<dest>.part``. Uploaded files are checked
against the sha256 the server returns.

Errors from the server raise :class:`ServiceError` (a :class:`pmvir.errors.PmvirError`)
with the HTTP status and the JSON error body. Needs only ``httpx`` (``pip install 'pmvir[client]'``).
"""

from __future__ import annotations

import hashlib
import time
import uuid
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Any

import httpx

from pmvir.errors import PmvirError

_RETRY_STATUS = frozenset({429, 502, 503, 504})
TERMINAL = frozenset({"succeeded", "failed", "canceled"})
BytesCallback = Callable[[int], None]


class ServiceError(PmvirError):
    """The service answered an error.

    Attributes:
        status: the HTTP status code.
        code: the body's machine-readable ``error``.
        body: the whole JSON error body (``message``, ``errors``, ...).
    """

    def __init__(self, status: int, body: dict[str, Any] | None, method: str = "", url: str = ""):
        self.status = status
        self.body = body or {}
        self.code = str(self.body.get("error", "error"))
        message = str(self.body.get("message", "")) or f"HTTP {status}"
        items = [
            f"{e.get('file') or '.'.join(str(p) for p in e.get('loc') or [])}: {e.get('msg')}"
            for e in self.body.get("errors", [])
        ]
        detail = f" ({'; '.join(items)})" if items else ""
        super().__init__(f"{method} {url}: HTTP {status} {message}{detail}".strip())


def verify_webhook(
    secret: str, body: bytes, signature: str, *, tolerance: float = 300.0, now: float | None = None
) -> bool:
    """Whether a webhook event is authentic: ``signature`` is its ``X-Pmvir-Signature`` header.

    The header is ``t=<unix seconds>,v1=<hex>`` with ``<hex>`` the HMAC-SHA256, keyed with the
    service's PMVIR_WEBHOOK_SECRET, of ``b"<t>." + body``; events older or newer than ``tolerance``
    seconds are refused (replays).
    """
    import hmac

    fields = dict(part.split("=", 1) for part in signature.split(",") if "=" in part)
    try:
        t = int(fields["t"])
    except (KeyError, ValueError):
        return False
    if abs((time.time() if now is None else now) - t) > tolerance:
        return False
    expected = hmac.new(secret.encode(), f"{t}.".encode() + body, hashlib.sha256).hexdigest()
    return hmac.compare_digest(expected, fields.get("v1", ""))


def sha256_of(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()


def capture_files(root: str | Path) -> list[str]:
    """The files of a capture folder that belong to the capture layout, capture.json first."""
    root = Path(root)
    out = ["capture.json"] if (root / "capture.json").is_file() else []
    for folder in ("frames", "masks"):
        d = root / folder
        if d.is_dir():
            out += sorted(
                f"{folder}/{p.name}" for p in d.iterdir() if p.is_file() and not p.name.startswith(".")
            )
    out += [g for g in ("gt/mesh.ply", "gt/illumination.json") if (root / g).is_file()]
    return out


class PmvirClient:
    """Client of the service's /v1 API.

    Args:
        server: base URL, e.g. ``http://localhost:8000``.
        api_key: sent as ``Authorization: Bearer``.
        timeout: seconds per network operation.
        retries: attempts after the first, per call.
        backoff: first retry delay in seconds (doubles, capped at 30 s).
        chunk_size: files larger than this are uploaded in resumable parts of this size.
        transport: an httpx transport (tests, proxies).
    """

    def __init__(
        self,
        server: str,
        api_key: str,
        *,
        timeout: float = 60.0,
        retries: int = 5,
        backoff: float = 0.5,
        chunk_size: int = 16 << 20,
        transport: httpx.BaseTransport | None = None,
    ):
        self.retries = retries
        self.backoff = backoff
        self.chunk_size = chunk_size
        self.http = httpx.Client(
            base_url=server.rstrip("/"),
            timeout=timeout,
            transport=transport,
            headers={"Authorization": f"Bearer {api_key}"},
        )
        #: Whether the server offers presigned uploads (asked once, at the first upload).
        self._presigned: bool | None = None
        #: A client without the API key, for presigned URLs of the bucket.
        self._bucket = httpx.Client(timeout=timeout)

    def close(self) -> None:
        self.http.close()
        self._bucket.close()

    def __enter__(self) -> PmvirClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- plumbing

    def _delay(self, attempt: int, response: httpx.Response | None) -> float:
        if response is not None:
            ra = response.headers.get("retry-after", "")
            if ra.isdigit():
                return min(float(ra), 30.0)
        return min(self.backoff * (2**attempt), 30.0)

    def request(
        self,
        method: str,
        url: str,
        *,
        ok: tuple[int, ...] = (200,),
        body: Callable[[], Any] | None = None,
        **kw: Any,
    ) -> httpx.Response:
        """Send with retries (``body()`` makes a fresh body per attempt); ServiceError unless status in ok."""
        attempt = 0
        while True:
            response = None
            try:
                if body is not None:
                    kw["content"] = body()
                response = self.http.request(method, url, **kw)
            except httpx.TransportError:
                if attempt >= self.retries:
                    raise
            else:
                if response.status_code in ok:
                    return response
                if response.status_code not in _RETRY_STATUS or attempt >= self.retries:
                    raise self._error(response)
            time.sleep(self._delay(attempt, response))
            attempt += 1

    @staticmethod
    def _error(response: httpx.Response) -> ServiceError:
        try:
            body = response.json()
        except ValueError:
            body = {"message": response.text[:200]}
        return ServiceError(
            response.status_code,
            body if isinstance(body, dict) else None,
            response.request.method,
            str(response.request.url.path),
        )

    # -- jobs

    def create_job(
        self,
        options: dict[str, Any] | None = None,
        *,
        label: str | None = None,
        idempotency_key: str | None = None,
    ) -> dict[str, Any]:
        """A new empty job (status created). ``options``: PipelineConfig fields (validated by the server)."""
        payload: dict[str, Any] = {"options": options or {}}
        if label:
            payload["label"] = label
        key = idempotency_key or uuid.uuid4().hex
        return self.request(
            "POST", "/v1/jobs", ok=(200, 201), json=payload, headers={"Idempotency-Key": key}
        ).json()

    def create_job_from_zip(
        self,
        zip_path: str | Path,
        options: dict[str, Any] | None = None,
        *,
        label: str | None = None,
        idempotency_key: str | None = None,
    ) -> dict[str, Any]:
        """A job holding a zipped capture, sent in one multipart request (small captures)."""
        import json

        zip_path = Path(zip_path)
        key = idempotency_key or uuid.uuid4().hex
        data = {"options": json.dumps(options or {})}
        if label:
            data["label"] = label
        attempt = 0
        while True:
            with open(zip_path, "rb") as f:
                try:
                    r = self.http.post(
                        "/v1/jobs",
                        data=data,
                        files={"capture": (zip_path.name, f, "application/zip")},
                        headers={"Idempotency-Key": key},
                    )
                except httpx.TransportError:
                    if attempt >= self.retries:
                        raise
                    r = None
            if r is not None:
                if r.status_code in (200, 201):
                    return r.json()
                if r.status_code not in _RETRY_STATUS or attempt >= self.retries:
                    raise self._error(r)
            time.sleep(self._delay(attempt, r))
            attempt += 1

    def job(self, job_id: str) -> dict[str, Any]:
        return self.request("GET", f"/v1/jobs/{job_id}").json()

    def jobs(self, *, offset: int = 0, limit: int = 50) -> dict[str, Any]:
        return self.request("GET", "/v1/jobs", params={"offset": offset, "limit": limit}).json()

    def log(self, job_id: str, since: int = 0) -> dict[str, Any]:
        return self.request("GET", f"/v1/jobs/{job_id}/log", params={"since": since}).json()

    def start(self, job_id: str, *, poll: float = 0.5, timeout: float | None = 3600.0) -> dict[str, Any]:
        """Start the job and wait while the server validates its capture; returns the job once queued
        (or further on). A retry that finds the job already started (409) counts as done.

        Raises:
            ServiceError: 422 when the capture was refused (``errors`` name each file's problem).
        """
        try:
            job = self.request("POST", f"/v1/jobs/{job_id}/start", ok=(200, 202)).json()
        except ServiceError as exc:
            if exc.status != 409:
                raise
            job = self.job(job_id)
            if job["status"] == "created":
                raise
        deadline = None if timeout is None else time.monotonic() + timeout
        while job["status"] == "validating":
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still validating after {timeout} s")
            time.sleep(poll)
            job = self.job(job_id)
        if job["status"] == "created" and job.get("problems"):
            body = {"error": "invalid_capture", "message": job.get("error") or "", "errors": job["problems"]}
            raise ServiceError(422, body, "POST", f"/v1/jobs/{job_id}/start")
        return job

    def rerun(
        self,
        job_id: str,
        options: dict[str, Any] | None = None,
        *,
        from_stage: str = "refine",
        label: str | None = None,
    ) -> dict[str, Any]:
        """A new, queued job on ``job_id``'s capture with ``options`` merged into its options,
        computing the stages from ``from_stage`` on (earlier ones come from the source's cache)."""
        payload: dict[str, Any] = {"options": options or {}, "from_stage": from_stage}
        if label:
            payload["label"] = label
        return self.request("POST", f"/v1/jobs/{job_id}/rerun", ok=(201,), json=payload).json()

    def info(self) -> dict[str, Any]:
        """The service's version, limits, queue length, workers and disk use (GET /v1/info)."""
        return self.request("GET", "/v1/info").json()

    def cancel(self, job_id: str) -> dict[str, Any]:
        return self.request("POST", f"/v1/jobs/{job_id}/cancel", ok=(200, 202)).json()

    def delete(self, job_id: str) -> None:
        try:
            self.request("DELETE", f"/v1/jobs/{job_id}", ok=(204,))
        except ServiceError as exc:
            if exc.status != 404:  # a retried delete finds it gone
                raise

    def wait(
        self,
        job_id: str,
        *,
        poll: float = 1.0,
        timeout: float | None = None,
        on_update: Callable[[dict[str, Any]], None] | None = None,
    ) -> dict[str, Any]:
        """Poll until the job is succeeded, failed or canceled; returns the last state."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            job = self.job(job_id)
            if on_update is not None:
                on_update(job)
            if job["status"] in TERMINAL:
                return job
            if deadline is not None and time.monotonic() > deadline:
                raise TimeoutError(f"job {job_id} still {job['status']} after {timeout} s")
            time.sleep(poll)

    # -- files

    def upload_file(
        self, job_id: str, path: str, local: str | Path, *, on_bytes: BytesCallback | None = None
    ) -> dict[str, Any]:
        """Upload one capture file (resumable above ``chunk_size``); checks the returned sha256.

        When the server offers presigned uploads (``GET /v1/info``'s ``presigned_uploads``), the
        bytes go to the bucket and the server checks them there; a bucket this client cannot
        reach (or that refuses the URL) falls back to sending them to the API.
        """
        local = Path(local)
        size = local.stat().st_size
        digest = sha256_of(local)
        url = f"/v1/jobs/{job_id}/files/{path}"
        presigned = self._upload_presigned(job_id, path, local, size, digest) if self._offers_presigned() else None
        if presigned is not None:
            out = presigned
            if on_bytes:
                on_bytes(size)
        elif size <= self.chunk_size:
            r = self.request(
                "PUT",
                url,
                body=lambda: _read_range(local, 0, size, on_bytes),
                headers={"Content-Type": "application/octet-stream", "Content-Length": str(size)},
            )
            out = r.json()
        else:
            out = self._upload_parts(job_id, path, url, local, size, on_bytes)
            if out.get("sha256") != digest:  # a resumed partial held other bytes: send it all again
                self.request(
                    "PUT",
                    url,
                    ok=(202,),
                    body=lambda: _read_range(local, 0, min(size, self.chunk_size), None),
                    headers={
                        "Content-Type": "application/octet-stream",
                        "Content-Range": f"bytes 0-{min(size, self.chunk_size) - 1}/{size}",
                    },
                )
                out = self._upload_parts(job_id, path, url, local, size, on_bytes)
        if out.get("sha256") != digest:
            raise ServiceError(
                0,
                {
                    "error": "checksum_mismatch",
                    "message": f"{path}: server sha256 {out.get('sha256')} != local {digest}",
                },
            )
        return out

    def _offers_presigned(self) -> bool:
        if self._presigned is None:
            try:
                self._presigned = bool(self.info().get("presigned_uploads"))
            except ServiceError:
                self._presigned = False
        return self._presigned

    def _upload_presigned(
        self, job_id: str, path: str, local: Path, size: int, digest: str
    ) -> dict[str, Any] | None:
        """Upload through a presigned PUT of the bucket; None when the bucket cannot be reached
        or refuses the URL (the caller sends the bytes to the API instead)."""
        offer = self.request(
            "POST", f"/v1/jobs/{job_id}/uploads", ok=(201,), json={"path": path, "size": size, "sha256": digest}
        ).json()
        try:
            r = self._bucket.request(
                offer["method"],
                offer["url"],
                content=_read_range(local, 0, size, None),
                headers={**offer["headers"], "Content-Length": str(size)},
            )
        except httpx.TransportError:
            return None
        if r.status_code >= 300:
            return None
        return dict(self.request("POST", offer["complete"]).json())

    def upload_missing(
        self,
        job_id: str,
        files: dict[str, Path],
        *,
        parallel: int = 4,
        on_bytes: BytesCallback | None = None,
    ) -> list[str]:
        """Upload the files the job does not hold yet (same sha256 on the server: skipped), ``parallel``
        at a time; an interrupted large upload continues where the server's partial file ends.

        Returns:
            The paths uploaded now.
        """
        held = {f["path"]: f["sha256"] for f in self.job(job_id).get("files", [])}
        todo = []
        for rel, local in files.items():
            if held.get(rel) == sha256_of(local):
                if on_bytes:
                    on_bytes(local.stat().st_size)
            else:
                todo.append(rel)
        with ThreadPoolExecutor(max_workers=max(1, parallel)) as pool:
            for done in [pool.submit(self.upload_file, job_id, rel, files[rel], on_bytes=on_bytes) for rel in todo]:
                done.result()
        return todo

    def _server_partial(self, job_id: str, path: str, size: int) -> int:
        """Where an earlier, interrupted upload of this file ended on the server (0: start over)."""
        for p in self.job(job_id).get("partial_uploads", []):
            if p["path"] == path and int(p["total"]) == size:
                return int(p["received"])
        return 0

    def _upload_parts(
        self, job_id: str, path: str, url: str, local: Path, size: int, on_bytes: BytesCallback | None
    ) -> dict[str, Any]:
        offset, failures = self._server_partial(job_id, path, size), 0
        if offset and on_bytes:
            on_bytes(offset)  # already on the server
        while True:
            end = min(offset + self.chunk_size, size)
            headers = {
                "Content-Type": "application/octet-stream",
                "Content-Length": str(end - offset),
                "Content-Range": f"bytes {offset}-{end - 1}/{size}",
            }
            try:
                r = self.http.put(url, content=_read_range(local, offset, end, on_bytes), headers=headers)
            except httpx.TransportError:
                r = None
            if r is not None and r.status_code == 200:
                return r.json()
            if r is not None and r.status_code == 202:
                offset, failures = int(r.json()["size"]), 0
                continue
            if r is not None and r.status_code == 409 and r.json().get("received") is not None:
                offset = int(r.json()["received"])
            elif r is not None and r.status_code not in _RETRY_STATUS:
                raise self._error(r)
            else:
                failures += 1
                if failures > self.retries:
                    raise ServiceError(
                        r.status_code if r is not None else 0,
                        {"message": f"{path}: upload failed {failures} times"},
                    )
                time.sleep(self._delay(failures - 1, r))
                offset = self._server_partial(job_id, path, size)

    def upload_capture(
        self,
        job_id: str,
        root: str | Path,
        *,
        files: list[str] | None = None,
        on_bytes: BytesCallback | None = None,
    ) -> list[dict[str, Any]]:
        """Upload a capture folder's files (default: :func:`capture_files`)."""
        root = Path(root)
        return [
            self.upload_file(job_id, rel, root / rel, on_bytes=on_bytes)
            for rel in files or capture_files(root)
        ]

    def download(
        self, job_id: str, name: str, dest: str | Path, *, on_bytes: BytesCallback | None = None
    ) -> Path:
        """Download a result file to ``dest``, resuming a ``<dest>.part`` left by an earlier try."""
        dest = Path(dest)
        dest.parent.mkdir(parents=True, exist_ok=True)
        part = dest.with_name(dest.name + ".part")
        attempt = 0
        etag = None
        while True:
            have = part.stat().st_size if part.exists() else 0
            headers = {"Range": f"bytes={have}-"} if have else {}
            if have and etag:
                headers["If-Range"] = etag
            try:
                # a redirect to a presigned URL of the bucket is followed without the API key
                with self.http.stream(
                    "GET", f"/v1/jobs/{job_id}/result/{name}", headers=headers, follow_redirects=True
                ) as r:
                    if r.status_code == 416:  # the part is complete already
                        part.replace(dest)
                        return dest
                    if r.status_code not in (200, 206):
                        r.read()
                        if r.status_code in _RETRY_STATUS and attempt < self.retries:
                            raise httpx.TransportError("retryable status")
                        raise self._error(r)
                    etag = r.headers.get("etag")
                    mode = "ab" if r.status_code == 206 else "wb"
                    with open(part, mode) as f:
                        for chunk in r.iter_bytes(1 << 20):
                            f.write(chunk)
                            if on_bytes:
                                on_bytes(len(chunk))
                part.replace(dest)
                return dest
            except httpx.TransportError:
                if attempt >= self.retries:
                    raise
                time.sleep(self._delay(attempt, None))
                attempt += 1

    # -- health

    def ready(self) -> bool:
        try:
            return self.http.get("/readyz").status_code == 200
        except httpx.TransportError:
            return False


def _read_range(path: Path, start: int, end: int, on_bytes: BytesCallback | None) -> Iterator[bytes]:
    """The bytes [start, end) of a file, in 1 MiB pieces (a streamed request body)."""
    with open(path, "rb") as f:
        f.seek(start)
        left = end - start
        while left > 0:
            chunk = f.read(min(1 << 20, left))
            if not chunk:
                return
            left -= len(chunk)
            if on_bytes:
                on_bytes(len(chunk))
            yield chunk
