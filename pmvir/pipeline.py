"""The stages wired together: capture in, result folder out (spec section 3).

:func:`run` is what the CLI (`pmvir reconstruct`) and the service's Celery task
call. It reports progress through one callback and checks a cancellation
callable at every stage and iteration boundary.

Stages, in order: ``decode`` (demosaicing and polarization quantities),
``geometry`` (poses, dense stereo, initial surface, visibility, sqrt(3)
subdivision: ``initial.ply``, ``poses/``) and ``refine`` (Polarimetric MVIR:
``mesh.ply``, ``illumination.json``); ``config.stop_after`` names the last one
to run. ``report.json`` is always written, with per-stage timings, counts,
energies, the parameters and the software versions. Every file of the result is written under a temporary
name and renamed, so a run that is killed leaves no half-written file, and a
run repeated on the same folder replaces its files.
"""

from __future__ import annotations

import json
import os
import platform
import tempfile
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

from pmvir import __version__
from pmvir.capture import Capture, open_capture
from pmvir.config import PipelineConfig
from pmvir.decode import decode_frame, write_decoded, write_previews
from pmvir.errors import CanceledError, ConfigError
from pmvir.geometry.stage import GeometryResult, geometry_report, run_geometry, write_geometry
from pmvir.io.illumination import illumination_from_arrays, write_illumination
from pmvir.io.ply import Mesh, write_mesh_ply
from pmvir.polarization.stokes import PolarizationImages
from pmvir.refine import RefineResult, make_visibility_fn, observation_from_decoded, refine_surface
from pmvir.refine.schedule import StageLog

#: progress(stage, overall fraction in [0, 1], message)
ProgressCallback = Callable[[str, float, str], None]
#: should_cancel() -> True to stop at the next boundary
CancelCheck = Callable[[], bool]

#: Share of the whole run each stage takes, for the overall progress fraction.
STAGE_WEIGHTS: dict[str, float] = {"decode": 0.1, "geometry": 0.3, "refine": 0.6}
STAGE_ORDER: tuple[str, ...] = ("decode", "geometry", "refine")
#: Stages this build can run.
AVAILABLE_STAGES: tuple[str, ...] = ("decode", "geometry", "refine")


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

    def __init__(
        self, stages: list[str], callback: ProgressCallback | None, should_cancel: CancelCheck | None
    ):
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


def decode_views(
    cap: Capture, config: PipelineConfig, report: Callable[[float, str], None]
) -> list[DecodedView]:
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
        raise ConfigError(
            f"stage(s) {missing} are not available in pmvir {__version__}; use stop_after='decode'"
        )
    tracker = _Progress(stages, progress, should_cancel)
    timings: dict[str, float] = {}
    files: list[str] = []
    t_run = time.perf_counter()
    sections: dict[str, object] = {}
    with open_capture(capture) as cap, tempfile.TemporaryDirectory(prefix=".work-", dir=out) as work:
        tracker("decode", 0.0, f"decoding {len(cap.frames)} frames")
        t0 = time.perf_counter()
        decode_only = config.stop_after == "decode"
        # when the decoded frames are the result, writing them is the second half of the stage
        share = 0.5 if decode_only else 1.0
        views = decode_views(cap, config, lambda f, m="": tracker("decode", share * f, m))
        if decode_only:
            files += _write_decoded_views(out, views, lambda f, m="": tracker("decode", share + share * f, m))
        timings["decode"] = time.perf_counter() - t0
        counts = {"frames": len(cap.frames)}
        if "geometry" in stages:
            t0 = time.perf_counter()
            geometry = _geometry_stage(cap, views, config, Path(work), tracker, should_cancel)
            files += _write_geometry(out, geometry)
            sections["geometry"] = geometry_report(geometry)
            timings["geometry"] = time.perf_counter() - t0
        if "refine" in stages:
            t0 = time.perf_counter()
            refined, registered = _refine_stage(cap, views, geometry, config, tracker, should_cancel)
            files += _write_refined(out, geometry, refined, [views[i].file for i in registered])
            sections["refine"] = refine_report(refined)
            timings["refine"] = time.perf_counter() - t0
    timings["total"] = time.perf_counter() - t_run
    _write_report(out, config, stages, timings, counts, sections)
    files.append("report.json")
    tracker(stages[-1], 1.0, "done")
    return PipelineResult(out=out, stages_run=stages, timings=timings, files=files)


