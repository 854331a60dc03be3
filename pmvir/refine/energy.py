"""The four terms of the polarimetric MVIR cost (paper, section 4.3), each its own function.

    E = E_pho + tau1 * E_pol + tau2 * E_gsm + tau3 * E_psm [+ tau_light * E_light]

E_light (not the paper's, ``RefineOptions.lighting.coupling``) ties the views' lighting together.

All functions are pure, vectorized over every (vertex, view) pair / face /
edge, and differentiable with autograd. Intensities and albedos are in the
capture's normalized units times ``units`` (by default 6.4 over the capture's median
intensity, ``RefineOptions.pho.intensity_scale`` and ``intensity_units``: the paper's weights
assume an intensity scale its text does not fix; see :class:`pmvir.config.RefineOptions`).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch

from pmvir.errors import ConfigError, ShapeError
from pmvir.polarization.azimuth import perspective_azimuth
from pmvir.refine.mesh_ops import face_normals, normalize, vertex_normals
from pmvir.refine.sampling import PairSamples, PairSet, ViewStack, sample_pairs
from pmvir.sh import sh_basis, sh_order_of

#: Offsets o of the paper's Eq. (eta): eta = min_o |alpha - phi + o|, for alpha in [0, 2 pi), phi in [0, pi).
ETA_OFFSETS = (-2.0 * math.pi, -1.5 * math.pi, -math.pi, -0.5 * math.pi, 0.0, 0.5 * math.pi, math.pi)


def azimuth(normal_cam: torch.Tensor, ray_cam: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Perspective-exact azimuth of camera-frame normals seen along their rays (spec section 2).

    alpha = atan2(e . r1, e . r0) in the ray's reference axes, wrapped to [0, 2 pi) as in
    the paper (section 3.2: the azimuth ranges over [0, 2 pi)); see
    :func:`pmvir.polarization.azimuth.perspective_azimuth`, the one implementation.

    Args:
        normal_cam: (..., 3) unit normals in OpenCV camera axes.
        ray_cam: (..., 3) unit directions from the camera centre to the points, camera axes.

    Returns:
        alpha (...) in [0, 2 pi) and a bool mask (...) of where it is defined.

    Example:
        Seen on the optical axis, a normal along camera +x has azimuth 0, one along image up
        (camera -y) 90 degrees, and one facing the camera has none:

        >>> normals = torch.tensor([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
        >>> alpha, defined = azimuth(normals, torch.tensor([0.0, 0.0, 1.0]).expand(3, 3))
        >>> bool(alpha[0] == 0), round(math.degrees(alpha[1]), 4), defined.tolist()
        (True, 90.0, [True, True, False])
    """
    return perspective_azimuth(normal_cam, ray_cam)


