"""E_pol's evidence floors: which (vertex, view) pairs carry enough polarization to be trusted, and the DoP weights' floor."""

from __future__ import annotations

import math

import torch

from pmvir.config import RefineOptions
from pmvir.refine.energy import (
    StageProblem,
    azimuth,
    azimuth_distance,
)
from pmvir.refine.sampling import (
    PairSamples,
)


def stage_dop_floor(samples: PairSamples, opts: RefineOptions) -> torch.Tensor | float | None:
    """E_pol's DoP floor for a stage (:func:`dop_floor`), None where every pair is kept (no
    polarization, or ``pol.dop_min`` 0 with a fixed floor)."""
    if not opts.pol.enabled or samples.dop is None:
        return None
    floor = dop_floor(samples, opts)
    return None if isinstance(floor, float) and floor <= 0.0 else floor



def _pol_used(samples: PairSamples, problem: StageProblem) -> torch.Tensor | None:
    """(P,) bool: the pairs E_pol uses at the stage's start (defined AoP, DoP at or above the floor);
    None without AoP samples."""
    if samples.aop_defined is None:
        return None
    return samples.aop_defined if problem.pol_mask is None else samples.aop_defined & problem.pol_mask


def pol_pair_count(samples: PairSamples, problem: StageProblem) -> int:
    """The number of pairs E_pol uses at the stage's start (:func:`_pol_used`)."""
    used = _pol_used(samples, problem)
    return 0 if used is None else int(used.sum())



def pol_weight_mean(samples: PairSamples, problem: StageProblem) -> float | None:
    """E_pol's mean pair weight over the pairs it uses at the stage's start (:func:`_pol_used`);
    None without weights or without such pairs."""
    used = _pol_used(samples, problem)
    if problem.pol_weight is None or used is None or not bool(used.any()):
        return None
    return float(problem.pol_weight[used].mean())



def floor_summary(floor: torch.Tensor | float | None) -> float | None:
    """The stage's DoP floor as one number for the log: 0 (every pair kept), the floor, its median
    (per-pair floors), or None (no pair is evidence: E_pol off)."""
    if floor is None:
        return 0.0
    if isinstance(floor, torch.Tensor):
        return float(floor.median())
    return None if math.isinf(floor) else floor



def pol_evidence(samples: PairSamples) -> torch.Tensor | None:
    """(P,) what E_pol weights and floors each pair by: its DoP, in units of its own AoP noise.

    With the views' measured polarization noise sigma (``refine.pol.aop_noise`` 'closure',
    :func:`pmvir.polarization.noise.closure_noise`): ``rho * m / sigma`` with m the median sigma
    over the stage's pairs, i.e. the AoP's signal-to-noise ratio rho / sigma scaled to read as a
    DoP at the median noise. Unmeasured (NaN) noise counts as m; sigma is held above m / 4, so no
    pair outweighs others by noise alone more than 16-fold at ``pol.dop_weight_power`` 2. Without noise
    maps: the DoP itself. None without polarization.
    """
    if samples.dop is None or samples.aop_noise is None:
        return samples.dop
    noise = samples.aop_noise
    measured = torch.isfinite(noise) & (noise > 0)
    if not bool(measured.any()):
        return samples.dop
    ref = noise[measured].median()
    noise = torch.where(measured, noise, ref).clamp_min(0.25 * ref)
    return samples.dop * (ref / noise)



def aop_noise_deg(samples: PairSamples) -> torch.Tensor | None:
    """(P,) each pair's AoP noise in degrees as the raw mosaic predicts it: ``sigma / (2 sqrt(2) rho)``.

    sigma is the closure noise (:func:`pmvir.polarization.noise.closure_noise`, the noise of r / s0
    with r = (I0 + I90) - (I45 + I135)); s1 / s0 and s2 / s0 each carry sigma / sqrt(2) of it, and the
    AoP, half the angle of (s1, s2), turns by that over 2 rho. Unmeasured (NaN) noise counts as the
    median of the measured pairs'. None without DoP or noise maps, or where no pair is measured.
    """
    if samples.dop is None or samples.aop_noise is None:
        return None
    noise = samples.aop_noise
    measured = torch.isfinite(noise) & (noise >= 0)
    if not bool(measured.any()):
        return None
    noise = torch.where(measured, noise, noise[measured].median())
    return torch.rad2deg(noise / (2.0 * math.sqrt(2.0) * samples.dop.clamp_min(1e-3)))


def aop_noise_weight(samples: PairSamples, scale_deg: float) -> torch.Tensor | None:
    """(P,) E_pol's absolute pair weights ``1 / (1 + (nu / scale_deg)^2)``, nu from :func:`aop_noise_deg`.

    The inverse of the AoP's error variance when that is ``a^2 + (b nu)^2`` (a floor a the noise does
    not explain: demosaicing, the renderer's mixing of diffuse and specular), scaled to 1 at nu = 0,
    with ``scale_deg = a / b``. Not normalized: a noisier capture weighs E_pol less. None where
    :func:`aop_noise_deg` is.
    """
    nu = aop_noise_deg(samples)
    if nu is None:
        return None
    return 1.0 / (1.0 + (nu / scale_deg) ** 2)


