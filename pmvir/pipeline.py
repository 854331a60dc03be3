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
from collections.abc import Sequence
from contextlib import nullcontext
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from pmvir import __version__, stage_cache
from pmvir.capture import MANIFEST_NAME, Capture, RawFrame, open_capture
from pmvir.config import DecodeOptions, PipelineConfig, RefineOptions
from pmvir.decode import decode_frame, write_decoded, write_previews
from pmvir.errors import ConfigError, PmvirError, ShapeError
from pmvir.export import write_previews as write_view_previews
from pmvir.export import write_refined_outputs
from pmvir.geometry.silhouette.hull_fit import RimFit
from pmvir.geometry.stage import GeometryResult, geometry_report, run_geometry, write_geometry
from pmvir.io.illumination import illumination_from_arrays
from pmvir.io.ply import Mesh
from pmvir.memory import check_memory, mapped_overhead_bytes, memory_limit
from pmvir.polarization.noise import closure_noise
from pmvir.polarization.stokes import PolarizationImages
from pmvir.progress import Progress
from pmvir.refine import RefineResult, make_visibility_fn, observation_from_decoded, refine_surface
from pmvir.refine.coarse import CoarseMesh
from pmvir.refine.sampling import Observation
from pmvir.refine.state import StageLog
from pmvir.result import ResultFolder
from pmvir.stages import STAGES, Stage, stages_through
from pmvir.working import (
    BinnedCapture,
    bin_images,
    bin_noise,
    binning_factor,
    frame_extent,
    resolution_report,
    unbin_mask,
    working_capture,
)

#: Above this median DoP inside the masks (the median over views of each view's median) the object is
#: specular-dominated and report.json warns: measured on path-traced 36-view captures, per-view medians
#: are 0.01-0.02 on Lambert, 0.02-0.12 on plastic and 0.25-0.37 on a smooth conductor.
SPECULAR_MEDIAN_DOP = 0.2

#: Share of the whole run each stage takes, for the overall progress fraction.
STAGE_WEIGHTS: dict[str, float] = {"decode": 0.1, "geometry": 0.3, "refine": 0.6}
#: The pipeline's stages, in order (the one definition; the CLI, config and service read it).
STAGE_ORDER: tuple[Stage, ...] = STAGES


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
    warnings: list[str] = field(default_factory=list)


def decode_views(
    cap: Capture, config: PipelineConfig, progress: Progress | None = None, *, factor: int = 1
) -> list[DecodedView]:
    """Decode every frame of an open capture (stage 1), one at a time, each binned by ``factor``
    (:mod:`pmvir.working`) right away so that only the working-resolution images are held."""
    progress = progress or Progress.none()
    views = []
    n = len(cap.frames)
    for i, frame in enumerate(cap.frames):
        images = bin_images(_decode_frame(cap, i, config.decode), factor)
        views.append(DecodedView(index=i, name=frame.name, file=frame.file, images=images))
        progress.update((i + 1) / n, f"decoded {frame.file}")
    return views


def _decode_frame(
    cap: Capture, i: int, options: DecodeOptions, raw: RawFrame | None = None
) -> PolarizationImages:
    """Frame ``i`` of an open capture demosaiced with ``options`` (its saturation and mask applied);
    ``raw``: the frame already read, if the caller has it."""
    raw = cap.read_raw(i) if raw is None else raw
    return decode_frame(
        raw.mosaic, cap.layout, saturated=raw.saturated, mask=cap.read_mask(i), options=options
    )


def median_dop_in_masks(cap: Capture, views: list[DecodedView]) -> float | None:
    """The median over views of each view's median DoP over its valid pixels inside its mask.

    ``views`` are decoded with their masks (:func:`decode_views`), so their ``valid`` already
    excludes the background; views whose frame has no mask are skipped. None when no view has a
    mask (the background's DoP would dilute it) or a valid pixel.
    """
    medians = []
    for view in views:
        if cap.frames[view.index].mask is None:
            continue
        dop = view.images.dop[view.images.valid]
        if dop.size:
            medians.append(float(np.median(dop)))
    return float(np.median(medians)) if medians else None


