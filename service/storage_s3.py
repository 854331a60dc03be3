"""Job files in an S3-compatible bucket (AWS S3, MinIO, Ceph RGW, moto): the shared medium of many hosts.

Layout in the bucket, under ``s3://<bucket>/<prefix>/``::

    jobs/<id>/capture/<path>     the uploaded capture (capture.json, frames/, masks/, gt/)
    jobs/<id>/result/<path>      the finished result (result.zip and every file the run wrote)
    jobs/<id>/cache/<file>       stage outputs a rerun resumes from, each with its HMAC ``.sig``
    jobs/<id>/incoming/<upload>  a presigned upload as the client PUT it, until the API checks it

Nothing else is shared: the API receives an upload into its scratch folder and
puts it in the bucket (multipart above 16 MiB); a worker copies the capture and
the cache into its own scratch folder, runs, uploads the result and the cache,
and removes its copies. Downloads stream from the bucket with ``Range``.
Credentials and region come from boto3's usual sources (``AWS_ACCESS_KEY_ID``,
``AWS_SECRET_ACCESS_KEY``, ``AWS_DEFAULT_REGION``, instance roles).
"""

from __future__ import annotations

import json
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

from pmvir import stage_cache
from pmvir.config import PipelineConfig
from pmvir.stages import Stage
from service import cache_sign
from service.storage import CHUNK, Blob, JobFiles

_PART = 16 * 1024 * 1024


def parse_url(url: str) -> tuple[str, str]:
    """(bucket, prefix) of ``s3://bucket/prefix``.

    >>> parse_url("s3://pmvir-jobs/prod/")
    ('pmvir-jobs', 'prod')
    """
    parts = urlsplit(url)
    if parts.scheme != "s3" or not parts.netloc:
        raise ValueError(f"PMVIR_STORAGE_URL must be s3://bucket[/prefix], got {url!r}")
    return parts.netloc, parts.path.strip("/")