def pol_pair_weights(
    samples: PairSamples, evidence: torch.Tensor | None, pol_mask: torch.Tensor | None, opts: RefineOptions
) -> torch.Tensor | None:
    """(P,) E_pol's pair weights for a stage, None for none (every pair weighs 1).

    With ``pol.aop_noise_scale_deg`` > 0 and noise maps: :func:`aop_noise_weight`, absolute. Otherwise,
    with ``pol.dop_weight``: the evidence (:func:`pol_evidence`) to ``pol.dop_weight_power``, divided by
    its mean over the pairs ``pol_mask`` keeps when ``pol.dop_weight_normalized``.
    """
    if opts.pol.aop_noise_scale_deg > 0:
        absolute = aop_noise_weight(samples, opts.pol.aop_noise_scale_deg)
        if absolute is not None:
            return absolute
    if evidence is None or not opts.pol.dop_weight:
        return None
    weight = evidence
    if opts.pol.dop_weight_power != 1.0:
        weight = weight.clamp_min(0.0) ** opts.pol.dop_weight_power
    if opts.pol.dop_weight_normalized:
        used = weight if pol_mask is None else weight[pol_mask]
        weight = weight / (used.mean() if used.numel() else weight.new_tensor(1.0)).clamp_min(1e-6)
    return weight


def above_floor(
    dop: torch.Tensor, evidence: torch.Tensor, floor: torch.Tensor | float, opts: RefineOptions
) -> torch.Tensor:
    """E_pol's pair mask: the 'evidence' floor applies to :func:`pol_evidence` (and the DoP stays at
    or above ``pol.dop_min``); the 'fixed' and 'shot' floors to the DoP."""
    if opts.pol.dop_min_noise == "evidence":
        return (evidence >= floor) & (dop >= opts.pol.dop_min)
    return dop >= floor



def dop_floor(samples: PairSamples, opts: RefineOptions) -> torch.Tensor | float:
    """E_pol's DoP floor per pair (``pol.dop_min``, ``pol.dop_min_noise``).

    'shot': ``pol.dop_min * sqrt(max(1, m / I))`` with I the pair's colour-mean I_int (recovered from
    I_min = (1 - rho) I_int when E_pho uses I_min) and m its median over the stage's pairs: the
    standard deviation of a DoP measured under shot noise grows as 1 / sqrt(I).

    Returns:
        a float (``'fixed'``; ``'evidence'``, see :func:`evidence_dop_floor`, ``inf`` when no pair
        is evidence) or a (P,) tensor (``'shot'``).
    """
    if opts.pol.dop_min_noise == "fixed" or samples.dop is None:
        return opts.pol.dop_min
    if opts.pol.dop_min_noise == "evidence":
        return evidence_dop_floor(samples, opts)
    i = samples.intensity.mean(dim=-1)
    if opts.pho.intensity == "min":
        i = i / (1.0 - samples.dop).clamp_min(0.05)
    i = i.clamp_min(1e-6)
    ratio = (i.median() / i).clamp_min(1.0)
    return opts.pol.dop_min * torch.sqrt(ratio)



#: Mean azimuth distance eta of an AoP unrelated to the surface (eta is uniform on [0, pi/4]).
CHANCE_ETA = math.pi / 8.0



def evidence_dop_floor(samples: PairSamples, opts: RefineOptions) -> float:
    """The DoP from which the observed AoP is evidence about the current surface ('evidence').

    The pairs at or above ``pol.dop_min`` (with a defined AoP and azimuth) are sorted by their
    evidence (:func:`pol_evidence`: the DoP, over its noise where the views measure it), most
    polarized first, and cut into bins of ``max(pol.dop_evidence_bin, 2% of them)`` pairs (a short
    remainder joins the last bin). Walking down, a bin is evidence while its mean azimuth distance
    eta to the samples' normals is at most ``pol.dop_evidence_ratio * pi / 8``: an AoP unrelated to
    the surface (noise, false polarization at albedo edges) has mean pi/8. The floor is the
    lowest evidence of the last such bin; the walk stops at the first bin that is not (when none is
    not, the floor is ``pol.dop_min``).

    Returns:
        the floor (at least ``pol.dop_min``), or ``inf`` when the most polarized bin is no evidence
        (E_pol then has no pairs this stage).
    """
    evidence = pol_evidence(samples)
    if evidence is None or samples.dop is None or samples.aop is None or samples.aop_defined is None:
        return opts.pol.dop_min
    alpha, defined = azimuth(samples.normal_cam, samples.ray_cam)
    usable = defined & samples.aop_defined & (samples.dop >= opts.pol.dop_min)
    ranked = evidence[usable]
    if ranked.numel() == 0:
        return opts.pol.dop_min
    eta = azimuth_distance(alpha[usable], samples.aop[usable])
    order = torch.argsort(ranked, descending=True)
    ranked, eta = ranked[order], eta[order]
    n = ranked.numel()
    size = min(n, max(opts.pol.dop_evidence_bin, math.ceil(0.02 * n)))
    starts = list(range(0, n, size))
    if len(starts) > 1 and n - starts[-1] < size:
        starts.pop()
    ends = [*starts[1:], n]
    bound = opts.pol.dop_evidence_ratio * CHANCE_ETA
    floor = math.inf
    for a, b in zip(starts, ends, strict=True):
        if float(eta[a:b].mean()) > bound:
            break
        floor = float(ranked[b - 1])
    else:
        return opts.pol.dop_min  # every bin is evidence: keep every pair above dop_min
    return max(floor, opts.pol.dop_min)
