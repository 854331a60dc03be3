"""Captures as ``.zip`` files: safe extraction and packing.

A zipped capture holds the capture folder either at the zip's root
(``capture.json``, ``frames/...``) or inside exactly one top-level folder
(``mycapture/capture.json``, ...). A zip of bare frames (no ``capture.json``;
frames directly there or in ``frames/``) is a capture whose manifest is
inferred once extracted (:mod:`pmvir.io.inference`). Uploads are untrusted, so every member is
checked before anything is written:

* names: relative, ``/``-separated, no ``..``/``.``/empty segments, no absolute
  names, no backslashes, no drive letters or ``:``, no NUL; no duplicates;
* names flagged UTF-8 must be valid UTF-8;
* no symbolic links, no encrypted members, and only the stored and deflate
  compression methods (Deflate64, LZMA, bzip2, ... are refused by name: what
  real capture tools write is deflate, and every other decoder is more attack
  surface);
* at most ``max_members`` members, at most ``max_total_bytes`` uncompressed in
  all (as declared, and counted again while extracting), no member over 1 MiB
  whose uncompressed/compressed ratio exceeds ``max_ratio``, and the same ratio
  for the whole zip (many small, highly compressible members are a zip bomb too).

macOS metadata (``__MACOSX/``, ``.DS_Store``) is skipped.

Public API: :func:`extract_capture_zip`, :func:`zip_capture`, :func:`capture_prefix`, and the default
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
from collections.abc import Iterable
from pathlib import Path, PurePosixPath

from pmvir.errors import CaptureError, ManifestError
from pmvir.io.frames import FRAME_SUFFIXES

DEFAULT_MAX_MEMBERS = 10_000
DEFAULT_MAX_TOTAL_BYTES = 8 * 1024**3
DEFAULT_MAX_RATIO = 200.0
_RATIO_MIN_BYTES = 1 << 20  # small members (manifests, text) compress well legitimately
_CHUNK = 1 << 20
#: Compression methods accepted, by zip method number.
SUPPORTED_COMPRESSION = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate"}
_METHOD_NAMES = {9: "Deflate64", zipfile.ZIP_BZIP2: "bzip2", zipfile.ZIP_LZMA: "LZMA", 93: "Zstandard", 95: "XZ"}


def open_zip(zip_path: str | Path, label: str) -> zipfile.ZipFile:
    """Open a zip's central directory; CaptureError (naming the zip) when it cannot be read.

    A member name flagged UTF-8 (bit 11) whose bytes are not UTF-8 is refused here, with the bytes shown.
    """
    try:
        return zipfile.ZipFile(zip_path)
    except UnicodeDecodeError as exc:
        raise CaptureError(
            label, f"zip member name {exc.object!r} is flagged UTF-8 but is not valid UTF-8 ({exc.reason})"
        ) from None
    except (zipfile.BadZipFile, OSError, ValueError, EOFError, NotImplementedError) as exc:
        raise CaptureError(label, f"not a readable zip file: {exc}") from exc


def compression_problem(info: zipfile.ZipInfo) -> str | None:
    """Why a member's compression method is refused, or None for stored/deflate."""
    if info.compress_type in SUPPORTED_COMPRESSION:
        return None
    name = _METHOD_NAMES.get(info.compress_type, "unknown")
    return (
        f"uses compression method {info.compress_type} ({name}); only "
        f"{' and '.join(SUPPORTED_COMPRESSION.values())} are accepted"
    )


def ratio_problem(uncompressed: int, compressed: int, max_ratio: float) -> str | None:
    """Why ``uncompressed`` bytes from ``compressed`` is a zip bomb, or None (below 1 MiB: never)."""
    if uncompressed <= _RATIO_MIN_BYTES:
        return None
    ratio = uncompressed / max(compressed, 1)
    if ratio <= max_ratio:
        return None
    return (
        f"expands {ratio:.0f}x ({compressed} -> {uncompressed} bytes), more than the limit of "
        f"{max_ratio:.0f}x (zip bomb?)"
    )


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
                   max_ratio: float, zip_bytes: int) -> list[zipfile.ZipInfo]:
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
        why = compression_problem(info)
        if why:
            raise CaptureError(label, f"zip member {name!r} {why}")
        total += info.file_size
        if total > max_total_bytes:
            raise CaptureError(
                label, f"zip uncompressed size exceeds the limit of {max_total_bytes} bytes (at member {name!r})"
            )
        why = ratio_problem(info.file_size, info.compress_size, max_ratio)
        if why:
            raise CaptureError(label, f"zip member {name!r} {why}")
        if not _is_ignored(name):
            kept.append(info)
    why = ratio_problem(total, zip_bytes, max_ratio)
    if why:
        raise CaptureError(label, f"the zip as a whole {why}")
    return kept


def _holds_frames(names: set[str], prefix: str) -> bool:
    """Whether frame files lie directly under ``prefix`` or in its ``frames/``."""
    for n in names:
        rest = n[len(prefix) :] if n.startswith(prefix) else None
        if rest is None:
            continue
        rest = rest.removeprefix("frames/")
        if "/" not in rest and PurePosixPath(rest).suffix.lower() in FRAME_SUFFIXES:
            return True
    return False


def capture_prefix(names: Iterable[str], label: str) -> str:
    """Where the capture lies in a zip of these member names: ``""`` (its root) or ``"<top>/"``.

    The root, else the single top-level folder, holding ``capture.json``, or else (a zip
    of bare frames, whose manifest is inferred) frame files directly or in ``frames/``.
    ManifestError naming the zip when neither holds either.
    """
    names = {n.rstrip("/") for n in names if not _is_ignored(n)}
    tops = {n.split("/")[0] for n in names}
    prefixes = [""] + ([next(iter(tops)) + "/"] if len(tops) == 1 else [])
    for prefix in prefixes:
        if f"{prefix}capture.json" in names:
            return prefix
    for prefix in prefixes:
        if _holds_frames(names, prefix):
            return prefix
    raise ManifestError(
        label, "no capture.json, and no frame files to infer it from, at the zip's root or inside its single "
        "top-level folder"
    )


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
        max_ratio: largest uncompressed/compressed ratio of a member over 1 MiB, and of the whole
            zip when it expands to more than 1 MiB.

    Returns:
        The capture's root folder inside ``dest`` (``dest`` or its one sub-folder).

    Raises:
        CaptureError: not a zip, a corrupt zip, an unsafe member, a limit exceeded.
        ManifestError: neither ``capture.json`` nor frame files where a capture is expected.
    """
    zip_path, dest = Path(zip_path), Path(dest)
    label = zip_path.name
    with open_zip(zip_path, label) as zf:
        infos = _check_members(
            zf,
            label,
            max_members=max_members,
            max_total_bytes=max_total_bytes,
            max_ratio=max_ratio,
            zip_bytes=zip_path.stat().st_size,
        )
        prefix = capture_prefix((i.filename for i in infos), label)
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
            except (zipfile.BadZipFile, zlib.error, OSError, EOFError, NotImplementedError, ValueError) as exc:
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