class S3JobFiles(JobFiles):
    """The job layout of :class:`JobFiles` in a bucket; ``root`` is this process's scratch folder."""

    backend = "s3"

    def __init__(
        self,
        url: str,
        *,
        scratch: str | Path,
        endpoint_url: str = "",
        cache_key: bytes = b"",
        public_endpoint_url: str = "",
    ):
        import boto3
        from boto3.s3.transfer import TransferConfig
        from botocore.config import Config

        super().__init__(scratch, cache_key=cache_key)
        self.bucket, self.prefix = parse_url(url)
        self.s3 = boto3.client(
            "s3",
            endpoint_url=endpoint_url or None,
            config=Config(retries={"max_attempts": 5, "mode": "standard"}, max_pool_connections=32),
        )
        #: Signs URLs for clients, with the endpoint they reach the bucket at.
        self.presigner = (
            boto3.client("s3", endpoint_url=public_endpoint_url) if public_endpoint_url else self.s3
        )
        self.transfer = TransferConfig(
            multipart_threshold=_PART, multipart_chunksize=_PART, max_concurrency=4
        )
        self._usage: tuple[float, int, int] | None = None

    def key(self, job_id: str, *parts: str) -> str:
        return "/".join(p for p in (self.prefix, "jobs", job_id, *parts) if p)

    def _list(self, prefix: str) -> Iterator[dict[str, Any]]:
        pages = self.s3.get_paginator("list_objects_v2").paginate(Bucket=self.bucket, Prefix=prefix)
        for page in pages:
            yield from page.get("Contents", [])

    def _delete_prefix(self, prefix: str) -> None:
        batch: list[dict[str, str]] = []
        for obj in self._list(prefix):
            batch.append({"Key": obj["Key"]})
            if len(batch) == 1000:
                self.s3.delete_objects(Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True})
                batch = []
        if batch:
            self.s3.delete_objects(Bucket=self.bucket, Delete={"Objects": batch, "Quiet": True})

    def _download_prefix(self, prefix: str, dest: Path, *, suffixes: tuple[str, ...] = ()) -> int:
        n = 0
        for obj in self._list(prefix + "/"):
            rel = obj["Key"][len(prefix) + 1 :]
            if not rel or (suffixes and not rel.endswith(suffixes)):
                continue
            target = dest.joinpath(*rel.split("/"))
            target.parent.mkdir(parents=True, exist_ok=True)
            self.s3.download_file(self.bucket, obj["Key"], str(target), Config=self.transfer)
            n += 1
        return n

    def _upload_folder(self, folder: Path, prefix: str) -> int:
        n = 0
        for p in sorted(folder.rglob("*")):
            if p.is_file() and not p.is_symlink() and not p.name.endswith(".tmp"):
                key = f"{prefix}/{p.relative_to(folder).as_posix()}"
                self.s3.upload_file(str(p), self.bucket, key, Config=self.transfer)
                n += 1
        return n

    # -- the API's side

    def place(self, job_id: str, tmp: Path, path: str) -> Path:
        """Put a finished upload in the bucket (multipart when large) and remove the local file."""
        try:
            self.s3.upload_file(
                str(tmp), self.bucket, self.key(job_id, "capture", path), Config=self.transfer
            )
        finally:
            tmp.unlink(missing_ok=True)
        return tmp

    def remove_capture_file(self, job_id: str, path: str) -> None:
        self.s3.delete_object(Bucket=self.bucket, Key=self.key(job_id, "capture", path))

    def share(self, source_id: str, job_id: str) -> None:
        """Give a rerun the source job's capture and stage cache (server-side copies)."""
        for part in ("capture", "cache"):
            src = self.key(source_id, part) + "/"
            for obj in self._list(src):
                rel = obj["Key"][len(src) :]
                self.s3.copy(
                    {"Bucket": self.bucket, "Key": obj["Key"]},
                    self.bucket,
                    self.key(job_id, part, rel),
                    Config=self.transfer,
                )

    def exists(self, job_id: str) -> bool:
        return any(True for _ in self._list(self.key(job_id) + "/"))

    def delete(self, job_id: str) -> None:
        super().delete(job_id)
        self._delete_prefix(self.key(job_id) + "/")

    def result_file(self, job_id: str, name: str) -> Path | None:
        return None  # results are in the bucket: result_files / result_blob

    def result_files(self, job_id: str) -> dict[str, int]:
        prefix = self.key(job_id, "result") + "/"
        return {o["Key"][len(prefix) :]: int(o["Size"]) for o in self._list(prefix)}

    def result_blob(self, job_id: str, path: str) -> Blob | None:
        key = self.key(job_id, "result", path)
        try:
            head = self.s3.head_object(Bucket=self.bucket, Key=key)
        except self.s3.exceptions.ClientError:
            return None
        etag = head.get("ETag", "")
        s3 = self.s3

        def read(first: int, last: int) -> Iterator[bytes]:
            body = s3.get_object(Bucket=self.bucket, Key=key, Range=f"bytes={first}-{last}", IfMatch=etag)[
                "Body"
            ]
            try:
                yield from body.iter_chunks(CHUNK)
            finally:
                body.close()

        return Blob(size=int(head["ContentLength"]), etag=etag, read=read)

    def cache_has_stage(self, job_id: str, stage: Stage, config: PipelineConfig) -> bool:
        data, key = (
            stage_cache.CACHED_STAGES[stage],
            Path(stage_cache.CACHED_STAGES[stage]).with_suffix(".key"),
        )
        names = {o["Key"].rsplit("/", 1)[-1] for o in self._list(self.key(job_id, "cache") + "/")}
        if data not in names or key.name not in names:
            return False
        body = self.s3.get_object(Bucket=self.bucket, Key=self.key(job_id, "cache", key.name))["Body"]
        return bool(body.read().decode() == stage_cache.options_key(config, stage))

    @contextmanager
    def capture_view(self, job_id: str) -> Iterator[Path]:
        """The capture copied from the bucket into a scratch folder of its own, removed afterwards."""
        view = self.job_dir(job_id) / "views" / uuid.uuid4().hex
        try:
            self._download_prefix(self.key(job_id, "capture"), view)
            yield view
        finally:
            self.remove_tree(view)

    def usage(self, *, max_age: float = 30.0) -> dict[str, int]:
        """The scratch disk's total/used/free bytes and the bytes and count of jobs in the bucket."""
        if self._usage is None or time.monotonic() - self._usage[0] > max_age:
            total, jobs, under = 0, set(), self.key("") + "/"
            for o in self._list(under):
                total += int(o["Size"])
                jobs.add(o["Key"][len(under) :].split("/", 1)[0])
            self._usage = (time.monotonic(), total, len(jobs))
        disk = super().usage(max_age=max_age)
        return {**disk, "jobs_bytes": self._usage[1], "jobs": self._usage[2]}

    def writable(self) -> bool:
        """Whether a probe object can be written to and removed from the bucket (and scratch is writable)."""
        probe = "/".join(p for p in (self.prefix, f".probe-{uuid.uuid4().hex}") if p)
        try:
            self.s3.put_object(Bucket=self.bucket, Key=probe, Body=json.dumps({"ok": True}).encode())
            self.s3.delete_object(Bucket=self.bucket, Key=probe)
        except Exception:  # noqa: BLE001 - any client or network error means "not writable"
            return False
        return super().writable()

    # -- presigned URLs: the bytes go between the client and the bucket

    def result_url(self, job_id: str, path: str, *, filename: str, media_type: str, ttl: int) -> str | None:
        """A presigned GET of a result file (None when the job has no such file)."""
        key = self.key(job_id, "result", path)
        try:
            self.s3.head_object(Bucket=self.bucket, Key=key)
        except self.s3.exceptions.ClientError:
            return None
        params = {
            "Bucket": self.bucket,
            "Key": key,
            "ResponseContentDisposition": f'attachment; filename="{filename}"',
            "ResponseContentType": media_type,
        }
        return str(self.presigner.generate_presigned_url("get_object", Params=params, ExpiresIn=ttl))

    def upload_url(self, job_id: str, upload_id: str, *, ttl: int) -> str:
        """A presigned PUT to the job's ``incoming/<upload_id>`` (Content-Type application/octet-stream)."""
        params = {
            "Bucket": self.bucket,
            "Key": self.key(job_id, "incoming", upload_id),
            "ContentType": "application/octet-stream",
        }
        return str(self.presigner.generate_presigned_url("put_object", Params=params, ExpiresIn=ttl))

    def landed(self, job_id: str, upload_id: str) -> tuple[int, str] | None:
        """(size, ETag) of what the client PUT to an upload URL; None when nothing is there."""
        try:
            head = self.s3.head_object(Bucket=self.bucket, Key=self.key(job_id, "incoming", upload_id))
        except self.s3.exceptions.ClientError:
            return None
        return int(head["ContentLength"]), str(head.get("ETag", ""))

    def landed_bytes(self, job_id: str, upload_id: str, etag: str) -> Iterator[bytes]:
        """The bytes that landed, as long as they are the version ``etag`` names."""
        key = self.key(job_id, "incoming", upload_id)
        body = self.s3.get_object(Bucket=self.bucket, Key=key, IfMatch=etag)["Body"]
        try:
            yield from body.iter_chunks(CHUNK)
        finally:
            body.close()

    def freeze_landed(self, job_id: str, upload_id: str, etag: str) -> None:
        """Keep the checked version (``etag``) of an upload where its URL cannot write; raises
        ``ClientError`` when the upload changed since it was checked."""
        key = self.key(job_id, "incoming", upload_id)
        self.s3.copy_object(
            Bucket=self.bucket,
            Key=key + ".checked",
            CopySource={"Bucket": self.bucket, "Key": key},
            CopySourceIfMatch=etag,
        )

    def place_landed(self, job_id: str, upload_id: str, path: str) -> None:
        """Move a frozen upload into the capture (server-side copy)."""
        key = self.key(job_id, "incoming", upload_id)
        self.s3.copy_object(
            Bucket=self.bucket,
            Key=self.key(job_id, "capture", path),
            CopySource={"Bucket": self.bucket, "Key": key + ".checked"},
        )
        self.drop_landed(job_id, upload_id)

    def drop_landed(self, job_id: str, upload_id: str) -> None:
        key = self.key(job_id, "incoming", upload_id)
        self.s3.delete_objects(
            Bucket=self.bucket, Delete={"Objects": [{"Key": key}, {"Key": key + ".checked"}], "Quiet": True}
        )

    # -- a worker's side

    def checkout(self, job_id: str) -> tuple[Path, Path]:
        """Copy the capture and (with a cache key) the verified stage cache into scratch."""
        local = self.job_dir(job_id)
        self.remove_tree(local)
        capture, cache = local / "capture", local / "cache"
        capture.mkdir(parents=True)
        self._download_prefix(self.key(job_id, "capture"), capture)
        if self.cache_key:  # without a key the bucket's pickles are never loaded
            self._download_prefix(self.key(job_id, "cache"), cache)
            cache_sign.verify_folder(cache, self.cache_key)
        return capture, cache

    def publish_result(self, job_id: str, run_dir: Path) -> None:
        """Zip the run, replace the job's result/ in the bucket with the run's files, remove the run."""
        from service.storage import zip_run

        zip_run(run_dir)
        prefix = self.key(job_id, "result")
        self._delete_prefix(prefix + "/")
        self._upload_folder(run_dir, prefix)
        self.remove_tree(run_dir)

    def push_cache(self, job_id: str, cache: Path) -> None:
        """Upload the signed stage cache (not at all without a cache key: see :mod:`service.cache_sign`)."""
        if not self.cache_key or not cache.is_dir():
            return
        cache_sign.sign_folder(cache, self.cache_key)
        self._upload_folder(cache, self.key(job_id, "cache"))

    def release(self, job_id: str) -> None:
        """Remove the worker's scratch copies of the job."""
        self.remove_tree(self.job_dir(job_id))


def open_storage(settings: Any) -> JobFiles:
    """The storage the settings name: a bucket with ``storage_url``, else the local folder ``storage``."""
    key = settings.cache_key.encode()
    if settings.storage_url:
        return S3JobFiles(
            settings.storage_url,
            scratch=settings.scratch or settings.storage,
            endpoint_url=settings.s3_endpoint_url,
            cache_key=key,
            public_endpoint_url=settings.s3_public_endpoint_url,
        )
    return JobFiles(settings.storage, cache_key=key)
