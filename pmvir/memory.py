"""A run's memory, estimated before it starts, so that a capture too large for its limit fails at once.

The estimate is a linear model of the peak resident memory of :func:`pmvir.pipeline.run` with
the default options, from the sizes of the arrays a run holds per working pixel and per frame
pixel (``bench/fullsize.py`` measures the true peaks; the benchmarks page shows them):

    peak = BASE_BYTES + PER_VIEW_PIXEL_BYTES * views * working pixels + PER_FRAME_PIXEL_BYTES * frame pixels

The views' decoded images, the refinement's per-view tables and its (vertex, view) pairs
grow with views x working pixels (the subdivision sizes triangles in working pixels); one
full-size frame is demosaiced at a time. A run that stops after decoding keeps its views at full
size instead (``PER_DECODED_PIXEL_BYTES`` per view and frame pixel). A limit comes from
``--max-memory`` or the ``PMVIR_JOB_MEMORY`` environment variable (bytes, or with a K/M/G/T
suffix, powers of 1024).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from pmvir.errors import ConfigError, ResourceLimitError

# Fitted to the peaks bench/fullsize.py measures (blob): BASE and PER_FRAME from the
# decode stage's peaks of 12 views at 612x512, 1224x1024 and 2448x2048 frames (0.65, 0.76 and 1.22 GiB:
# one full-size frame demosaiced at a time, 131 bytes per frame pixel); PER_VIEW from the refinement's
# peaks with the default options. 36 views measured 4.34 GiB at 612x512 (485k vertices; estimated
# 5.6 GiB) and 7.30 GiB for 2448x2048 frames worked at 816x682 (811k vertices; estimated 10.0 GiB).
# Rounded up.
#: Python, NumPy, torch, Open3D and pycolmap loaded, and a small run's working set.
BASE_BYTES = 0.65 * 2**30
#: Per view and working pixel: decoded images, refinement tables and (vertex, view) pairs.
PER_VIEW_PIXEL_BYTES = 470.0
#: Per pixel of the largest frame: one frame's demosaicing at full resolution.
PER_FRAME_PIXEL_BYTES = 135.0
#: Per view and frame pixel of a decode-only run, which keeps every decoded view at full size until
#: it writes them (measured 36 bytes: 1.04 and 1.39 GiB peaks for 1 and 3 frames of 2448x2048).
PER_DECODED_PIXEL_BYTES = 40.0
#: The environment variable that caps a job's memory (also read by the service's workers).
MEMORY_VARIABLE = "PMVIR_JOB_MEMORY"

_UNITS = {"": 1, "K": 2**10, "M": 2**20, "G": 2**30, "T": 2**40}


def parse_bytes(text: str) -> int:
    """``"12G"``, ``"800M"``, ``"12GiB"`` or ``"1073741824"`` as bytes (suffixes are powers of 1024)."""
    m = re.fullmatch(r"\s*(\d+(?:\.\d+)?)\s*([KMGT]?)(?:i?B)?\s*", text, flags=re.IGNORECASE)
    if m is None:
        raise ConfigError(f"memory size {text!r}: expected a number of bytes, optionally with K, M, G or T")
    value = float(m.group(1)) * _UNITS[m.group(2).upper()]
    if value < 1:
        raise ConfigError(f"memory size {text!r} must be positive")
    return int(value)


def memory_limit(explicit: int | None = None) -> tuple[int | None, str]:
    """The limit in bytes and where it came from: ``explicit``, else ``PMVIR_JOB_MEMORY``, else none.

    ``PMVIR_JOB_MEMORY`` of 0 means no limit (as in the service's settings).
    """
    if explicit is not None:
        return explicit, "--max-memory"
    raw = os.environ.get(MEMORY_VARIABLE, "").strip()
    if not raw or raw == "0":
        return None, ""
    return parse_bytes(raw), MEMORY_VARIABLE


def estimated_peak_bytes(
    frame_size: tuple[int, int], views: int, factor: int, *, decode_only: bool = False
) -> int:
    """The estimated peak of a run on ``views`` frames of ``frame_size`` (width, height) binned by ``factor``
    (``decode_only``: a run that stops after decoding, its views kept at full size)."""
    w, h = frame_size
    if decode_only:
        return int(BASE_BYTES + (PER_DECODED_PIXEL_BYTES * views + PER_FRAME_PIXEL_BYTES) * w * h)
    working = (w // factor) * (h // factor)
    return int(BASE_BYTES + PER_VIEW_PIXEL_BYTES * views * working + PER_FRAME_PIXEL_BYTES * w * h)


def mapped_overhead_bytes() -> int:
    """Address space this process maps beyond what it holds (``VmSize - VmRSS``: shared libraries,
    thread stacks, allocator arenas) when its address space is capped (``RLIMIT_AS``, as a service
    worker caps a job's at ``PMVIR_JOB_MEMORY``); 0 when it is not capped or cannot be read.

    The estimate is of resident memory, so under an address-space cap a run needs this much more.
    """
    try:
        import resource
    except ImportError:  # not a POSIX system
        return 0
    soft, _ = resource.getrlimit(resource.RLIMIT_AS)
    if soft == resource.RLIM_INFINITY:
        return 0
    kib: dict[str, int] = {}
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmSize", "VmRSS"):
                kib[key] = int(value.split()[0])
    except (OSError, ValueError, IndexError):
        return 0
    if len(kib) != 2:
        return 0
    return max(kib["VmSize"] - kib["VmRSS"], 0) * 1024


def _gib(n: float) -> str:
    return f"{n / 2**30:.1f} GiB"


def check_memory(
    label: str,
    frame_size: tuple[int, int],
    views: int,
    factor: int,
    limit: int | None,
    source: str,
    *,
    decode_only: bool = False,
    reserved: int = 0,
) -> int:
    """The estimated peak; ResourceLimitError naming the limit and what would fit when it is above ``limit``.

    Args:
        label: the capture, as the error names it.
        frame_size: (width, height) of the largest frame.
        views: frames to reconstruct.
        factor: the working resolution's binning factor.
        limit: bytes, or None for no limit.
        source: where the limit came from (``--max-memory`` or ``PMVIR_JOB_MEMORY``).
        decode_only: the run stops after decoding (its views at full size; binning does not apply).
        reserved: bytes of the limit already taken by other means (:func:`mapped_overhead_bytes`
            under an address-space cap).
    """
    need = estimated_peak_bytes(frame_size, views, factor, decode_only=decode_only)
    if limit is None or need + reserved <= limit:
        return need
    w, h = frame_size
    working = (w // factor) * (h // factor)
    room = limit - reserved - BASE_BYTES - PER_FRAME_PIXEL_BYTES * w * h
    per_view = PER_DECODED_PIXEL_BYTES * w * h if decode_only else PER_VIEW_PIXEL_BYTES * working
    fewest_views = 1 if decode_only else 3  # a reconstruction needs three views; decoding one
    fits: list[str] = []
    if room > 0 and (max_views := int(room // per_view)) >= fewest_views:
        fits.append(f"at most {max_views} views at this size")
    if not decode_only:  # decoding alone runs at full size: binning does not apply
        for f in range(factor + 1, factor + 9):
            if estimated_peak_bytes(frame_size, views, f) + reserved <= limit:
                fits.append(f"decode.max_working_size_px={max(w, h) // f} (frames binned by {f})")
                break
    hint = "; it fits with " + " or ".join(fits) if fits else ""
    mapped = f" plus {_gib(reserved)} of address space the process maps already" if reserved else ""
    raise ResourceLimitError(
        f"{label}: {views} frames of {w}x{h} at the working size {w // factor}x{h // factor} need about "
        f"{_gib(need)}{mapped}, above the memory limit of {_gib(limit)} ({source}){hint}, or raise the limit"
    )
