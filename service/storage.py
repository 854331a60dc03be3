"""Job files on disk, under the storage root, per job id.

Layout::

    <root>/jobs/<id>/capture/            the uploaded capture (capture.json, frames/, masks/, gt/)
    <root>/jobs/<id>/incoming/           uploads being written (unique names; renamed into capture/)
    <root>/jobs/<id>/partial/<h>.part    resumable (Content-Range) uploads not complete yet
    <root>/jobs/<id>/runs/<run id>/      a run's output while it is produced
    <root>/jobs/<id>/result/             the finished result (a run's folder, renamed)
    <root>/jobs/<id>/cache/              stage outputs a rerun resumes from (pmvir.stage_cache)
    <root>/trash/                        folders being deleted (renamed here first, then removed)

Everything that becomes visible appears by rename, so a reader never sees a
half-written file and a run that is repeated (a redelivered task) replaces
its own temporary folder instead of mixing with a finished result.
"""

from __future__ import annotations

import hashlib
import os
import re
import shutil
import time
import uuid
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath

from pmvir import stage_cache
from pmvir.config import PipelineConfig
from pmvir.io.frames import FRAME_SUFFIXES
from pmvir.result import RESULT_FILES, RESULT_ZIP, downloadable_names
from pmvir.stages import Stage
from service import cache_sign

_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_.+-]{0,127}$")
_LAYOUT = {
    "frames": tuple(sorted(FRAME_SUFFIXES)),
    "masks": (".png",),
}
_GT_FILES = ("gt/mesh.ply", "gt/illumination.json")
CHUNK = 1 << 20
#: Suffixes zipped without compression: compressed already, or float arrays deflate barely shrinks.
_STORED = (".npz", ".npy", ".png", ".jpg", ".jpeg", ".zip", ".gz", ".tif", ".tiff", ".exr")


def capture_path_problem(path: str) -> str | None:
    """Why ``path`` is not a file of the capture layout, or None when it is.

    Accepted: ``capture.json``, ``frames/<name>.<png|tif|tiff|dng|raw|bin>``,
    ``masks/<name>.png``, ``gt/mesh.ply``, ``gt/illumination.json``; ``<name>`` is
    1-128 characters of letters, digits, ``_ . + -``, not starting with ``.``/``-``/``+``
    (the extension's case does not matter).
    """
    if not path:
        return "is empty"
    if "\x00" in path:
        return "contains a NUL character"
    if "\\" in path:
        return "contains a backslash"
    if path.startswith("/") or re.match(r"^[A-Za-z]:", path):
        return "is an absolute path"
    parts = path.split("/")
    if any(p in ("", ".", "..") for p in parts):
        return "has an empty, '.' or '..' segment (path traversal)"
    if path == "capture.json" or path in _GT_FILES:
        return None
    if len(parts) != 2 or parts[0] not in _LAYOUT:
        return (
            "is not part of the capture layout (capture.json, frames/<name>.<ext>, masks/<name>.png, "
            "gt/mesh.ply, gt/illumination.json)"
        )
    folder, name = parts
    suffix = PurePosixPath(name).suffix
    if suffix.lower() not in _LAYOUT[folder] or not PurePosixPath(name).stem:
        return f"must end in one of {', '.join(_LAYOUT[folder])} inside {folder}/"
    if not _NAME.match(name[: -len(suffix)]):
        return (
            f"has an unsupported file name {name!r} (before the extension: 1-128 letters, digits, "
            "'_', '.', '+', '-', not starting with '.', '+' or '-')"
        )
    return None


def is_frame(path: str) -> bool:
    return path.startswith("frames/")


@dataclass(frozen=True)
class Blob:
    """A stored file to be sent: its size, an ETag, and a reader of an inclusive byte range."""

    size: int
    etag: str
    read: Callable[[int, int], Iterator[bytes]]


def _read_local(path: Path) -> Callable[[int, int], Iterator[bytes]]:
    def read(first: int, last: int) -> Iterator[bytes]:
        remaining = last - first + 1
        with open(path, "rb") as f:
            f.seek(first)
            while remaining > 0 and (chunk := f.read(min(CHUNK, remaining))):
                remaining -= len(chunk)
                yield chunk

    return read


def registered_results(paths: list[str]) -> list[str]:
    """The paths of a result listing that belong to a registered result entry, sorted."""
    out = []
    for f in RESULT_FILES:
        if f.is_folder:
            out += [p for p in paths if p.startswith(f.name)]
        elif f.name in paths:
            out.append(f.name)
    return sorted(out)