def is_specular(median_dop: float | None) -> bool:
    """Whether a capture of this median DoP inside the masks is specular-dominated."""
    return median_dop is not None and median_dop > SPECULAR_MEDIAN_DOP


def specular_warning(median_dop: float | None, options: RefineOptions) -> str | None:
    """The warning for a specular-dominated object (median DoP above ``SPECULAR_MEDIAN_DOP``), or None."""
    if not is_specular(median_dop):
        return None
    scan = (
        "the offset scan is off for it (refine.offset_scan.specular; the scan moved a path-traced "
        "conductor armadillo 37% away from the truth)"
        if refinement_options(options, median_dop).offset_scan.mode != options.offset_scan.mode
        else "the offset scan runs as set (refine.offset_scan.specular 'same')"
    )
    return (
        f"the object looks specular-dominated: its median DoP inside the masks is {median_dop:.2f} "
        f"(above {SPECULAR_MEDIAN_DOP}; diffuse plastic shows 0.02-0.12). The refinement's photometric "
        f"term models diffuse reflection, which a metal or a dark glossy surface lacks; {scan}. "
        "Compare mesh.ply with initial.ply."
    )


def unregistered_warning(missing: Sequence[str], views: int) -> str | None:
    """The warning for the views SfM could not place (``missing``, of ``views``; they are left out of the
    mesh, albedo and lighting), or None when there are none."""
    if not missing:
        return None
    shown = ", ".join(missing[:12]) + (f" and {len(missing) - 12} more" if len(missing) > 12 else "")
    return (
        f"SfM registered {views - len(missing)} of {views} views; {shown} are left out of the mesh, "
        "the albedo and the lighting. They share too few features with the registered views: views about "
        "10-20 degrees apart around the object register, and so do views given with their poses. "
        "report.json's poses section says what each SfM step found."
    )


MASK_MARGIN_WARNING_PX = 0.5
"""An estimated mask margin (:class:`pmvir.geometry.silhouette.hull_fit.RimFit`) at or above this is warned about."""


def mask_margin_warning(fit: RimFit | None) -> str | None:
    """The warning for masks that reach past the refined surface's rims everywhere (dilated masks, or a
    surface inside all round), or None. With a margin set (or 0 where the offset scans are off), only
    what the estimate finds beyond it is warned about: a known margin that matches is not."""
    if fit is None:
        return None
    unaccounted = fit.margin_estimate_px - (0.0 if fit.margin_estimated else fit.mask_margin_px)
    if unaccounted < MASK_MARGIN_WARNING_PX:
        return None
    done = (
        "The rim fit discounted that margin (set refine.surface.rim_fit_mask_margin_px if it is known)"
        if fit.margin_estimated
        else f"The rim fit discounted {fit.mask_margin_px:.2f} px as set (refine.surface.rim_fit_mask_margin_px; 0 where "
        "the offset scans are off) and may have pushed the surface out toward them"
    )
    return (
        f"the masks reach about {fit.margin_estimate_px:.2f} px past the refined surface's rims nearly "
        f"everywhere (exact masks give 0): they look dilated, or the surface lies inside all round. {done}. "
        "Compare mesh.ply with initial.ply."
    )


DRAWN_HULL_MIN_GAIN = 0.2
"""``refine.surface.hull_min_gain`` on masks the isolation drew when it is None (on given masks: 0).
Measured (docs/method.md, section 5): on 16-view knots without masks the farthest vertex near the
table went from 0.04-0.05 of the diagonal to 0.02; on the Stanford models with their given masks
it cost 2 % of completeness for the same accuracy."""


