"""The stages wired together: capture in, result folder out (spec section 3).

:func:`run` is what the CLI (`pmvir reconstruct`) and the service's Celery task
call. It reports progress through one callback and checks a cancellation
callable at every stage and iteration boundary.

Stages, in order: ``decode`` (demosaicing and polarization quantities), then
``geometry`` and ``refine`` as they are available; ``config.stop_after`` names
the last one to run. Every file of the result is written under a temporary
name and renamed, so a run that is killed leaves no half-written file, and a
run repeated on the same folder replaces its files.
"""

from __future__ import annotations

import json
import os
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from pmvir import __version__
from pmvir.capture import Capture, open_capture
from pmvir.config import PipelineConfig
from pmvir.decode import decode_frame, write_decoded, write_previews
from pmvir.errors import CanceledError, ConfigError
from pmvir.polarization.stokes import PolarizationImages

#: progress(stage, overall fraction in [0, 1], message)
ProgressCallback = Callable[[str, float, str], None]
#: should_cancel() -> True to stop at the next boundary
CancelCheck = Callable[[], bool]

#: Share of the whole run each stage takes, for the overall progress fraction.
STAGE_WEIGHTS: dict[str, float] = {"decode": 0.1, "geometry": 0.3, "refine": 0.6}
STAGE_ORDER: tuple[str, ...] = ("decode", "geometry", "refine")
#: Stages this build can run.
AVAILABLE_STAGES: tuple[str, ...] = ("decode",)


@dataclass
class DecodedView:
    """One frame after decoding, with what later stages need of it."""

    index: int
    name: str
    file: str
    images: PolarizationImages


@dataclass
class PipelineResult:
    """What :func:`run` wrote and how long each stage took."""

    out: Path
    stages_run: list[str]
    timings: dict[str, float]
    files: list[str] = field(default_factory=list)


class _Progress:
    """Turns per-stage fractions into an overall fraction that never goes backwards."""

    def __init__(self, stages: list[str], callback: ProgressCallback | None, should_cancel: CancelCheck | None):
        total = sum(STAGE_WEIGHTS[s] for s in stages)
        self._start: dict[str, float] = {}
        acc = 0.0
        for s in stages:
            self._start[s] = acc / total
            acc += STAGE_WEIGHTS[s]
        self._weight = {s: STAGE_WEIGHTS[s] / total for s in stages}
        self._callback = callback
        self._should_cancel = should_cancel
        self._last = 0.0

    def __call__(self, stage: str, fraction: float, message: str = "") -> None:
        """Report ``fraction`` (0..1) of ``stage`` done; raise CanceledError when asked to stop."""
        if self._should_cancel is not None and self._should_cancel():
            raise CanceledError(f"canceled during {stage}")
        overall = self._start[stage] + self._weight[stage] * min(max(fraction, 0.0), 1.0)
        self._last = max(self._last, overall)
        if self._callback is not None:
            self._callback(stage, self._last, message)

    def stage_callback(self, stage: str) -> Callable[[float, str], None]:
        """A ``(fraction, message)`` callback for one stage's own code."""
        return lambda fraction, message="": self(stage, fraction, message)


def stages_for(config: PipelineConfig) -> list[str]:
    """The stages a run with ``config`` executes, in order."""
    return list(STAGE_ORDER[: STAGE_ORDER.index(config.stop_after) + 1])


def decode_views(cap: Capture, config: PipelineConfig, report: Callable[[float, str], None]) -> list[DecodedView]:
    """Decode every frame of an open capture (stage 1)."""
    views = []
    n = len(cap.frames)
    for i, frame in enumerate(cap.frames):
        raw = cap.read_raw(i)
        images = decode_frame(
            raw.mosaic, cap.layout, saturated=raw.saturated, mask=cap.read_mask(i), options=config.decode
        )
        views.append(DecodedView(index=i, name=frame.name, file=frame.file, images=images))
        report((i + 1) / n, f"decoded {frame.file}")
    return views


def run(
    config: PipelineConfig,
    capture: str | Path,
    out: str | Path,
    *,
    progress: ProgressCallback | None = None,
    should_cancel: CancelCheck | None = None,
) -> PipelineResult:
    """Run the pipeline on a capture and write the result folder.

    Args:
        config: the typed configuration (CLI and HTTP job options alike).
        capture: a capture folder, its capture.json, or a .zip.
        out: the result folder (created; files of the same names are replaced).
        progress: called as ``progress(stage, overall_fraction, message)``; the
            fraction never decreases.
        should_cancel: checked at every stage and iteration boundary.

    Returns:
        The stages run, their timings and the files written (relative to ``out``).

    Raises:
        CaptureError: the capture is unreadable or invalid (names the file).
        ReconstructionError: a stage could not produce a usable result.
        CanceledError: ``should_cancel()`` returned True.
    """
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    stages = stages_for(config)
    missing = [s for s in stages if s not in AVAILABLE_STAGES]
    if missing:
        raise ConfigError(f"stage(s) {missing} are not available in pmvir {__version__}; use stop_after='decode'")
    tracker = _Progress(stages, progress, should_cancel)
    timings: dict[str, float] = {}
    files: list[str] = []
    t_run = time.perf_counter()
    with open_capture(capture) as cap:
        tracker("decode", 0.0, f"decoding {len(cap.frames)} frames")
        t0 = time.perf_counter()
        decode_only = config.stop_after == "decode"
        # when the decoded frames are the result, writing them is the second half of the stage
        share = 0.5 if decode_only else 1.0
        views = decode_views(cap, config, lambda f, m="": tracker("decode", share * f, m))
        if decode_only:
            files += _write_decoded_views(out, views, lambda f, m="": tracker("decode", share + share * f, m))
        timings["decode"] = time.perf_counter() - t0
        n_frames = len(cap.frames)
    timings["total"] = time.perf_counter() - t_run
    _write_report(out, config, stages, timings, {"frames": n_frames})
    files.append("report.json")
    tracker(stages[-1], 1.0, "done")
    return PipelineResult(out=out, stages_run=stages, timings=timings, files=files)


def _write_decoded_views(out: Path, views: list[DecodedView], report: Callable[[float, str], None]) -> list[str]:
    folder = out / "decoded"
    folder.mkdir(exist_ok=True)
    written = []
    for k, view in enumerate(views):
        write_decoded(folder / f"{view.name}.npz", view.images)
        written.append(f"decoded/{view.name}.npz")
        written += [f"decoded/{p.name}" for p in write_previews(folder, view.name, view.images)]
        report((k + 1) / len(views), f"wrote decoded/{view.name}.npz")
    return written


def software_versions() -> dict[str, str]:
    """Versions of pmvir and the libraries whose behaviour shapes a result."""
    versions = {"pmvir": __version__, "python": platform.python_version()}
    for module in ("numpy", "scipy", "cv2", "open3d", "pycolmap", "torch"):
        try:
            versions[module] = __import__(module).__version__
        except Exception:  # an optional library that is absent or broken is reported as such
            versions[module] = "unavailable"
    return versions


def _write_report(out: Path, config: PipelineConfig, stages: list[str], timings: dict[str, float], counts: dict) -> None:
    report = {
        "format": "pmvir-report/1",
        "stages": stages,
        "timings_s": timings,
        "counts": counts,
        "parameters": config.model_dump(mode="json"),
        "software": software_versions(),
    }
    tmp = out / "report.json.tmp"
    tmp.write_text(json.dumps(report, indent=1))
    os.replace(tmp, out / "report.json")
