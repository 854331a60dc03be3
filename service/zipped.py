"""A zipped capture sent with ``POST /v1/jobs`` (multipart field ``capture``).

Before anything is extracted, the zip's central directory is checked against
the service's limits and the capture layout: member count
(``max_zip_members``, 413), each member's declared size (``max_frame_bytes`` /
``max_manifest_bytes``, 413), the declared total (``max_job_bytes``, 413) and
its ratio to the zip's size (``max_zip_ratio``, 413), the frame count
(``max_frames``, 413), every member name (capture layout, and valid UTF-8 when
flagged so, 422) and compression method (stored or deflate, 422).
Extraction itself is :func:`pmvir.io.capture_zip.extract_capture_zip`, which
rejects unsafe names, links, encrypted members and zip bombs (ratio) before
writing, and counts the bytes again while writing (422 naming the member).

A zip of bare frames (no capture.json; the frames at the top, in ``frames/``, or
in one top folder) is a capture too: the frames are placed in ``frames/`` and the
manifest inferred from them (:mod:`pmvir.io.inference`, its defaults: IMX250MYR,
black level from a DNG else 0, SfM intrinsics unless EXIF gives them) is written
as the job's capture.json, listed with its files; a frame that keeps it from being
inferred is a 422 naming the file.
"""

from __future__ import annotations

import shutil
import uuid
from pathlib import Path
from typing import BinaryIO

from pmvir.errors import CaptureError, ConfigError, ManifestError
from pmvir.io.capture_zip import (
    capture_prefix,
    compression_problem,
    extract_capture_zip,
    open_zip,
    ratio_problem,
)
from pmvir.io.inference import infer_manifest
from pmvir.io.manifest import MANIFEST_NAME, write_capture_manifest
from service.deps import Services
from service.errors import ApiError, ErrorItem, too_large
from service.storage import CHUNK, capture_path_problem, is_frame, sha256_file
from service.store import FileInfo, Gate
from service.uploads import file_limit


def ignored_member(name: str) -> bool:
    """A zip member the import skips: macOS metadata (``__MACOSX/``, ``.DS_Store``)."""
    parts = name.rstrip("/").split("/")
    return parts[0] == "__MACOSX" or parts[-1] == ".DS_Store"


def _capture_error(exc: CaptureError) -> ApiError:
    return ApiError(
        422,
        "invalid_zip",
        str(exc),
        errors=[ErrorItem(file=exc.path, msg=exc.problem, type=type(exc).__name__)],
    )


def precheck_zip(svc: Services, zip_path: Path) -> None:
    """Check the central directory against limits and the capture layout (nothing is extracted)."""
    s = svc.settings
    try:
        zf = open_zip(zip_path, "capture")
    except CaptureError as exc:
        raise _capture_error(exc) from exc
    with zf:
        infos = zf.infolist()
        if len(infos) > s.max_zip_members:
            raise too_large(f"the zip has {len(infos)} members, more than the limit of {s.max_zip_members}")
        members = [i for i in infos if not i.is_dir() and not ignored_member(i.filename)]
        names = {i.filename for i in members}
        try:
            prefix = capture_prefix(names, "capture")
        except ManifestError as exc:
            raise ApiError(
                422,
                "invalid_zip",
                "the zip has no capture.json, and no frames to infer it from, at its root or in its one top folder",
                errors=[ErrorItem(file="capture.json", msg="missing", type="ManifestError")],
            ) from exc
        flat = flat_frames(names, prefix)
        errors = []
        total = 0
        frames = 0
        for info in members:
            rel = info.filename[len(prefix) :]
            rel = f"frames/{rel}" if flat and "/" not in rel else rel
            problem = capture_path_problem(rel)
            if problem:
                errors.append(ErrorItem(file=info.filename, msg=f"member {problem}", type="invalid_path"))
                continue
            problem = compression_problem(info)
            if problem:
                errors.append(ErrorItem(file=info.filename, msg=f"member {problem}", type="unsupported_zip"))
                continue
            limit = file_limit(svc, rel)
            if info.file_size > limit:
                raise too_large(
                    f"zip member {info.filename!r} expands to {info.file_size} bytes, more than the "
                    f"limit of {limit}"
                )
            total += info.file_size
            frames += is_frame(rel)
        if errors:
            raise ApiError(
                422,
                "invalid_zip",
                f"{len(errors)} zip member(s) outside the capture layout or unsupported",
                errors=errors,
            )
        if total > s.max_job_bytes:
            raise too_large(f"the zip expands to {total} bytes, more than the job limit of {s.max_job_bytes}")
        bomb = ratio_problem(total, zip_path.stat().st_size, s.max_zip_ratio)
        if bomb:
            raise too_large(f"the zip as a whole {bomb}")
        if frames > s.max_frames:
            raise too_large(f"the zip holds {frames} frames, more than the limit of {s.max_frames}")