def refinement_options(options: RefineOptions, median_dop: float | None, *, drawn_masks: bool = False) -> RefineOptions:
    """The refinement's options for a capture of this median DoP inside the masks: a specular-dominated
    one is refined without the offset scan unless ``refine.offset_scan.specular`` is 'same'.

    On masks the isolation drew (``drawn_masks``) the rim fit does not run and the hull fit takes
    ``surface.drawn_hull_tolerance_px`` and at least two views (``surface.hull_views``): the fits
    move the surface to a mask's outline to the pixel, and a drawn mask misses or adds a pixel or two
    of it here and there (the columns down to the support, too), or cuts into the object where its
    colours match the support's; what two views' drawn masks rule out by more than a pixel is not
    the object's. Unless ``surface.hull_min_gain`` is set, the hull fit stops a vertex where a step
    along its normal brings it less than :data:`DRAWN_HULL_MIN_GAIN` of its length closer to the
    masks (a web across a loop, a flap by the table). The observations leave
    ``views.drawn_mask_margin_px`` more pixels inside the outline unsampled, as a drawn mask reaches
    about a pixel past the object's and the samples there mix the background into its colour.
    """
    if drawn_masks:
        gain = options.surface.hull_min_gain
        fits = {"hull_tolerance_px": options.surface.drawn_hull_tolerance_px, "rim_fit_gain": 0.0,
                "hull_views": max(2, options.surface.hull_views),
                "hull_min_gain": DRAWN_HULL_MIN_GAIN if gain is None else gain}
        margin = {"silhouette_margin_px": options.views.silhouette_margin_px + options.views.drawn_mask_margin_px}
        options = options.model_copy(update={
            "surface": options.surface.model_copy(update=fits),
            "views": options.views.model_copy(update=margin),
        })
    if is_specular(median_dop) and options.offset_scan.specular == "off" and options.offset_scan.mode != "off":
        return options.model_copy(update={"offset_scan": options.offset_scan.model_copy(update={"mode": "off"})})
    return options


def redecodes_for_refinement(decode: DecodeOptions, refine: RefineOptions) -> bool:
    """Whether the refinement decodes the frames again (``refine.demosaic`` names another method)."""
    return refine.demosaic not in ("same", decode.demosaic)


def refinement_observations(
    cap: Capture,
    views: list[DecodedView],
    indices: list[int],
    decode: DecodeOptions,
    refine: RefineOptions,
    progress: Progress | None = None,
    masks: Sequence[np.ndarray | None] | None = None,
) -> list[Observation]:
    """The images the refinement fits, for the views ``indices`` of an open capture.

    With ``refine.demosaic`` 'same' (or the decode stage's method) these are the decoded
    ``views``; otherwise each frame is decoded once more with ``refine.demosaic`` (the decode
    stage's noise floor, saturation and mask), one at a time, so only the observations stay
    in memory. With ``refine.pol.aop_noise`` 'closure' (and E_pol on) each observation carries its
    frame's polarization noise (:func:`pmvir.polarization.noise.closure_noise` over its valid
    pixels), measured from the raw mosaic read once more. A :class:`~pmvir.working.BinnedCapture`
    gives observations binned as its decoded ``views`` are (the noise measured at full
    resolution inside the binned valid pixels, then binned). ``masks`` (one per index, e.g. the ones
    the isolation drew) limit each observation as a given mask does (:func:`within_mask`), before
    its noise is measured.
    """
    progress = progress or Progress.none()
    factor = cap.factor if isinstance(cap, BinnedCapture) else 1
    cap = cap.full if isinstance(cap, BinnedCapture) else cap
    redecode = redecodes_for_refinement(decode, refine)
    options = decode.model_copy(update={"demosaic": refine.demosaic}) if redecode else decode
    noise = refine.pol.enabled and refine.pol.aop_noise == "closure"
    observations = []
    for k, i in enumerate(indices):
        raw = cap.read_raw(i) if redecode or noise else None
        images = bin_images(_decode_frame(cap, i, options, raw), factor) if redecode else views[i].images
        obs = observation_from_decoded(vars(images), intensity=refine.pho.intensity)
        obs = within_mask(obs, masks[k] if masks is not None else None)
        if raw is not None and noise:
            valid = unbin_mask(obs.valid, factor, raw.mosaic.shape)
            sigma = closure_noise(raw.mosaic, cap.layout, valid=valid, sigma_px=refine.pol.aop_noise_px)
            sigma = bin_noise(sigma, factor)
            obs = replace(obs, aop_noise=sigma)
        observations.append(obs)
        if redecode:
            progress.update((k + 1) / len(indices), f"decoded {cap.frames[i].file} with {refine.demosaic}")
    return observations