class JobFiles:
    """The storage root: folders per job, atomic writes, deletion by rename.

    The local backend: the root is shared by the API and every worker (one host, or one
    POSIX volume). :class:`service.storage_s3.S3JobFiles` keeps the same interface with a
    bucket as the shared medium and the root as this process's scratch folder.
    """

    #: Where the jobs are kept, for logs and /v1/info ("local" or "s3").
    backend = "local"

    def __init__(self, root: str | Path, *, cache_key: bytes = b""):
        self.root = Path(root)
        self.cache_key = cache_key

    def job_dir(self, job_id: str) -> Path:
        return self.root / "jobs" / job_id

    def capture_dir(self, job_id: str) -> Path:
        return self.job_dir(job_id) / "capture"

    def result_dir(self, job_id: str) -> Path:
        return self.job_dir(job_id) / "result"

    def cache_dir(self, job_id: str) -> Path:
        return self.job_dir(job_id) / "cache"

    def share(self, source_id: str, job_id: str) -> None:
        """Give a rerun the source job's capture and stage cache: hard links (copies across devices)."""
        for part in ("capture", "cache"):
            src, dst = self.job_dir(source_id) / part, self.job_dir(job_id) / part
            if src.is_dir():
                shutil.copytree(src, dst, copy_function=_link_or_copy, dirs_exist_ok=True)

    def run_dir(self, job_id: str, run_id: str) -> Path:
        return self.job_dir(job_id) / "runs" / run_id

    def incoming_path(self, job_id: str) -> Path:
        d = self.job_dir(job_id) / "incoming"
        d.mkdir(parents=True, exist_ok=True)
        return d / f"{uuid.uuid4().hex}.tmp"

    def partial_path(self, job_id: str, path: str) -> Path:
        h = hashlib.sha256(path.encode()).hexdigest()[:32]
        return self.job_dir(job_id) / "partial" / f"{h}.part"

    def create(self, job_id: str) -> None:
        self.capture_dir(job_id).mkdir(parents=True, exist_ok=False)

    def exists(self, job_id: str) -> bool:
        return self.job_dir(job_id).is_dir()

    def place(self, job_id: str, tmp: Path, path: str) -> Path:
        """Rename a finished temporary file to its capture path (replacing any earlier upload)."""
        target = self.capture_dir(job_id).joinpath(*path.split("/"))
        target.parent.mkdir(parents=True, exist_ok=True)
        os.replace(tmp, target)
        return target

    def remove_capture_file(self, job_id: str, path: str) -> None:
        target = self.capture_dir(job_id).joinpath(*path.split("/"))
        target.unlink(missing_ok=True)

    def result_file(self, job_id: str, name: str) -> Path | None:
        """A finished result file, or None when the job has none of that name."""
        if name not in downloadable_names():
            return None
        p = self.result_dir(job_id) / name
        return p if p.is_file() else None

    def result_files(self, job_id: str) -> dict[str, int]:
        """Every file of the job's published result: relative path -> size (empty without a result)."""
        root = self.result_dir(job_id)
        if not root.is_dir():
            return {}
        return {
            p.relative_to(root).as_posix(): p.stat().st_size
            for p in root.rglob("*")
            if p.is_file() and not p.is_symlink()
        }

    def result_blob(self, job_id: str, path: str) -> Blob | None:
        """A result file by its relative path (one of :meth:`result_files`), or None."""
        p = self.result_dir(job_id).joinpath(*path.split("/"))
        try:
            st = p.stat()
        except OSError:
            return None
        return Blob(size=st.st_size, etag=f'"{st.st_size:x}-{st.st_mtime_ns:x}"', read=_read_local(p))

    def cache_has_stage(self, job_id: str, stage: Stage, config: PipelineConfig) -> bool:
        """Whether the job's stage cache holds ``stage``'s output made with these options."""
        return stage_cache.has_stage(self.cache_dir(job_id), stage, config)

    @contextmanager
    def capture_view(self, job_id: str) -> Iterator[Path]:
        """A local folder holding the job's capture, for reading (validation)."""
        yield self.capture_dir(job_id)

    def checkout(self, job_id: str) -> tuple[Path, Path]:
        """A worker's local (capture, cache) folders of the job; a cache file whose signature
        is wrong is removed first (with a cache key set), so it is recomputed, never unpickled."""
        cache = self.cache_dir(job_id)
        if self.cache_key:
            cache_sign.verify_folder(cache, self.cache_key)
        return self.capture_dir(job_id), cache

    def push_cache(self, job_id: str, cache: Path) -> None:
        """Sign the stage cache a run wrote (with a cache key set); it is in place already."""
        if self.cache_key:
            cache_sign.sign_folder(cache, self.cache_key)

    def release(self, job_id: str) -> None:
        """A worker is done with the job's local copies (none to remove here: they are the storage)."""

    def remove_tree(self, path: Path) -> None:
        """Remove a folder: renamed into trash/ first, so it disappears from its place at once."""
        if not path.exists():
            return
        trash = self.root / "trash"
        trash.mkdir(parents=True, exist_ok=True)
        dest = trash / f"{path.name}-{uuid.uuid4().hex}"
        try:
            os.replace(path, dest)
        except OSError:
            dest = path
        shutil.rmtree(dest, ignore_errors=True)

    def delete(self, job_id: str) -> None:
        self.remove_tree(self.job_dir(job_id))

    def usage(self, *, max_age: float = 30.0) -> dict[str, int]:
        """Disk use: the storage disk's total/used/free bytes and the bytes and count of job folders.

        The job folders are walked at most every ``max_age`` seconds (the last answer is reused).
        """
        self.root.mkdir(parents=True, exist_ok=True)
        cached = _USAGE.get(self.root)
        if cached is None or time.monotonic() - cached[0] > max_age:
            jobs = self.root / "jobs"
            folders = [d for d in jobs.iterdir() if d.is_dir()] if jobs.is_dir() else []
            _USAGE[self.root] = cached = (
                time.monotonic(),
                sum(_tree_bytes(d) for d in folders),
                len(folders),
            )
        disk = shutil.disk_usage(self.root)
        return {
            "total": disk.total,
            "used": disk.used,
            "free": disk.free,
            "jobs_bytes": cached[1],
            "jobs": cached[2],
        }

    def free_bytes(self) -> int:
        self.root.mkdir(parents=True, exist_ok=True)
        return shutil.disk_usage(self.root).free

    def writable(self) -> bool:
        """Whether a file can be created, written and removed under the root."""
        try:
            self.root.mkdir(parents=True, exist_ok=True)
            probe = self.root / f".probe-{uuid.uuid4().hex}"
            probe.write_bytes(b"ok")
            probe.unlink()
            return True
        except OSError:
            return False

    def publish_result(self, job_id: str, run_dir: Path) -> None:
        """Zip a finished run's folder into result.zip inside it (and each result folder into
        ``<folder>.zip``, to be served singly), then rename it to result/.

        Running twice is harmless: an earlier result folder is moved away first.
        """
        zip_run(run_dir)
        final = self.result_dir(job_id)
        if final.exists():
            self.remove_tree(final)
        os.replace(run_dir, final)


