"""Moves of the whole surface between and after the stages: the photo-consistent offset scan, the hull fit inside the masks, the fit out to the rims, the fairing."""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
import torch

from pmvir.config import RefineOptions
from pmvir.geometry.mesh_ops import vertex_normals as vertex_normals_np
from pmvir.geometry.silhouette.hull_fit import HullFit, RimFit, fit_inside_hull, fit_to_rims
from pmvir.geometry.surface.clean import facing_projected_areas
from pmvir.progress import Progress
from pmvir.refine.offset import OffsetScan, photo_consistent_offset
from pmvir.refine.relax import Fairing, fair_taubin, fairing_scale, taubin_schedule
from pmvir.refine.state import RefineSetup, Unknowns


def scan_offset(
    setup: RefineSetup, state: Unknowns, opts: RefineOptions, scans: list[OffsetScan], progress: Progress
) -> tuple[Unknowns, list[OffsetScan]]:
    """Move the whole surface along its normals to the most photo-consistent offset (:mod:`pmvir.refine.offset`).

    A uniform offset along the normals leaves the normals, so the albedo and lighting stay valid.
    The first scan covers +-1.5 pixels; the later ones (``offset_scan.mode`` "stages"), which found at most
    0.25 pixels on the captures measured (README), +-0.75 pixels at half the cost.
    """
    progress.update(0.0, "photo-consistent offset along the normals")
    t0 = time.perf_counter()
    v = state.vertices.detach().cpu().numpy().astype(np.float64)
    scan = photo_consistent_offset(
        v,
        setup.faces_np,
        setup.cameras,
        setup.observations,
        min_cos=opts.offset_scan.min_cos,
        max_px=0.75 if scans else 1.5,
        deblur_px=opts.offset_scan.deblur_px,
    )
    scan = replace(scan, seconds=time.perf_counter() - t0)
    if not scan.applied:
        return state, [*scans, scan]
    v = v + scan.offset * vertex_normals_np(v, setup.faces_np)
    moved = torch.from_numpy(v).to(device=setup.device, dtype=setup.dtype)
    return replace(state, vertices=moved), [*scans, scan]



def hold_inside_hull(
    setup: RefineSetup, state: Unknowns, masks: Sequence[np.ndarray | None] | None, fits: list[HullFit]
) -> Unknowns:
    """``state`` with the vertices outside the masks' visual hull moved inside (``surface.hull_tolerance_px``);
    the fit is appended to ``fits``. Unchanged without masks or with the option off."""
    tolerance = setup.opts.surface.hull_tolerance_px
    if masks is None or tolerance is None:
        return state
    t0 = time.perf_counter()
    v = state.vertices.detach().cpu().numpy().astype(np.float64)
    fit = fit_inside_hull(v, setup.faces_np, setup.cameras, masks, tolerance_px=tolerance,
                          views=setup.opts.surface.hull_views, min_gain=setup.opts.surface.hull_min_gain or 0.0)
    fit = replace(fit, seconds=time.perf_counter() - t0)
    fits.append(fit)
    if fit.moved == 0:
        return state
    moved = torch.from_numpy(fit.vertices).to(device=setup.device, dtype=setup.dtype)
    return replace(state, vertices=moved)



def rim_fit_margin(opts: RefineOptions) -> float | None:
    """The masks' margin the rim fit discounts: ``surface.rim_fit_mask_margin_px`` where set; else estimated from the
    rims (None) where the offset scans run, and 0 where they are off. The estimate takes a surface that lies
    inside all round for a margin of the masks, and the scans are what moves such a surface; without them
    (a specular-dominated capture, whose stereo surface lies inside at the depth of its reflections) the
    rims are the only measure of it."""
    if opts.surface.rim_fit_mask_margin_px is not None:
        return opts.surface.rim_fit_mask_margin_px
    return None if opts.offset_scan.mode != "off" else 0.0



def move_to_rims(
    setup: RefineSetup, state: Unknowns, masks: Sequence[np.ndarray | None]
) -> tuple[Unknowns, RimFit]:
    """``state`` with the shoulders whose rims lie inside the masks moved outward (``surface.rim_fit_gain``)."""
    v = state.vertices.detach().cpu().numpy().astype(np.float64)
    fit = fit_to_rims(
        v,
        setup.faces_np,
        setup.cameras,
        masks,
        gain=setup.opts.surface.rim_fit_gain,
        mask_margin_px=rim_fit_margin(setup.opts),
    )
    moved = torch.from_numpy(fit.vertices).to(device=setup.device, dtype=setup.dtype)
    return replace(state, vertices=moved), fit


def fair_surface(setup: RefineSetup, state: Unknowns) -> tuple[Unknowns, Fairing]:
    """``state`` with its surface faired: ``surface.fair_iterations`` pairs of Taubin steps on the
    reference mesh, scaled to the mesh's median projected face area (:func:`pmvir.refine.relax.fairing_scale`
    with ``surface.fair_reference_area_px``; the areas are not computed when that is 0). Each vertex
    keeps its albedo (it moves by a fraction of an edge)."""
    v = state.vertices.detach().cpu().numpy().astype(np.float64)
    reference = setup.opts.surface.fair_reference_area_px
    median = 0.0
    if reference > 0.0:
        areas = facing_projected_areas(v, setup.faces_np, setup.cameras)
        median = float(np.median(areas[areas > 0.0])) if (areas > 0.0).any() else 0.0
    scale = fairing_scale(median, reference)
    iterations = setup.opts.surface.fair_iterations
    faired = fair_taubin(v, setup.faces_np, iterations, scale=scale)
    pairs, mu = taubin_schedule(iterations, scale)
    state = replace(state, vertices=torch.from_numpy(faired).to(device=setup.device, dtype=setup.dtype))
    return state, Fairing(median_face_area_px=median, scale=scale, pairs=pairs, mu=mu)