def run(
    config: PipelineConfig,
    capture: str | Path | Capture,
    out: str | Path,
    *,
    progress: Progress | None = None,
    cache: str | Path | None = None,
    resume_from: Stage | str | None = None,
    max_memory: int | None = None,
) -> PipelineResult:
    """Run the pipeline on a capture and write the result folder.

    Args:
        config: the typed configuration (CLI and HTTP job options alike).
        capture: a capture folder (with capture.json, or frames whose manifest is inferred),
            its capture.json, a .zip, or an open Capture (left open).
        out: the result folder (created; files of the same names are replaced).
        progress: reports ``(stage, overall fraction, message)`` (the fraction never
            decreases) and is asked to cancel at every stage, step and iteration boundary.
        cache: a folder where the decode and geometry stages save their outputs
            (:mod:`pmvir.stage_cache`), for a later run to resume from.
        resume_from: the first stage to compute; the outputs of the stages before it are
            loaded from ``cache`` (made with the same options for those stages).
        max_memory: the run's memory limit in bytes (else ``PMVIR_JOB_MEMORY``, else none): a
            capture whose estimated peak (:mod:`pmvir.memory`) is above it fails before decoding.

    Returns:
        The stages run, their timings and the files written (relative to ``out``).

    Raises:
        CaptureError: the capture is unreadable or invalid (names the file).
        ReconstructionError: a stage could not produce a usable result.
        CanceledError: the progress object's ``should_cancel()`` returned True.
        ResourceLimitError: the capture needs more memory than ``max_memory`` (names what fits).
    """
    progress = progress or Progress.none()
    result = ResultFolder(out)
    result.root.mkdir(parents=True, exist_ok=True)
    stages = stages_through(config.stop_after)
    resume = Stage(resume_from or Stage.DECODE)
    if resume.position > 0 and cache is None:
        raise PmvirError(f"resume_from={resume} needs the cache folder of an earlier run")
    if resume not in stages:
        raise ConfigError(f"resume_from={resume} is after stop_after={config.stop_after}")
    total = sum(STAGE_WEIGHTS[s] for s in stages)
    weight = {s: STAGE_WEIGHTS[s] / total for s in stages}
    t_run = time.perf_counter()
    sections: dict[str, object] = {}
    warnings: list[str] = []
    opened = nullcontext(capture) if isinstance(capture, Capture) else open_capture(capture)
    with opened as cap, tempfile.TemporaryDirectory(prefix=".work-", dir=out) as work:
        counts = {"frames": len(cap.frames)}
        result.write_json(MANIFEST_NAME, cap.manifest.model_dump(mode="json", exclude_none=True))
        sections["capture"] = {
            "manifest": "given" if cap.inferred is None else "inferred",
            "inferred": list(cap.inferred or ()),
        }
        extent = frame_extent(cap)
        factor = 1 if config.stop_after == Stage.DECODE else binning_factor(*extent, config.decode.max_working_size_px)
        work_cap = working_capture(cap, factor)
        limit, source = memory_limit(max_memory)
        check_memory(
            str(capture), extent, len(cap.frames), factor, limit, source,
            decode_only=config.stop_after == Stage.DECODE, reserved=mapped_overhead_bytes(),
        )
        sections["resolution"] = resolution_report(extent, factor)
        with progress.step(Stage.DECODE, weight[Stage.DECODE]) as p:
            if cache is not None and resume.position > Stage.DECODE.position:  # resuming needs a cache
                views = stage_cache.load_stage(cache, Stage.DECODE, config)
                p.update(0.9, "decoded frames loaded from the cache")
            elif config.stop_after == Stage.DECODE:  # the decoded frames are the result
                with p.step("read", 0.5) as q:
                    views = decode_views(cap, config, q)
                with p.step("write", 0.5) as q:
                    result.write_folder("decoded", lambda d: _write_decoded_views(d, views, q))
            else:
                with p.step("read", 0.9) as q:
                    views = decode_views(cap, config, q, factor=factor)
            if cache is not None and resume.position == Stage.DECODE.position:
                stage_cache.save_stage(cache, Stage.DECODE, config, views)
            with p.step("previews", 0.1) as q:
                write_view_previews(
                    result, [(v.name, v.images) for v in views], max_size=config.export.preview_max_size, progress=q
                )
        median_dop = median_dop_in_masks(work_cap, views)
        sections["decode"] = {"median_dop_in_masks": median_dop}
        if (warning := specular_warning(median_dop, config.refine)) is not None:
            warnings.append(warning)
        if Stage.GEOMETRY in stages:
            with progress.step(Stage.GEOMETRY, weight[Stage.GEOMETRY]) as p:
                if cache is not None and resume.position > Stage.GEOMETRY.position:
                    geometry = stage_cache.load_stage(cache, Stage.GEOMETRY, config)
                    p.update(1.0, "cameras and initial surface loaded from the cache")
                else:
                    geometry = run_geometry(
                        work_cap,
                        [v.images for v in views],
                        options=config.geometry,
                        workdir=Path(work) / "geometry",
                        progress=p,
                    )
                    if cache is not None:
                        stage_cache.save_stage(cache, Stage.GEOMETRY, config, geometry)
                write_geometry(result, geometry)
                sections["geometry"] = report = geometry_report(geometry)
                if (warning := unregistered_warning(report["poses"]["unregistered"], len(geometry.names))) is not None:
                    warnings.append(warning)
        if Stage.REFINE in stages:
            with progress.step(Stage.REFINE, weight[Stage.REFINE]) as p:
                drawn = geometry.isolation is not None
                refine_options = refinement_options(config.refine, median_dop, drawn_masks=drawn)
                refined, registered = _refine_stage(work_cap, views, geometry, config, refine_options, p, share=0.85)
                mesh = _write_refined(result, geometry, refined, [views[i].file for i in registered])
                sections["refine"] = {
                    **refine_report(refined),
                    "offset_scan": refine_options.offset_scan.mode,
                    "silhouette_margin_px": refine_options.views.silhouette_margin_px,
                    "masks": "drawn" if drawn else "given" if any(m is not None for m in geometry.masks) else "none",
                }
                if (warning := mask_margin_warning(refined.rim_fit)) is not None:
                    warnings.append(warning)
                with p.step("exports", 0.15) as q:
                    sections["exports"] = write_refined_outputs(
                        result,
                        mesh,
                        [(views[i].name, views[i].images) for i in registered],
                        [cam for i in registered if (cam := geometry.cameras[i]) is not None],
                        refined.shading_coefficients(),
                        refined.rgb_scale,
                        config=config,
                        progress=q,
                    )
    timings = {str(k): v for k, v in progress.timings.items()}
    timings["total"] = time.perf_counter() - t_run
    if resume.position > 0:
        sections["resumed_from"] = str(resume)
    sections["warnings"] = warnings
    result.write_json("report.json", _report(config, stages, timings, counts, sections))
    return PipelineResult(
        out=result.root, stages_run=[str(s) for s in stages], timings=timings, files=list(result.written),
        warnings=warnings,
    )