def zip_run(run_dir: Path) -> None:
    """Write a run's result.zip and the ``<folder>.zip`` of each result folder served singly."""
    for entry in RESULT_FILES:
        folder = run_dir / entry.name.rstrip("/")
        if entry.is_folder and entry.single and folder.is_dir():
            write_folder_zip(folder, run_dir / entry.download_name)
    write_result_zip(run_dir)


def write_result_zip(folder: Path) -> Path:
    """Write ``folder/result.zip`` holding every other file under ``folder`` (temporary name, then rename).

    Text and PLY members are deflated; arrays and images are stored as they are (see ``_STORED``).
    """
    return write_folder_zip(folder, folder / RESULT_ZIP)


def write_folder_zip(folder: Path, target: Path) -> Path:
    """Zip every file under ``folder`` (but ``target`` and other .zip files beside it) into ``target``."""
    tmp = target.with_name(f".{target.name}.{uuid.uuid4().hex}.tmp")
    try:
        with zipfile.ZipFile(tmp, "w", allowZip64=True) as zf:
            for p in sorted(folder.rglob("*")):
                if not p.is_file() or p.is_symlink() or p == target or p.name.endswith(".tmp"):
                    continue
                if p.parent == target.parent and p.suffix == ".zip":  # the folder zips beside result.zip
                    continue
                stored = p.suffix.lower() in _STORED
                zf.write(
                    p,
                    p.relative_to(folder).as_posix(),
                    compress_type=zipfile.ZIP_STORED if stored else zipfile.ZIP_DEFLATED,
                    compresslevel=None if stored else 6,
                )
        os.replace(tmp, target)
    finally:
        tmp.unlink(missing_ok=True)
    return target


_USAGE: dict[Path, tuple[float, int, int]] = {}


def _tree_bytes(folder: Path) -> int:
    """Bytes of the regular files under ``folder`` (hard links shared by reruns are counted per job)."""
    total, stack = 0, [folder]
    while stack:
        try:
            entries = list(os.scandir(stack.pop()))
        except OSError:  # removed meanwhile
            continue
        for e in entries:
            if e.is_dir(follow_symlinks=False):
                stack.append(Path(e.path))
            elif e.is_file(follow_symlinks=False):
                total += e.stat(follow_symlinks=False).st_size
    return total


def _link_or_copy(src: str, dst: str) -> None:
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def sha256_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while chunk := f.read(CHUNK):
            h.update(chunk)
    return h.hexdigest()