def flat_frames(names: set[str], prefix: str) -> bool:
    """A zip of bare frames lying directly under ``prefix`` (no capture.json, no frames/ folder):
    its files are the capture's ``frames/<name>``."""
    inside = [n[len(prefix) :] for n in names if n.startswith(prefix)]
    return "capture.json" not in inside and not any(n.startswith("frames/") for n in inside)


def _complete_bare_capture(root: Path) -> None:
    """A capture of bare frames made whole: frames lying at its top moved into ``frames/``, and the
    capture.json inferred from them written (422 naming the file that keeps it from being inferred)."""
    if (root / MANIFEST_NAME).exists():
        return
    try:  # inferred where the frames lie, so that problems name the files as they were zipped
        manifest = infer_manifest(root).manifest
    except (CaptureError, ConfigError) as exc:
        item = exc if isinstance(exc, CaptureError) else CaptureError(MANIFEST_NAME, str(exc))
        raise _capture_error(item) from exc
    names = {p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file()}
    if flat_frames(names, ""):
        (root / "frames").mkdir()
        for name in names:
            if "/" not in name:
                (root / name).rename(root / "frames" / name)
    write_capture_manifest(root, manifest)


def save_upload(src: BinaryIO, dest: Path, limit: int) -> int:
    """Copy a spooled upload to ``dest`` in chunks; 413 past ``limit`` bytes."""
    n = 0
    src.seek(0)
    with open(dest, "wb") as out:
        while chunk := src.read(CHUNK):
            n += len(chunk)
            if n > limit:
                raise too_large(f"the zipped capture is more than the limit of {limit} bytes")
            out.write(chunk)
    return n


def import_zip(svc: Services, job_id: str, zip_path: Path) -> list[FileInfo]:
    """Check, extract and record a zipped capture into the job's capture folder."""
    s = svc.settings
    precheck_zip(svc, zip_path)
    staging = svc.files.job_dir(job_id) / "incoming" / f"zip-{uuid.uuid4().hex}"
    staging.mkdir(parents=True)
    try:
        try:
            root = extract_capture_zip(
                zip_path,
                staging,
                max_members=s.max_zip_members,
                max_total_bytes=s.max_job_bytes,
                max_ratio=s.max_zip_ratio,
            )
        except CaptureError as exc:
            raise _capture_error(exc) from exc
        _complete_bare_capture(root)
        recorded = []
        for p in sorted(root.rglob("*")):
            if not p.is_file() or p.is_symlink():
                continue
            rel = p.relative_to(root).as_posix()
            problem = capture_path_problem(rel)
            if problem:  # precheck_zip saw every name; this is a second line of defence
                raise ApiError(422, "invalid_zip", f"zip member {rel!r} {problem}")
            info = FileInfo(path=rel, size=p.stat().st_size, sha256=sha256_file(p))
            svc.files.place(job_id, p, rel)
            why = svc.store.upload_commit(job_id, "", info)
            if why is not Gate.OK:
                raise ApiError(409, "conflict", f"the job is {why}")
            recorded.append(info)
        return recorded
    finally:
        shutil.rmtree(staging, ignore_errors=True)
        zip_path.unlink(missing_ok=True)