def _refine_stage(
    cap: Capture,
    views: list[DecodedView],
    geometry: GeometryResult,
    config: PipelineConfig,
    options: RefineOptions,
    progress: Progress,
    share: float,
) -> tuple[RefineResult, list[int]]:
    """Polarimetric MVIR on the registered views (stage 3) with ``options`` (the run's refine options
    as :func:`refinement_options` adapts them), ``share`` of ``progress``.

    Returns the result and those views' indices.
    """
    registered = [i for i, cam in enumerate(geometry.cameras) if cam is not None]
    cameras = [cam for cam in geometry.cameras if cam is not None]  # in the order of registered
    masks = [geometry.masks[i] if geometry.masks else cap.read_mask(i) for i in registered]  # given or isolated
    drawn = masks if geometry.isolation is not None else None  # given masks are in the decoded views already
    decode_share = 0.0
    if not redecodes_for_refinement(config.decode, options):
        observations = refinement_observations(cap, views, registered, config.decode, options, masks=drawn)
    else:  # the frames are decoded once more: a timed step of its own
        decode_share = 0.1 * share
        with progress.step("images", decode_share) as q:
            observations = refinement_observations(cap, views, registered, config.decode, options, q, masks=drawn)
    visibility_fn = make_visibility_fn(
        cameras, masks, min_cos=config.geometry.visibility.min_cos, rel_tol=config.geometry.visibility.rel_tol
    )
    coarse = coarse_surface(geometry, registered) if options.stages.coarse > 0 else None
    with progress.step("optimize", share - decode_share) as q:
        refined = refine_surface(
            geometry.vertices,
            geometry.faces,
            cameras,
            observations,
            geometry.visibility[:, registered],
            options=options,
            visibility_fn=visibility_fn,
            progress=q,
            masks=masks,
            coarse=coarse,
        )
    return refined, registered


