"""The stages wired together: capture in, result folder out (spec section 3).

:func:`run` is what the CLI (`pmvir reconstruct`) and the service's Celery task
call. It reports progress, checks cancellation and times every stage through
one :class:`~pmvir.progress.Progress` object, and writes every file through
:class:`~pmvir.result.ResultFolder`.

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

import platform
import tempfile
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path

from pmvir import __version__
from pmvir.capture import Capture, open_capture
from pmvir.config import PipelineConfig
from pmvir.decode import decode_frame, write_decoded, write_previews
from pmvir.geometry.stage import GeometryResult, geometry_report, run_geometry, write_geometry
from pmvir.io.illumination import illumination_from_arrays
from pmvir.io.ply import Mesh
from pmvir.polarization.stokes import PolarizationImages
from pmvir.progress import Progress
from pmvir.refine import RefineResult, make_visibility_fn, observation_from_decoded, refine_surface
from pmvir.refine.schedule import StageLog
from pmvir.result import ResultFolder
from pmvir.stages import STAGES, Stage

#: Share of the whole run each stage takes, for the overall progress fraction.
STAGE_WEIGHTS: dict[str, float] = {"decode": 0.1, "geometry": 0.3, "refine": 0.6}
#: The pipeline's stages, in order (the one definition; the CLI, config and service read it).
STAGE_ORDER: tuple[Stage, ...] = STAGES
#: Stages this build can run.
AVAILABLE_STAGES: tuple[Stage, ...] = STAGES


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


def stages_for(config: PipelineConfig) -> list[Stage]:
    """The stages a run with ``config`` executes, in order."""
    return list(STAGES[: Stage(config.stop_after).position + 1])


def decode_views(cap: Capture, config: PipelineConfig, progress: Progress) -> list[DecodedView]:
    """Decode every frame of an open capture (stage 1)."""
    views = []
    n = len(cap.frames)
    for i, frame in enumerate(cap.frames):
        raw = cap.read_raw(i)
        images = decode_frame(
            raw.mosaic, cap.layout, saturated=raw.saturated, mask=cap.read_mask(i), options=config.decode
        )
        views.append(DecodedView(index=i, name=frame.name, file=frame.file, images=images))
        progress.update((i + 1) / n, f"decoded {frame.file}")
    return views


def run(
    config: PipelineConfig,
    capture: str | Path,
    out: str | Path,
    *,
    progress: Progress | None = None,
) -> PipelineResult:
    """Run the pipeline on a capture and write the result folder.

    Args:
        config: the typed configuration (CLI and HTTP job options alike).
        capture: a capture folder, its capture.json, or a .zip.
        out: the result folder (created; files of the same names are replaced).
        progress: reports ``(stage, overall fraction, message)`` (the fraction never
            decreases) and is asked to cancel at every stage, step and iteration boundary.

    Returns:
        The stages run, their timings and the files written (relative to ``out``).

    Raises:
        CaptureError: the capture is unreadable or invalid (names the file).
        ReconstructionError: a stage could not produce a usable result.
        CanceledError: the progress object's ``should_cancel()`` returned True.
    """
    progress = progress or Progress.none()
    result = ResultFolder(out)
    result.root.mkdir(parents=True, exist_ok=True)
    stages = stages_for(config)
    total = sum(STAGE_WEIGHTS[s] for s in stages)
    weight = {s: STAGE_WEIGHTS[s] / total for s in stages}
    t_run = time.perf_counter()
    sections: dict[str, object] = {}
    with open_capture(capture) as cap, tempfile.TemporaryDirectory(prefix=".work-", dir=out) as work:
        counts = {"frames": len(cap.frames)}
        with progress.step(Stage.DECODE, weight[Stage.DECODE]) as p:
            if config.stop_after == Stage.DECODE:  # the decoded frames are the result
                with p.step("read", 0.5) as q:
                    views = decode_views(cap, config, q)
                with p.step("write", 0.5) as q:
                    result.write_folder("decoded", lambda d: _write_decoded_views(d, views, q))
            else:
                views = decode_views(cap, config, p)
        if Stage.GEOMETRY in stages:
            with progress.step(Stage.GEOMETRY, weight[Stage.GEOMETRY]) as p:
                geometry = run_geometry(
                    cap,
                    [v.images for v in views],
                    options=config.geometry,
                    workdir=Path(work) / "geometry",
                    progress=p,
                )
                write_geometry(result, geometry)
                sections["geometry"] = geometry_report(geometry)
        if Stage.REFINE in stages:
            with progress.step(Stage.REFINE, weight[Stage.REFINE]) as p:
                refined, registered = _refine_stage(cap, views, geometry, config, p)
                _write_refined(result, geometry, refined, [views[i].file for i in registered])
                sections["refine"] = refine_report(refined)
    timings = {str(k): v for k, v in progress.timings.items()}
    timings["total"] = time.perf_counter() - t_run
    result.write_json("report.json", _report(config, stages, timings, counts, sections))
    return PipelineResult(
        out=result.root, stages_run=[str(s) for s in stages], timings=timings, files=list(result.written)
    )


def _refine_stage(
    cap: Capture,
    views: list[DecodedView],
    geometry: GeometryResult,
    config: PipelineConfig,
    progress: Progress,
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
        cameras, masks, min_cos=config.geometry.visibility.min_cos, rel_tol=config.geometry.visibility.rel_tol
    )
    refined = refine_surface(
        geometry.vertices,
        geometry.faces,
        cameras,
        observations,
        geometry.visibility[:, registered],
        options=config.refine,
        visibility_fn=visibility_fn,
        progress=progress,
    )
    return refined, registered


def _write_refined(
    result: ResultFolder, geometry: GeometryResult, refined: RefineResult, files: list[str]
) -> None:
    mesh = Mesh(refined.vertices, geometry.faces, albedo=refined.albedo, normals=refined.normals)
    result.write_mesh("mesh.ply", mesh)
    result.write_illumination(illumination_from_arrays(files, refined.sh, refined.rgb_scale))


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


def _write_decoded_views(folder: Path, views: list[DecodedView], progress: Progress) -> None:
    for k, view in enumerate(views):
        write_decoded(folder / f"{view.name}.npz", view.images)
        write_previews(folder, view.name, view.images)
        progress.update((k + 1) / len(views), f"wrote decoded/{view.name}.npz")


def software_versions() -> dict[str, str]:
    """Versions of pmvir and the libraries whose behaviour shapes a result."""
    versions = {"pmvir": __version__, "python": platform.python_version()}
    for module in ("numpy", "scipy", "cv2", "open3d", "pycolmap", "torch"):
        try:
            versions[module] = __import__(module).__version__
        except Exception:  # an optional library that is absent or broken is reported as such
            versions[module] = "unavailable"
    return versions


def _report(
    config: PipelineConfig,
    stages: list[Stage],
    timings: dict[str, float],
    counts: dict,
    sections: dict,
) -> dict:
    return {
        "format": "pmvir-report/1",
        "stages": [str(s) for s in stages],
        "timings_s": timings,
        "counts": counts,
        **sections,
        "parameters": config.model_dump(mode="json"),
        "software": software_versions(),
    }
