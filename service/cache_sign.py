"""HMAC signatures of the stage cache, so a writer of the shared storage cannot run code on workers.

The stage cache (:mod:`pmvir.stage_cache`) holds pickles. A worker that writes
one signs it: ``<file>.sig`` holds HMAC-SHA256 of the file's name and bytes
under ``PMVIR_CACHE_KEY``, a secret only the workers hold (the API never reads
the cache's contents). Before a run the worker verifies every cache file and
removes those whose signature is missing or wrong, so the pipeline recomputes
that stage (or a rerun from a later stage fails with "no cached output")
instead of unpickling bytes it did not write.
"""

from __future__ import annotations

import hashlib
import hmac
import logging
from pathlib import Path

log = logging.getLogger("pmvir.worker")

SUFFIX = ".sig"


def signature(path: Path, key: bytes) -> str:
    """HMAC-SHA256 (hex) of ``path``'s name and contents under ``key``."""
    mac = hmac.new(key, path.name.encode() + b"\0", hashlib.sha256)
    with open(path, "rb") as f:
        while chunk := f.read(1 << 20):
            mac.update(chunk)
    return mac.hexdigest()


def _signed_files(folder: Path) -> list[Path]:
    if not folder.is_dir():
        return []
    return [p for p in sorted(folder.iterdir()) if p.is_file() and not p.name.endswith((SUFFIX, ".tmp"))]


def sign_folder(folder: Path, key: bytes) -> int:
    """Write ``<file>.sig`` beside every cache file of ``folder``; returns how many."""
    files = _signed_files(folder)
    for p in files:
        p.with_name(p.name + SUFFIX).write_text(signature(p, key))
    return len(files)


def verify_folder(folder: Path, key: bytes) -> list[str]:
    """Remove every cache file of ``folder`` whose signature is missing or wrong; returns their names."""
    dropped = []
    for p in _signed_files(folder):
        sig = p.with_name(p.name + SUFFIX)
        try:
            ok = hmac.compare_digest(sig.read_text().strip(), signature(p, key))
        except OSError:
            ok = False
        if not ok:
            log.warning("stage cache %s: signature missing or wrong; removed", p.name)
            p.unlink(missing_ok=True)
            sig.unlink(missing_ok=True)
            dropped.append(p.name)
    return dropped
