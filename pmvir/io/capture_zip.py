"""Captures as ``.zip`` files: safe extraction and packing.

A zipped capture holds the capture folder either at the zip's root
(``capture.json``, ``frames/...``) or inside exactly one top-level folder
(``mycapture/capture.json``, ...). Uploads are untrusted, so every member is
checked before anything is written:

* names: relative, ``/``-separated, no ``..``/``.``/empty segments, no absolute
  names, no backslashes, no drive letters or ``:``, no NUL; no duplicates;
* no symbolic links, no encrypted members;
* at most ``max_members`` members, at most ``max_total_bytes`` uncompressed in
  all (as declared, and counted again while extracting), and no member over
  1 MiB whose uncompressed/compressed ratio exceeds ``max_ratio`` (zip bombs).

macOS metadata (``__MACOSX/``, ``.DS_Store``) is skipped.

Public API: :func:`extract_capture_zip`, :func:`zip_capture`, and the default
limits :data:`DEFAULT_MAX_MEMBERS`, :data:`DEFAULT_MAX_TOTAL_BYTES`,
:data:`DEFAULT_MAX_RATIO`. Problems raise :class:`pmvir.errors.CaptureError`
(or :class:`pmvir.errors.ManifestError` when there is no ``capture.json``)
naming the zip and the member.
"""

from __future__ import annotations

import os
import stat
import zipfile
import zlib
from pathlib import Path

from pmvir.errors import CaptureError, ManifestError

DEFAULT_MAX_MEMBERS = 10_000
DEFAULT_MAX_TOTAL_BYTES = 8 * 1024**3
DEFAULT_MAX_RATIO = 200.0
_RATIO_MIN_BYTES = 1 << 20  # small members (manifests, text) compress well legitimately
_CHUNK = 1 << 20


def _is_ignored(name: str) -> bool:
    parts = name.rstrip("/").split("/")
    return parts[0] == "__MACOSX" or parts[-1] == ".DS_Store"


def _name_problem(name: str) -> str | None:
    """Why a member name is unsafe, or None."""
    if "\x00" in name:
        return "contains a NUL character"
    if "\\" in name:
        return "contains a backslash"
    if name.startswith("/"):
        return "is an absolute path"
    if ":" in name:
        return "contains ':' (drive letter or stream name)"
    parts = name.rstrip("/").split("/")
    if any(p in ("", ".", "..") for p in parts):
        return "has an empty, '.' or '..' segment (path traversal)"
    return None


def _check_members(zf: zipfile.ZipFile, label: str, *, max_members: int, max_total_bytes: int,
                   max_ratio: float) -> list[zipfile.ZipInfo]:
    infos = zf.infolist()
    if len(infos) > max_members:
        raise CaptureError(label, f"zip has {len(infos)} members, more than the limit of {max_members}")
    seen: set[str] = set()
    total = 0
    kept = []
    for info in infos:
        name = info.filename
        problem = _name_problem(name)
        if problem:
            raise CaptureError(label, f"unsafe zip member {name!r}: {problem}")
        key = name.rstrip("/")
        if key in seen:
            raise CaptureError(label, f"zip member {name!r} appears more than once")
        seen.add(key)
        if stat.S_ISLNK(info.external_attr >> 16):
            raise CaptureError(label, f"zip member {name!r} is a symbolic link")
        if info.flag_bits & 0x1:
            raise CaptureError(label, f"zip member {name!r} is encrypted")
        total += info.file_size
        if total > max_total_bytes:
            raise CaptureError(
                label, f"zip uncompressed size exceeds the limit of {max_total_bytes} bytes (at member {name!r})"
            )
        if info.file_size > _RATIO_MIN_BYTES:
            ratio = info.file_size / max(info.compress_size, 1)
            if ratio > max_ratio:
                raise CaptureError(
                    label,
                    f"zip member {name!r} expands {ratio:.0f}x ({info.compress_size} -> {info.file_size} bytes), "
                    f"more than the limit of {max_ratio:.0f}x (zip bomb?)",
                )
        if not _is_ignored(name):
            kept.append(info)
    return kept