def _geometry_stage(
    cap: Capture,
    views: list[DecodedView],
    config: PipelineConfig,
    work: Path,
    tracker: _Progress,
    should_cancel: CancelCheck | None,
) -> GeometryResult:
    """Poses, dense stereo, initial surface, visibility, subdivision (stage 2)."""
    return run_geometry(
        cap,
        [v.images for v in views],
        options=config.geometry,
        workdir=work / "geometry",
        progress=tracker.stage_callback("geometry"),
        cancel=should_cancel,
    )


def _write_geometry(out: Path, geometry: GeometryResult) -> list[str]:
    written = write_geometry(out, geometry)
    poses = sorted(p.relative_to(out).as_posix() for p in Path(written["poses"]).iterdir())
    return ["initial.ply", *poses]


def _refine_stage(
    cap: Capture,
    views: list[DecodedView],
    geometry: GeometryResult,
    config: PipelineConfig,
    tracker: _Progress,
    should_cancel: CancelCheck | None,
) -> tuple[RefineResult, list[int]]:
    """Polarimetric MVIR on the registered views (stage 3). Returns the result and those views' indices."""
    registered = [i for i, cam in enumerate(geometry.cameras) if cam is not None]
    cameras = [geometry.cameras[i] for i in registered]
    observations = [
        observation_from_decoded(asdict(views[i].images), intensity=config.refine.intensity)
        for i in registered
    ]
    masks = [cap.read_mask(i) for i in registered]
    visibility_fn = make_visibility_fn(
        cameras, masks, min_cos=config.geometry.visibility_min_cos, rel_tol=config.geometry.visibility_rel_tol
    )
    refined = refine_surface(
        geometry.vertices,
        geometry.faces,
        cameras,
        observations,
        geometry.visibility[:, registered],
        options=config.refine,
        visibility_fn=visibility_fn,
        progress=tracker.stage_callback("refine"),
        cancel=should_cancel,
    )
    return refined, registered


def _write_refined(out: Path, geometry: GeometryResult, refined: RefineResult, files: list[str]) -> list[str]:
    mesh = Mesh(refined.vertices, geometry.faces, albedo=refined.albedo, normals=refined.normals)
    write_mesh_ply(out / "mesh.ply", mesh)
    write_illumination(
        out / "illumination.json", illumination_from_arrays(files, refined.sh, refined.rgb_scale)
    )
    return ["mesh.ply", "illumination.json"]


def _stage_report(st: StageLog) -> dict:
    return {
        "index": st.index,
        "tau_pol": st.tau_pol,
        "tau_gsm": st.tau_gsm,
        "tau_psm": st.tau_psm,
        "t": st.t,
        "k": st.k,
        "vertex_view_pairs": st.n_pairs,
        "observed_vertices": st.n_observed,
        "iterations": len(st.energies) - 1,
        "evaluations": st.evaluations,
        "stop_reason": st.stop_reason,
        "seconds": st.seconds,
        "energies_first": st.energies[0] if st.energies else {},
        "energies_last": st.energies[-1] if st.energies else {},
        "energies": st.energies,
    }


def refine_report(refined: RefineResult) -> dict:
    """The refinement's part of report.json: per stage its parameters and per-iteration term values."""
    return {
        "vertices": len(refined.vertices),
        "timings": {k: float(v) for k, v in refined.timings.items()},
        "stages": [_stage_report(st) for st in refined.stages],
    }


def _write_decoded_views(
    out: Path, views: list[DecodedView], report: Callable[[float, str], None]
) -> list[str]:
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


def _write_report(
    out: Path,
    config: PipelineConfig,
    stages: list[str],
    timings: dict[str, float],
    counts: dict,
    sections: dict,
) -> None:
    report = {
        "format": "pmvir-report/1",
        "stages": stages,
        "timings_s": timings,
        "counts": counts,
        **sections,
        "parameters": config.model_dump(mode="json"),
        "software": software_versions(),
    }
    tmp = out / "report.json.tmp"
    tmp.write_text(json.dumps(report, indent=1))
    os.replace(tmp, out / "report.json")