def azimuth_distance(alpha: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """eta of the paper's Eq. (eta): the distance from alpha to the nearest of phi + {-pi, -pi/2, 0, pi/2, pi, ...}.

    The seven terms |alpha - phi + o|, o in ``ETA_OFFSETS``, with alpha in [0, 2 pi) and
    phi in [0, pi] put alpha - phi in (-pi, 2 pi); the seven candidates are spaced
    pi/2 over [-pi, 2 pi], so eta <= pi/4 always (theta in [0, 1]). Their minimum is the distance
    from alpha - phi to the nearest multiple of pi/2, computed as such (one remainder instead of
    seven candidates; the same value and derivative).

    Args:
        alpha: (...) azimuth, radians in [0, 2 pi).
        phi: (...) AoP, radians in [0, pi].

    Returns:
        (...) eta in [0, pi/4].
    """
    quarter = 0.5 * math.pi
    return (torch.remainder(alpha - phi + 0.5 * quarter, quarter) - 0.5 * quarter).abs()


def polarimetric_cost(eta: torch.Tensor, *, k: float) -> torch.Tensor:
    """((exp(-k theta) - exp(-k)) / (1 - exp(-k)))^2 with theta = 1 - 4 eta / pi, per element.

    Zero when eta = 0 (the azimuth matches one of the four AoP candidates), one when
    eta = pi/4 (halfway between two candidates).
    """
    theta = 1.0 - 4.0 * eta / math.pi
    ek = math.exp(-k)
    f = (torch.exp(-k * theta) - ek) / (1.0 - ek)
    return f * f


def pair_light(
    normals: torch.Tensor, sh: torch.Tensor, rgb_scale: torch.Tensor, pairs: PairSet
) -> torch.Tensor:
    """S(N_i, L_basis,c) * L_scale,c of every pair, (P, 3): the rendered colour divided by the albedo.


    Args:
        normals: (N, 3) unit world vertex normals N(X).
        sh: (V, T) coefficients L_basis per view: pmvir-sh9 (T = 9) or a richer basis of
            :func:`pmvir.sh.sh_basis` (T = 16 or 25, pmvir-sh9 first).
        rgb_scale: (V, 3) L_scale per view.
        pairs: the stage's pairs.
    """
    if sh.shape[0] != len(pairs.offsets) - 1:  # pairs.flat indexes (N, V) with the pairs' V
        raise ShapeError(f"lighting for {sh.shape[0]} views, but the pairs are of {len(pairs.offsets) - 1}")
    order = sh_order_of(sh.shape[1])
    # The shading of every vertex under every view's lighting, (N, V), then one value gathered per
    # pair: the basis is evaluated per vertex, not per pair (P is about 12 N), and no (P, T) basis is
    # gathered or scattered back (N V is far below P T).
    per_vertex = sh_basis(normals, order) @ sh.T
    shading = per_vertex.reshape(-1).index_select(0, pairs.flat)
    return shading[:, None] * rgb_scale.index_select(0, pairs.view)


def _fresnel_reflectance(cos_o: torch.Tensor, ior: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Fresnel reflectances (R_s, R_p) of a dielectric of index ``ior`` for light crossing its surface
    at angle acos(cos_o) outside it (clamped to [1e-6, 1]; the same at either crossing direction)."""
    c = cos_o.clamp(1e-6, 1.0)
    sin2_t = (1.0 - c * c) / (ior * ior)
    cos_t = torch.sqrt((1.0 - sin2_t).clamp_min(1e-12))
    r_s = ((c - ior * cos_t) / (c + ior * cos_t)) ** 2
    r_p = ((ior * c - cos_t) / (ior * c + cos_t)) ** 2
    return r_s, r_p


def fresnel_transmittance(cos_o: torch.Tensor, ior: float) -> torch.Tensor:
    """Unpolarized Fresnel transmittance ``1 - (R_s + R_p) / 2`` of a dielectric of index ``ior``
    for light leaving it at emission angle acos(cos_o), divided by its value at normal emission.

    The diffuse lobe of a smooth dielectric (Mitsuba's ``pplastic``, Wolff's diffuse model) is
    scattered inside and leaves through the interface, so it is darker toward grazing emission
    than a Lambertian surface: this factor is 1 at normal emission and falls to about 0.95 at 60
    degrees and 0.80 at 75 degrees for ior 1.5.

    Args:
        cos_o: (...) cosine between the normal and the direction to the camera (clamped to [0, 1]).
        ior: refractive index > 1.

    Returns:
        (...) factor in (0, 1], differentiable in ``cos_o``.
    """
    r_s, r_p = _fresnel_reflectance(cos_o, ior)
    t0 = 1.0 - ((ior - 1.0) / (ior + 1.0)) ** 2
    return (1.0 - 0.5 * (r_s + r_p)) / t0


def diffuse_min_fraction(cos_o: torch.Tensor, ior: float) -> torch.Tensor:
    """``1 - rho_d``: the fraction of a dielectric's diffuse light that I_min keeps, at emission angle acos(cos_o).

    Diffuse light leaves a dielectric through its surface and is partly polarized there, along
    the plane of emission, with DoP ``rho_d = (T_p - T_s) / (T_p + T_s)`` (Wolff; the built-in
    renderer's and Mitsuba's ``pplastic`` diffuse polarization). I_min = (1 - rho) I_int drops that
    polarized part, so a diffuse surface looks darker in I_min toward grazing emission than a
    Lambertian one: ``1 - rho_d = 2 T_s / (T_s + T_p)`` is 1 at normal emission, 0.98 at 30
    degrees, 0.96 at 45 and 0.90 at 60 for ior 1.5. Times :func:`fresnel_transmittance` (the
    unpolarized transmittance) it is ``T_s / T_s(0)``, the whole I_min of a ``pplastic`` diffuse lobe.
    Arguments and result as :func:`fresnel_transmittance`'s.
    """
    r_s, r_p = _fresnel_reflectance(cos_o, ior)
    t_s, t_p = 1.0 - r_s, 1.0 - r_p
    return 2.0 * t_s / (t_s + t_p)


def diffuse_view_factor(
    normal_cam: torch.Tensor, ray_cam: torch.Tensor, *, fresnel_ior: float, dop_ior: float
) -> torch.Tensor | None:
    """The per-pair factor E_pho's diffuse model puts on ``K S(N) L_scale`` (None: 1, Lambertian).

    Args:
        normal_cam: (P, 3) unit vertex normals in each pair's camera frame.
        ray_cam: (P, 3) unit directions from the camera centre to the vertex (camera frame).
        fresnel_ior: > 0: times :func:`fresnel_transmittance` of this index (``pho.diffuse_fresnel_ior``).
        dop_ior: > 0: times :func:`diffuse_min_fraction` of this index (``pho.diffuse_dop_ior``; only
            meaningful when E_pho observes I_min).

    Returns:
        (P,) factor or None when both are off.
    """
    if fresnel_ior <= 0.0 and dop_ior <= 0.0:
        return None  # the default: no work in the energy's hot path
    cos_o = -(normal_cam * ray_cam).sum(-1)
    if dop_ior <= 0.0:
        return fresnel_transmittance(cos_o, fresnel_ior)
    keep = diffuse_min_fraction(cos_o, dop_ior)
    return keep if fresnel_ior <= 0.0 else keep * fresnel_transmittance(cos_o, fresnel_ior)


def photometric_term(
    observed: torch.Tensor,
    light: torch.Tensor,
    albedo: torch.Tensor,
    pairs: PairSet,
    *,
    units: float = 255.0,
    weight: torch.Tensor | None = None,
) -> torch.Tensor:
    """E_pho = sum_i sum_{c in V(i)} ||I_ic - K_i S(N_i, L_c) L_scale,c||^2 / |V(i)|.

    Args:
        observed: (P, 3) observed RGB I_ic at each pair's projection.
        light: (P, 3) S(N_i, L_basis,c) L_scale,c (see :func:`pair_light`).
        albedo: (N, 3) RGB albedo K.
        pairs: the stage's pairs.
        units: intensities and albedos are multiplied by this before squaring.
        weight: (P,) optional per-pair factor on 1/|V(i)|, data fixed for the stage (e.g. 0 for
            pairs rejected as specular); None: 1.

    Returns:
        scalar tensor.
    """
    rendered = albedo.index_select(0, pairs.vertex) * light
    r = (observed - rendered) * units
    w = pairs.weight if weight is None else pairs.weight * weight
    return ((r * r).sum(-1) * w).sum()


def polarimetric_term(
    normal_cam: torch.Tensor,
    ray_cam: torch.Tensor,
    aop: torch.Tensor,
    weight: torch.Tensor | None,
    aop_defined: torch.Tensor,
    pairs: PairSet,
    *,
    k: float = 0.5,
) -> torch.Tensor:
    """E_pol = sum_i sum_{c in V(i)} rho_ic ((e^{-k theta_ic} - e^{-k}) / (1 - e^{-k}))^2 / |V(i)|.

    Args:
        normal_cam: (P, 3) vertex normals in each pair's camera frame.
        ray_cam: (P, 3) unit directions from each pair's camera centre to its vertex (camera frame).
        aop: (P,) observed AoP phi_ic in [0, pi).
        weight: (P,) the DoP weight rho_ic, data (no gradient flows into it; the schedule fixes it
            per stage from the DoP sampled at the stage's start), or None for no weighting.
        aop_defined: (P,) bool; pairs where the sampled AoP is undefined contribute nothing.
        pairs: the stage's pairs.
        k: narrowness of the cost's concave shape (paper: 0.5).

    Returns:
        scalar tensor.
    """
    alpha, defined = azimuth(normal_cam, ray_cam)
    cost = polarimetric_cost(azimuth_distance(alpha, aop), k=k)
    w = pairs.weight * (defined & aop_defined).to(cost.dtype)
    if weight is not None:
        w = w * weight.detach()
    return (cost * w).sum()


def geometric_smoothness_term(
    normals: torch.Tensor, face_pairs: torch.Tensor, has_neighbour: torch.Tensor, *, t: float
) -> torch.Tensor:
    """E_gsm = sum_r (arccos(N'_r . N'_r,avg) / pi)^t.

    N'_r,avg is the normalized mean of the unit normals of the faces sharing an
    edge with face r. The angle is computed as atan2(|a x b|, a . b), equal to
    arccos(a . b) for unit vectors but with a finite gradient at zero angle. A face of
    zero area (collinear corners) has no unit normal, nor has a face whose neighbours'
    normals cancel: their |a x b| and a . b are both near 0, where atan2's gradient
    1 / (|a x b|^2 + (a . b)^2) is unbounded, so they count 0, and a face of zero area
    adds nothing to its neighbours' mean.

    Args:
        normals: (F, 3) unit face normals N'_r.
        face_pairs: (M, 2) int64 pairs (r, s) of edge-adjacent faces, both orders present.
        has_neighbour: (F,) bool, faces with at least one adjacent face (the others are skipped).
        t: exponent (paper: 2.2, 2.8, 3.4 over the stages).

    Returns:
        scalar tensor.
    """
    whole = ((normals * normals).sum(-1) > 0.25).detach()  # (faces of zero area: a normal near 0)
    normals = torch.where(whole[:, None], normals, 0.0)  # ... whose 1/|e1 x e2| gradient stays out
    avg = torch.zeros_like(normals).index_add(0, face_pairs[:, 0], normals.index_select(0, face_pairs[:, 1]))
    avg = normalize(avg)
    cross = torch.linalg.cross(normals, avg, dim=1)
    sin = torch.sqrt((cross * cross).sum(-1).clamp_min(1e-30))
    cos = (normals * avg).sum(-1)
    unit = (sin * sin + cos * cos).detach() > 0.25  # (1 for unit a and b)
    angle = torch.atan2(torch.where(unit, sin, 0.0), torch.where(unit, cos, 1.0))
    return ((angle / math.pi) ** t * (has_neighbour & unit).to(angle.dtype)).sum()


def photometric_smoothness_term(
    albedo: torch.Tensor, edges: torch.Tensor, weights: torch.Tensor, *, units: float = 255.0
) -> torch.Tensor:
    """E_psm = sum_i sum_{j in A(i)} w_ij ||K_i - K_j||^2 (each undirected edge counted twice).

    Args:
        albedo: (N, 3) RGB albedo.
        edges: (E, 2) int64 undirected mesh edges.
        weights: (E,) w_ij, fixed for the stage (see :func:`psm_weights`).
        units: albedos are multiplied by this before squaring.
    """
    d = (albedo.index_select(0, edges[:, 0]) - albedo.index_select(0, edges[:, 1])) * units
    return 2.0 * ((d * d).sum(-1) * weights).sum()


def psm_weights(
    colour: np.ndarray,
    observed: np.ndarray,
    edges: np.ndarray,
    *,
    sigma_chroma: float,
    sigma_log_intensity: float,
) -> np.ndarray:
    """MVIR's photometric-smoothness weights from the observed colours of adjacent vertices.

    ``w_ij = exp(-||c_i - c_j||^2 / sigma_c^2) * exp(-(log I_i - log I_j)^2 / sigma_I^2)`` where
    ``I = (R + G + B) / 3`` and ``c = (R, G, B) / (R + G + B)`` (chromaticity) of the vertex's
    observed colour averaged over its views. Edges touching a vertex without observations get 1.

    Args:
        colour: (N, 3) mean observed RGB per vertex (normalized units).
        observed: (N,) bool, vertices with at least one observation.
        edges: (E, 2) int64.

    Returns:
        (E,) float64 weights in (0, 1].
    """
    rgb = np.maximum(np.asarray(colour, dtype=np.float64), 0.0)
    s = rgb.sum(1) + 1e-6
    chroma = rgb / s[:, None]
    log_i = np.log(s / 3.0)
    i, j = edges[:, 0], edges[:, 1]
    dc = ((chroma[i] - chroma[j]) ** 2).sum(1)
    di = (log_i[i] - log_i[j]) ** 2
    w = np.exp(-dc / sigma_chroma**2) * np.exp(-di / sigma_log_intensity**2)
    return np.where(observed[i] & observed[j], w, 1.0)


def lighting_coupling_term(sh: torch.Tensor, rgb_scale: torch.Tensor, *, scale: float) -> torch.Tensor:
    """E_light = scale * sum_c ||L_c - L_mean||^2 over the views' order-2 lighting.

    ``L_c = L_scale,c (x) L_basis,c[:9]`` (3 x 9, the pmvir-sh9 shading of view c per channel);
    ``L_mean`` is their mean over the views. A view's lighting is determined by the data only for
    the normals that view sees (those facing it); the others are left free by E_pho and take
    whatever value the fit gives them. Views of one capture are lit alike, so pulling each toward
    the mean lets the other views' data determine them. The higher SH terms (order 3-4, which
    hold the view-dependent glossy residue) stay free. The term is quadratic: a deviation relative
    to the current mean would let the fit shrink it by inflating a part the views share. (Coupling
    only the shape ``L_basis,c[1:9]`` and leaving ``L_scale`` free measured worse: README.)

    Args:
        sh: (V, T) L_basis per view (T = 9, 16 or 25, pmvir-sh9 first).
        rgb_scale: (V, 3) L_scale per view.
        scale: a constant (:attr:`StageProblem.light_scale`; the final lighting fit divides E_pho's
            value with nothing rendered by ``||L_mean||^2`` at its start, so that a deviation of
            d times the mean lighting costs about what an E_pho residual of d on every
            observation would).

    Returns:
        scalar tensor (0 with one view).
    """
    lights = rgb_scale[:, :, None] * sh[:, None, :9]
    return scale * ((lights - lights.mean(dim=0)) ** 2).sum()


@dataclass(frozen=True)
class StageProblem:
    """Everything an energy evaluation needs besides the unknowns (constant within a stage).

    Attributes:
        faces: (F, 3) int64 tensor.
        face_pairs: (M, 2) int64 edge-adjacent face pairs (both orders).
        has_neighbour: (F,) bool.
        edges: (E, 2) int64 undirected edges.
        psm_weight: (E,) w_ij.
        views: packed cameras and images.
        pairs: the stage's (vertex, view) pairs.
        polarimetric: whether E_pol is evaluated.
        pol_mask: (P,) bool pairs used by E_pol (None: all), e.g. DoP above the noise floor at the stage start.
        pol_weight: (P,) E_pol's per-pair DoP weight, fixed for the stage (None: unweighted).
        pho_weight: (P,) E_pho's per-pair factor, fixed for the stage (None: 1).
        diffuse_fresnel_ior: > 0: the rendered colour of each pair is multiplied by the Fresnel
            transmittance toward its camera (:func:`fresnel_transmittance`); 0: Lambertian.
        diffuse_dop_ior: > 0: the rendered colour of each pair is multiplied by the fraction of
            diffuse light I_min keeps (:func:`diffuse_min_fraction`); 0: off (RefineOptions rejects
            it with E_pho on I_int).
        light_factor: (P,) each pair's rendered colour is multiplied by it, fixed for the stage
            (the unblocked share of its irradiance, :mod:`pmvir.refine.shadowing`); None: 1.
        light_scale: > 0: E_light is evaluated with this scale (:func:`lighting_coupling_term`);
            0: it is not (``lighting.coupling`` 0).
        k, t, units: term parameters.
    """

    faces: torch.Tensor
    face_pairs: torch.Tensor
    has_neighbour: torch.Tensor
    edges: torch.Tensor
    psm_weight: torch.Tensor
    views: ViewStack
    pairs: PairSet
    polarimetric: bool
    pol_mask: torch.Tensor | None
    pol_weight: torch.Tensor | None
    k: float
    t: float
    units: float
    pho_weight: torch.Tensor | None = None
    diffuse_fresnel_ior: float = 0.0
    diffuse_dop_ior: float = 0.0
    light_factor: torch.Tensor | None = None
    light_scale: float = 0.0


def energy_terms(
    vertices: torch.Tensor,
    albedo: torch.Tensor | Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    sh: torch.Tensor,
    rgb_scale: torch.Tensor,
    problem: StageProblem,
) -> dict[str, torch.Tensor]:
    """The named, unweighted terms ``{"pho", "pol", "gsm", "psm", "light"}`` (``"pol"`` only when
    polarimetric, ``"light"`` only with ``problem.light_scale`` > 0).

    Args:
        vertices: (N, 3) positions X.
        albedo: (N, 3) albedo K, or a function (observed (P, 3), light (P, 3), both detached)
            -> K that chooses it (e.g. :class:`pmvir.refine.albedo.AlbedoSolver`).
        sh: (V, 9) L_basis; rgb_scale: (V, 3) L_scale.
        problem: the stage's constants.
    """
    normals = vertex_normals(vertices, problem.faces)
    samples: PairSamples = sample_pairs(vertices, normals, problem.views, problem.pairs)
    light = pair_light(normals, sh, rgb_scale, problem.pairs)
    factor = diffuse_view_factor(
        samples.normal_cam,
        samples.ray_cam,
        fresnel_ior=problem.diffuse_fresnel_ior,
        dop_ior=problem.diffuse_dop_ior,
    )
    if factor is not None:
        light = light * factor[:, None]
    if problem.light_factor is not None:
        light = light * problem.light_factor[:, None]
    if callable(albedo):
        albedo = albedo(samples.intensity.detach(), light.detach())
    terms = {
        "pho": photometric_term(
            samples.intensity, light, albedo, problem.pairs, units=problem.units, weight=problem.pho_weight
        )
    }
    if problem.polarimetric:
        if samples.aop is None or samples.aop_defined is None:
            raise ConfigError("E_pol needs a view stack built with polarization (polarimetric=True)")
        terms["pol"] = polarimetric_term(
            samples.normal_cam,
            samples.ray_cam,
            samples.aop,
            problem.pol_weight,
            samples.aop_defined if problem.pol_mask is None else samples.aop_defined & problem.pol_mask,
            problem.pairs,
            k=problem.k,
        )
    terms["gsm"] = geometric_smoothness_term(
        face_normals(vertices, problem.faces), problem.face_pairs, problem.has_neighbour, t=problem.t
    )
    terms["psm"] = photometric_smoothness_term(albedo, problem.edges, problem.psm_weight, units=problem.units)
    if problem.light_scale > 0.0:
        terms["light"] = lighting_coupling_term(sh, rgb_scale, scale=problem.light_scale)
    return terms


def total_energy(
    terms: dict[str, torch.Tensor],
    *,
    tau_pol: float,
    tau_gsm: float,
    tau_psm: float,
    tau_light: float = 0.0,
) -> torch.Tensor:
    """E_pho + tau1 E_pol + tau2 E_gsm + tau3 E_psm + tau_light E_light (a missing ``"pol"`` or
    ``"light"`` counts as 0)."""
    e = terms["pho"] + tau_gsm * terms["gsm"] + tau_psm * terms["psm"]
    if "pol" in terms:
        e = e + tau_pol * terms["pol"]
    if "light" in terms:
        e = e + tau_light * terms["light"]
    return e