def _capture_prefix(infos: list[zipfile.ZipInfo], label: str) -> str:
    names = {i.filename.rstrip("/") for i in infos}
    if "capture.json" in names:
        return ""
    tops = {n.split("/")[0] for n in names}
    if len(tops) == 1:
        top = next(iter(tops))
        if f"{top}/capture.json" in names:
            return top + "/"
    raise ManifestError(label, "no capture.json at the zip's root or inside its single top-level folder")


def extract_capture_zip(
    zip_path: str | Path,
    dest: str | Path,
    *,
    max_members: int = DEFAULT_MAX_MEMBERS,
    max_total_bytes: int = DEFAULT_MAX_TOTAL_BYTES,
    max_ratio: float = DEFAULT_MAX_RATIO,
) -> Path:
    """Check every member of a zipped capture, then extract it under ``dest``.

    Args:
        zip_path: the ``.zip`` file.
        dest: an existing empty folder to extract into.
        max_members: most members the zip may list.
        max_total_bytes: most uncompressed bytes in all.
        max_ratio: largest uncompressed/compressed ratio of a member over 1 MiB.

    Returns:
        The capture's root folder inside ``dest`` (``dest`` or its one sub-folder).

    Raises:
        CaptureError: not a zip, a corrupt zip, an unsafe member, a limit exceeded.
        ManifestError: no ``capture.json`` where one is expected.
    """
    zip_path, dest = Path(zip_path), Path(dest)
    label = zip_path.name
    try:
        zf = zipfile.ZipFile(zip_path)
    except (zipfile.BadZipFile, OSError) as exc:
        raise CaptureError(label, f"not a readable zip file: {exc}") from exc
    with zf:
        infos = _check_members(
            zf, label, max_members=max_members, max_total_bytes=max_total_bytes, max_ratio=max_ratio
        )
        prefix = _capture_prefix(infos, label)
        written = 0
        for info in infos:
            target = dest.joinpath(*info.filename.rstrip("/").split("/"))
            if info.is_dir():
                target.mkdir(parents=True, exist_ok=True)
                continue
            target.parent.mkdir(parents=True, exist_ok=True)
            member_bytes = 0
            try:
                with zf.open(info) as src, open(target, "wb") as out:
                    while chunk := src.read(_CHUNK):
                        member_bytes += len(chunk)
                        written += len(chunk)
                        if member_bytes > info.file_size or written > max_total_bytes:
                            raise CaptureError(
                                label, f"zip member {info.filename!r} expands past its declared size"
                            )
                        out.write(chunk)
            except (zipfile.BadZipFile, zlib.error, OSError, EOFError) as exc:
                raise CaptureError(label, f"zip member {info.filename!r} is corrupt: {exc}") from exc
    return dest / prefix.rstrip("/") if prefix else dest


def zip_capture(folder: str | Path, zip_path: str | Path, *, top_folder: str | None = None) -> None:
    """Pack a capture folder into a zip (deflate), at the root or under ``top_folder/``.

    Symbolic links are not followed into the zip; files are added in sorted order.
    """
    folder, zip_path = Path(folder), Path(zip_path)
    tmp = zip_path.with_name(f".{zip_path.name}.{os.getpid()}.tmp")
    try:
        with zipfile.ZipFile(tmp, "w", compression=zipfile.ZIP_DEFLATED) as zf:
            for path in sorted(folder.rglob("*")):
                if path.is_symlink() or not path.is_file():
                    continue
                arc = path.relative_to(folder).as_posix()
                zf.write(path, f"{top_folder}/{arc}" if top_folder else arc)
        os.replace(tmp, zip_path)
    finally:
        if tmp.exists():
            tmp.unlink()