def within_mask(obs: Observation, mask: np.ndarray | None) -> Observation:
    """The observation with its pixels outside ``mask`` invalid, as the decode stage makes them for a
    given mask: a mask the isolation drew keeps the table and the room out of E_pho, E_pol and the
    intensity scale, as a given one does.

    Raises:
        ShapeError: a mask of another size than the observation's images.
    """
    if mask is None:
        return obs
    if mask.shape != obs.valid.shape:
        raise ShapeError(f"a {mask.shape} mask for a {obs.valid.shape} observation")
    return replace(obs, valid=obs.valid & mask.astype(bool))


def coarse_surface(geometry: GeometryResult, registered: list[int]) -> CoarseMesh | None:
    """The surface one sqrt(3) step before the subdivided one (``refine.stages.coarse``), kept by the
    geometry stage, with its visibility in the ``registered`` views; None where the initial surface was
    not subdivided.

    Raises:
        PmvirError: a cached geometry stage that kept no coarse surface of its subdivided one.
    """
    if geometry.subdivision_rounds == 0:
        return None
    if geometry.coarse is None:
        raise PmvirError(
            "refine.stages.coarse needs the surface one subdivision step short, which the cached geometry "
            "stage did not keep: run the geometry stage again (resume_from='geometry')"
        )
    vertices, faces, visibility = geometry.coarse
    return CoarseMesh(vertices, faces, visibility[:, registered])


def _write_refined(
    result: ResultFolder, geometry: GeometryResult, refined: RefineResult, files: list[str]
) -> Mesh:
    mesh = Mesh(refined.vertices, geometry.faces, albedo=refined.albedo, normals=refined.normals)
    result.write_mesh("mesh.ply", mesh)
    result.write_illumination(illumination_from_arrays(files, refined.sh, refined.rgb_scale, refined.sh_high))
    return mesh


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
        "pol_pairs": st.pol_pairs,
        "dop_floor": st.dop_floor,
        "pol_weight_mean": st.pol_weight_mean,
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
        "coarse_vertices": refined.coarse_vertices,
        "intensity_factor": refined.intensity_factor,
        "timings": {k: float(v) for k, v in refined.timings.items()},
        "stages": [
            _stage_report(st) | {"timings": {k: float(v) for k, v in parts.items()}}
            for st, parts in zip(refined.stages, refined.stage_timings or [{}] * len(refined.stages), strict=True)
        ],
        "offset_scans": [scan.to_dict() for scan in refined.offset_scans],
        "hull_fits": [fit.to_dict() for fit in refined.hull_fits],
        "rim_fit": None if refined.rim_fit is None else refined.rim_fit.to_dict(),
        "fairing": None if refined.fairing is None else refined.fairing.to_dict(),
        "lighting_fit": None if refined.lighting_fit is None else _stage_report(refined.lighting_fit),
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
        except Exception:  # noqa: BLE001 - an absent or broken optional library is reported as such
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
