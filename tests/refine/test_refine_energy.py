"""The cost's terms: gradients against finite differences, E_pol's shape (paper figure), conventions."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from pmvir.camera import Camera, look_at
from pmvir.errors import ConfigError, ShapeError
from pmvir.refine.energy import (
    ETA_OFFSETS,
    StageProblem,
    azimuth,
    azimuth_distance,
    diffuse_min_fraction,
    diffuse_view_factor,
    energy_terms,
    fresnel_transmittance,
    geometric_smoothness_term,
    lighting_coupling_term,
    pair_light,
    photometric_smoothness_term,
    photometric_term,
    polarimetric_cost,
    polarimetric_term,
    psm_weights,
    total_energy,
)
from pmvir.refine.forward import render_decoded
from pmvir.refine.mesh_ops import face_adjacency, face_normals, unique_edges, vertex_normals
from pmvir.refine.sampling import (
    Observation,
    PairSet,
    build_view_stack,
    observation_from_decoded,
    sample_pairs,
    select_pairs,
)
from pmvir.sh import sh_basis
from pmvir.synth.shapes import geodesic_sphere

F64 = torch.float64


def _pairs(n: int) -> PairSet:
    """n pairs of n distinct vertices in one view, weight 1."""
    idx = torch.arange(n)
    return PairSet(
        idx,
        torch.zeros(n, dtype=torch.int64),
        [0, n],
        torch.ones(n, dtype=F64),
        np.ones(n, dtype=np.int64),
        idx,
    )


# --- E_pol: the paper's figure and the azimuth convention -----------------------------------------


def test_polarimetric_cost_reproduces_paper_figure() -> None:
    """phi = 120 deg, k = 0.5: zero at alpha = 30, 120, 210, 300 deg, maximum (1) halfway between."""
    alpha = torch.deg2rad(torch.arange(0.0, 360.0, 0.25, dtype=F64))
    phi = torch.full_like(alpha, math.radians(120.0))
    cost = polarimetric_cost(azimuth_distance(alpha, phi), k=0.5)
    deg = np.degrees(alpha.numpy())
    c = cost.numpy()
    assert c.min() >= 0.0 and c.max() <= 1.0 + 1e-12
    zeros = deg[c < 1e-12]
    np.testing.assert_allclose(np.sort(zeros), [30.0, 120.0, 210.0, 300.0])
    for peak in (75.0, 165.0, 255.0, 345.0):
        assert c[np.argmin(np.abs(deg - peak))] == pytest.approx(1.0)
    # local maxima of the sampled curve sit exactly halfway between the zeros
    interior = (c[1:-1] > c[:-2]) & (c[1:-1] >= c[2:])
    np.testing.assert_allclose(deg[1:-1][interior], [75.0, 165.0, 255.0, 345.0])


def test_polarimetric_cost_against_values_known_without_the_formula() -> None:
    """Independent facts about the cost f(eta)^2, not a re-implementation of it.

    * k = ln 4 at eta = pi/8 (theta = 1/2): e^{-k theta} = 1/2 and e^{-k} = 1/4, so
      f = (1/2 - 1/4) / (3/4) = 1/3 and the cost is exactly 1/9.
    * As k -> 0 the cost tends to the quadratic (4 eta / pi)^2 (f -> 1 - theta).
    * f is convex in eta for k > 0 (an exponential of a linear function), so it lies
      *below* its chord 4 eta / pi: a larger k gives a flatter valley floor around
      each candidate azimuth (more tolerant of small AoP noise) and a steeper climb near
      the midpoint, with the cost strictly decreasing in k at any interior eta.
    """
    eighth = torch.tensor(math.pi / 8, dtype=F64)
    assert float(polarimetric_cost(eighth, k=math.log(4.0))) == pytest.approx(1.0 / 9.0, rel=1e-12)
    eta = torch.linspace(0.0, math.pi / 4, 41, dtype=F64)
    np.testing.assert_allclose(
        polarimetric_cost(eta, k=1e-7).numpy(), ((4 * eta / math.pi) ** 2).numpy(), atol=1e-6
    )
    costs = [polarimetric_cost(eta[1:-1], k=k).numpy() for k in (1e-7, 0.5, 2.0)]
    assert np.all(costs[1] < costs[0]) and np.all(costs[2] < costs[1])


def test_polarimetric_term_matches_figure_through_camera_normals() -> None:
    """The same curve through polarimetric_term: camera-frame normals with azimuth alpha, DoP 1."""
    alpha = torch.deg2rad(torch.tensor([30.0, 75.0, 120.0, 165.0, 210.0, 255.0, 300.0, 345.0], dtype=F64))
    normal_cam = torch.stack([torch.cos(alpha), -torch.sin(alpha), -torch.ones_like(alpha)], dim=1)
    ray = torch.tensor([[0.0, 0.0, 1.0]], dtype=F64).expand(len(alpha), 3)  # on the optical axis
    phi = torch.full_like(alpha, math.radians(120.0))
    n = len(alpha)
    per_pair = [
        float(
            polarimetric_term(
                normal_cam[i : i + 1],
                ray[:1],
                phi[:1],
                torch.ones(1, dtype=F64),
                torch.ones(1, dtype=torch.bool),
                _pairs(1),
                k=0.5,
            )
        )
        for i in range(n)
    ]
    np.testing.assert_allclose(per_pair, [0, 1, 0, 1, 0, 1, 0, 1], atol=1e-12)
    # DoP weighting scales it; switching it off ignores the DoP
    dop = torch.full((n,), 0.25, dtype=F64)
    defined = torch.ones(n, dtype=torch.bool)
    assert float(polarimetric_term(normal_cam, ray, phi, dop, defined, _pairs(n))) == pytest.approx(4 * 0.25)
    assert float(polarimetric_term(normal_cam, ray, phi, None, defined, _pairs(n))) == pytest.approx(4)


def test_eta_is_at_most_quarter_pi_over_the_whole_range() -> None:
    """alpha in [0, 2 pi) (as azimuth() returns) and phi in [0, pi]: the seven offsets cover every case,
    and the closed form azimuth_distance computes equals the paper's minimum over the seven terms."""
    a, p = np.meshgrid(np.linspace(0, 2 * np.pi, 721)[:-1], np.linspace(0, np.pi, 361), indexing="ij")
    a = a + 1e-3 * np.sin(7 * p)  # off the grid of exact ties between two candidates
    eta = azimuth_distance(torch.from_numpy(a), torch.from_numpy(p)).numpy()
    assert eta.max() <= np.pi / 4 + 1e-12
    literal = np.min([np.abs(a - p + o) for o in ETA_OFFSETS], axis=0)
    np.testing.assert_allclose(eta, literal, atol=1e-12)
    theta = 1 - 4 * eta / np.pi
    assert theta.min() >= -1e-12 and theta.max() <= 1 + 1e-12


def test_eta_offsets_need_alpha_wrapped_to_0_2pi() -> None:
    """With alpha = atan2 in (-pi, pi] unwrapped the literal seven terms would exceed pi/4: azimuth() wraps."""
    alpha_raw, phi = -0.9 * math.pi, 0.9 * math.pi
    literal = min(abs(alpha_raw - phi + o) for o in ETA_OFFSETS)
    assert literal > math.pi / 4
    normal_cam = torch.tensor([[math.cos(alpha_raw), -math.sin(alpha_raw), -1.0]], dtype=F64)
    alpha, defined = azimuth(normal_cam, torch.tensor([[0.0, 0.0, 1.0]], dtype=F64))
    assert bool(defined[0]) and 0.0 <= float(alpha[0]) < 2 * math.pi
    assert float(alpha[0]) == pytest.approx(alpha_raw + 2 * math.pi)
    assert float(azimuth_distance(alpha, torch.tensor([phi], dtype=F64))[0]) <= math.pi / 4


def test_azimuth_is_counter_clockwise_on_screen() -> None:
    """Spec section 2, on the optical axis: alpha = atan2(-ny, nx): image right is 0, image up (-y) is pi/2."""
    n = torch.tensor([[1.0, 0, -1], [0, -1.0, -1], [-1.0, 0, -1], [0, 1.0, -1], [0, 0, -1.0]], dtype=F64)
    alpha, defined = azimuth(n, torch.tensor([0.0, 0.0, 1.0], dtype=F64))
    np.testing.assert_allclose(alpha[:4].numpy(), [0, np.pi / 2, np.pi, 1.5 * np.pi], atol=1e-12)
    assert defined.tolist() == [True, True, True, True, False]


def test_rendered_aop_follows_the_spec_sense() -> None:
    """A sphere seen head-on: the right limb has AoP ~0, the top limb (image up) AoP ~pi/2 (diffuse)."""
    v, f = geodesic_sphere(12)
    R, t = look_at(np.array([0.0, -4.0, 0.0]), np.zeros(3))
    cam = Camera.from_intrinsics(120.0, 120.0, 32.0, 32.0, 64, 64, R, t)
    fr = render_decoded(v, f, np.full((len(v), 3), 0.5), [cam], np.eye(9)[0], np.ones(3))[0]
    row = 32
    cols = np.flatnonzero(fr["mask"][row])
    right = fr["aop"][row, cols.max() - 1]
    assert min(right, np.pi - right) < np.radians(8)
    rows = np.flatnonzero(fr["mask"][:, 32])
    top = fr["aop"][rows.min() + 1, 32]
    assert abs(top - np.pi / 2) < np.radians(8)
    assert fr["dop"][row, cols.max() - 1] > fr["dop"][row, 32]  # more polarized at grazing angles


# --- sampling ----------------------------------------------------------------------------------------


def _flat_view(h: int = 20, w: int = 24) -> tuple[Camera, np.ndarray]:
    cam = Camera.from_intrinsics(50.0, 50.0, w / 2, h / 2, w, h, np.eye(3), np.zeros(3))
    rows, cols = np.mgrid[0:h, 0:w].astype(np.float64)
    return cam, 0.01 * cols + 0.02 * rows + 0.1


def test_bilinear_sampling_is_exact_on_a_linear_image() -> None:
    cam, ramp = _flat_view()
    intensity = np.stack([ramp, 2 * ramp, 0.5 * ramp], axis=-1).astype(np.float32)
    obs = Observation(intensity, np.zeros(ramp.shape), ramp, np.ones(ramp.shape, bool))
    views = build_view_stack([cam], [obs], polarimetric=True, device="cpu", dtype=F64)
    rng = np.random.default_rng(0)
    uv = rng.uniform([1.0, 1.0], [cam.width - 1.0, cam.height - 1.0], (50, 2))
    pts = np.concatenate([(uv - cam.K[:2, 2]) / 50.0 * 2.0, np.full((50, 1), 2.0)], axis=1)  # depth 2
    pairs = select_pairs(pts, np.ones((50, 1), bool), [cam], [obs], device="cpu", dtype=F64)
    assert pairs.size == 50
    x = torch.from_numpy(pts)
    smp = sample_pairs(x, torch.zeros_like(x), views, pairs)
    expect = (0.01 * (uv[:, 0] - 0.5) + 0.02 * (uv[:, 1] - 0.5) + 0.1)[pairs.vertex.numpy()]
    np.testing.assert_allclose(smp.intensity[:, 0].numpy(), expect, atol=1e-6)
    np.testing.assert_allclose(smp.intensity[:, 1].numpy(), 2 * expect, atol=1e-6)
    np.testing.assert_allclose(smp.dop.numpy(), expect, atol=1e-6)


def test_sampling_gradients_match_finite_differences_whichever_samples_are_used() -> None:
    """The lookup's grouped outputs (RGB, cos 2 phi, sin 2 phi, DoP) differentiate like one sample, also
    when only some of them reach the cost; the projection takes the intrinsics of the view stack given."""
    cam, ramp = _flat_view()
    rows, cols = np.mgrid[0 : cam.height, 0 : cam.width].astype(np.float64)
    curved = 0.3 + 0.002 * (cols - 9.0) ** 2 + 0.03 * np.sin(0.4 * rows)
    intensity = np.stack([ramp, curved, 0.5 * ramp * curved], axis=-1).astype(np.float32)
    obs = Observation(intensity, np.clip(curved + 0.5 * ramp, 0, 3.0), curved, np.ones(ramp.shape, bool))
    views = build_view_stack([cam], [obs], polarimetric=True, device="cpu", dtype=F64)
    rng = np.random.default_rng(1)
    uv = rng.uniform([2.0, 2.0], [cam.width - 2.0, cam.height - 2.0], (12, 2))
    pts = np.concatenate([(uv - cam.K[:2, 2]) / 50.0 * 2.0, np.full((12, 1), 2.0)], axis=1)
    pairs = select_pairs(pts, np.ones((12, 1), bool), [cam], [obs], device="cpu", dtype=F64)
    normals = torch.zeros(12, 3, dtype=F64)
    costs = {
        "rgb": lambda s: (s.intensity**2).sum(),
        "aop": lambda s: (s.aop**2).sum(),
        "all": lambda s: (s.intensity**2).sum() + (s.aop**2).sum() + s.dop.sum(),
    }
    for name, cost in costs.items():
        x = torch.from_numpy(pts).requires_grad_(True)
        assert torch.autograd.gradcheck(
            lambda x, cost=cost: cost(sample_pairs(x, normals, views, pairs)), (x,), eps=1e-6, atol=1e-5
        ), name
    wide = Camera.from_intrinsics(40.0, 40.0, cam.width / 2, cam.height / 2, cam.width, cam.height,
                                  np.eye(3), np.zeros(3))
    other = build_view_stack([wide], [obs], polarimetric=True, device="cpu", dtype=F64)
    x = torch.from_numpy(pts)
    u = (40.0 * pts[:, 0] / pts[:, 2] + cam.width / 2)[pairs.vertex.numpy()]
    v = (40.0 * pts[:, 1] / pts[:, 2] + cam.height / 2)[pairs.vertex.numpy()]
    expect = 0.01 * (u - 0.5) + 0.02 * (v - 0.5) + 0.1
    np.testing.assert_allclose(sample_pairs(x, normals, other, pairs).intensity[:, 0].numpy(), expect, atol=1e-6)


def test_aop_is_interpolated_as_an_axial_angle() -> None:
    """Across the 0/pi wrap the sampled AoP stays near 0 (mod pi), never near pi/2."""
    cam, ramp = _flat_view()
    aop = np.where(np.arange(cam.width)[None, :] < 12, 0.05, np.pi - 0.05) * np.ones(ramp.shape)
    obs = Observation(np.ones(ramp.shape + (3,)), aop, np.full(ramp.shape, 0.3), np.ones(ramp.shape, bool))
    views = build_view_stack([cam], [obs], polarimetric=True, device="cpu", dtype=F64)
    u = np.linspace(11.0, 13.0, 9)  # pixel centres 11.5 (col 11) and 12.5 (col 12)
    pts = np.stack([(u - cam.K[0, 2]) / 50.0, np.zeros_like(u), np.ones_like(u)], axis=1)
    pairs = select_pairs(pts, np.ones((len(u), 1), bool), [cam], [obs], device="cpu", dtype=F64)
    x = torch.from_numpy(pts)
    phi = sample_pairs(x, torch.zeros_like(x), views, pairs).aop.numpy()
    dist = np.minimum(phi, np.pi - phi)
    assert dist.max() <= 0.05 + 1e-6  # the view table is float32
    assert np.all((phi >= 0) & (phi < np.pi + 1e-12))


def test_pairs_need_valid_footprints() -> None:
    cam, ramp = _flat_view()
    valid = np.ones(ramp.shape, bool)
    valid[:, 12] = False
    obs = Observation(np.ones(ramp.shape + (3,)), np.zeros(ramp.shape), ramp, valid)
    u = np.array([5.0, 12.4, 13.0, 20.0])  # the middle two touch column 12
    pts = np.stack([(u - cam.K[0, 2]) / 50.0, np.zeros_like(u), np.ones_like(u)], axis=1)
    pairs = select_pairs(pts, np.ones((4, 1), bool), [cam], [obs], device="cpu", dtype=F64)
    assert pairs.vertex.tolist() == [0, 3]
    np.testing.assert_array_equal(pairs.count, [1, 0, 0, 1])


def test_grazing_pairs_are_left_out_below_the_minimum_viewing_cosine() -> None:
    """A vertex whose normal turns 50 / 70 degrees away from the camera is kept / dropped at min_cos 0.5."""
    cam, ramp = _flat_view()
    obs = Observation(np.ones(ramp.shape + (3,)), np.zeros(ramp.shape), ramp, np.ones(ramp.shape, bool))
    pts = np.array([[0.0, 0.0, 1.0], [0.01, 0.0, 1.0], [-0.01, 0.0, 1.0]])
    to_cam = -pts / np.linalg.norm(pts, axis=1, keepdims=True)
    tilt = np.radians([0.0, 50.0, 70.0])
    # turn each normal about the y axis away from the direction to the camera
    normals = np.stack(
        [np.cos(t) * d + np.sin(t) * np.cross([0.0, 1.0, 0.0], d) for t, d in zip(tilt, to_cam, strict=True)]
    )
    vis = np.ones((3, 1), bool)
    kept = select_pairs(pts, vis, [cam], [obs], device="cpu", dtype=F64, normals=normals, min_cos=0.5)
    assert sorted(kept.vertex.tolist()) == [0, 1]
    everything = select_pairs(pts, vis, [cam], [obs], device="cpu", dtype=F64)
    assert sorted(everything.vertex.tolist()) == [0, 1, 2]
    with pytest.raises(ConfigError, match="normals"):
        select_pairs(pts, vis, [cam], [obs], device="cpu", dtype=F64, min_cos=0.5)


# --- smoothness terms -------------------------------------------------------------------------------


def test_gsm_is_zero_on_a_plane_and_grows_with_bending() -> None:
    xs, ys = np.meshgrid(np.arange(5.0), np.arange(5.0))
    v = np.stack([xs.ravel(), ys.ravel(), np.zeros(25)], axis=1)
    quads = [
        (r * 5 + c, r * 5 + c + 1, (r + 1) * 5 + c, (r + 1) * 5 + c + 1) for r in range(4) for c in range(4)
    ]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, d), (a, d, c))])
    fp = torch.from_numpy(face_adjacency(f))
    has = torch.ones(len(f), dtype=torch.bool)
    ft = torch.from_numpy(f)
    flat = geometric_smoothness_term(face_normals(torch.from_numpy(v), ft), fp, has, t=2.2)
    assert float(flat) == pytest.approx(0.0, abs=1e-12)
    energies = []
    for h in (0.1, 0.3):
        bent = v.copy()
        bent[12, 2] = h
        energies.append(
            float(geometric_smoothness_term(face_normals(torch.from_numpy(bent), ft), fp, has, t=2.2))
        )
    assert 0 < energies[0] < energies[1]


def test_gsm_gradient_stays_bounded_at_a_face_of_zero_area() -> None:
    """A face with collinear corners (a sliver the initial surface can hold) has no unit normal: it
    counts 0 in E_gsm, and the gradient stays of the order of a smooth mesh's (its atan2 at (0, 0)
    gave gradients above 1e17 that stalled the first L-BFGS step), equal to the gradient without it."""
    xs, ys = np.meshgrid(np.arange(5.0), np.arange(5.0))
    rng = np.random.default_rng(3)
    v = np.stack([xs.ravel(), ys.ravel(), 0.2 * rng.standard_normal(25)], axis=1)
    quads = [
        (r * 5 + c, r * 5 + c + 1, (r + 1) * 5 + c, (r + 1) * 5 + c + 1) for r in range(4) for c in range(4)
    ]
    f = np.array([t for a, b, c, d in quads for t in ((a, b, d), (a, d, c))])
    v[7] = 0.5 * (v[6] + v[12])  # face 10, (6, 7, 12), loses its area
    assert tuple(f[10]) == (6, 7, 12)
    ft = torch.from_numpy(f)
    fp = torch.from_numpy(face_adjacency(f))
    has = torch.ones(len(f), dtype=torch.bool)
    x = torch.from_numpy(v).requires_grad_(True)
    normals = face_normals(x, ft)
    assert float(normals[10].norm()) < 0.5  # the zero-area face: no unit normal
    energy = geometric_smoothness_term(normals, fp, has, t=2.2)
    (grad,) = torch.autograd.grad(energy, x)
    assert torch.isfinite(grad).all() and float(grad.abs().max()) < 100.0
    without = has.clone()
    without[10] = False
    x2 = torch.from_numpy(v).requires_grad_(True)
    (grad2,) = torch.autograd.grad(geometric_smoothness_term(face_normals(x2, ft), fp, without, t=2.2), x2)
    assert torch.allclose(grad, grad2)


def test_gsm_gradient_stays_finite_where_neighbour_normals_cancel() -> None:
    """A face folded between two neighbours whose normals are opposite (a fin of the initial surface)
    has a neighbour mean of 0: it counts 0 in E_gsm and the gradient stays finite, where atan2 at
    (0, 0) gave infinite gradients; the unfolded neighbour still counts."""
    v = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [1.0, 1.0, 0.0], [0.3, 0.3, 0.0]])
    f = np.array([[0, 1, 2], [1, 3, 2], [1, 0, 4]])  # face 0's neighbours: +z (face 1) and -z (face 2)
    ft = torch.from_numpy(f)
    fp = torch.from_numpy(face_adjacency(f))
    has = torch.ones(len(f), dtype=torch.bool)
    x = torch.from_numpy(v).requires_grad_(True)
    normals = face_normals(x, ft)
    assert float(normals[1, 2]) == pytest.approx(1.0) and float(normals[2, 2]) == pytest.approx(-1.0)
    energy = geometric_smoothness_term(normals, fp, has, t=2.2)
    (grad,) = torch.autograd.grad(energy, x)
    assert torch.isfinite(grad).all()
    assert float(energy) == pytest.approx(1.0)  # face 2 sees face 0 at 180 degrees, face 1 at 0; face 0: 0


def test_psm_weights_follow_chromaticity_and_intensity() -> None:
    colour = np.array([[0.5, 0.4, 0.3], [0.5, 0.4, 0.3], [0.25, 0.2, 0.15], [0.3, 0.4, 0.5], [0.0, 0.0, 0.0]])
    observed = np.array([True, True, True, True, False])
    edges = np.array([[0, 1], [0, 2], [0, 3], [0, 4]])
    w = psm_weights(colour, observed, edges, sigma_chroma=0.05, sigma_log_intensity=0.3)
    assert w[0] == pytest.approx(1.0)
    assert w[1] == pytest.approx(np.exp(-(np.log(2.0) ** 2) / 0.09), rel=1e-4)  # same chroma, half intensity
    assert w[2] < 1e-6  # different chromaticity
    assert w[3] == 1.0  # unobserved neighbour: plain smoothness


def test_psm_counts_each_edge_twice() -> None:
    k = torch.tensor([[0.1, 0.2, 0.3], [0.2, 0.2, 0.5]], dtype=F64)
    e = photometric_smoothness_term(k, torch.tensor([[0, 1]]), torch.tensor([0.5], dtype=F64), units=1.0)
    assert float(e) == pytest.approx(2 * 0.5 * (0.01 + 0.0 + 0.04))


# --- finite-difference gradient checks --------------------------------------------------------------


@pytest.fixture(scope="module")
def small_problem():
    return make_small_problem()


def make_small_problem():
    """42-vertex bumpy sphere, 3 views of 24 x 24, float64, perturbed vertices."""
    rng = np.random.default_rng(3)
    tv, tf = geodesic_sphere(3)
    tv = tv * (1 + 0.05 * np.sin(3 * tv[:, :1]))
    cams = []
    for az in (0.3, 2.4, 4.4):
        R, t = look_at(3.0 * np.array([np.cos(az), np.sin(az), 0.4]), np.zeros(3))
        cams.append(Camera.from_intrinsics(30.0, 30.0, 12.0, 12.0, 24, 24, R, t))
    sh = np.array([0.8, 0.1, 0.3, 0.1, 0.05, 0.05, 0.1, 0.02, 0.03])
    frames = render_decoded(
        tv, tf, np.full((len(tv), 3), 0.5), cams, sh, np.ones(3), stokes_noise=0.01, seed=1
    )
    obs = [observation_from_decoded(fr) for fr in frames]
    v0 = tv + rng.normal(0, 0.01, tv.shape)
    from pmvir.geometry.visibility import vertex_visibility

    vis = vertex_visibility(v0, tf, cams)
    views = build_view_stack(cams, obs, polarimetric=True, device="cpu", dtype=F64)
    pairs = select_pairs(v0, vis, cams, obs, device="cpu", dtype=F64)
    assert pairs.size > 30
    edges = unique_edges(tf)
    fp = face_adjacency(tf)
    x0 = torch.from_numpy(v0)
    dop0 = sample_pairs(x0, vertex_normals(x0, torch.from_numpy(tf)), views, pairs).dop  # data, fixed
    problem = StageProblem(
        faces=torch.from_numpy(tf),
        face_pairs=torch.from_numpy(fp),
        has_neighbour=torch.from_numpy(np.bincount(fp[:, 0], minlength=len(tf)) > 0),
        edges=torch.from_numpy(edges),
        psm_weight=torch.from_numpy(rng.uniform(0.2, 1.0, len(edges))),
        views=views,
        pairs=pairs,
        polarimetric=True,
        pol_mask=None,
        pol_weight=dop0,
        k=0.5,
        t=2.2,
        units=255.0,
    )
    n_views = len(cams)
    inputs = (
        torch.from_numpy(v0).requires_grad_(),
        torch.from_numpy(rng.uniform(0.3, 0.7, (len(tv), 3))).requires_grad_(),
        torch.from_numpy(np.tile(sh, (n_views, 1)) + rng.normal(0, 0.05, (n_views, 9))).requires_grad_(),
        torch.from_numpy(rng.uniform(0.8, 1.2, (n_views, 3))).requires_grad_(),
    )
    return problem, inputs


def _pho(problem, x, k, sh, sc):
    n = vertex_normals(x, problem.faces)
    smp = sample_pairs(x, n, problem.views, problem.pairs)
    return photometric_term(smp.intensity, pair_light(n, sh, sc, problem.pairs), k, problem.pairs)


def _pol(problem, x):
    n = vertex_normals(x, problem.faces)
    smp = sample_pairs(x, n, problem.views, problem.pairs)
    return polarimetric_term(
        smp.normal_cam, smp.ray_cam, smp.aop, problem.pol_weight, smp.aop_defined, problem.pairs, k=0.5
    )


def _gsm(problem, x):
    return geometric_smoothness_term(
        face_normals(x, problem.faces), problem.face_pairs, problem.has_neighbour, t=2.8
    )


def _psm(problem, k):
    return photometric_smoothness_term(k, problem.edges, problem.psm_weight)


def _total(problem, x, k, sh, sc):
    terms = energy_terms(x, k, sh, sc, problem)
    return total_energy(terms, tau_pol=60.0, tau_gsm=0.1, tau_psm=2.0)


def _light(problem, sh, sc):
    return lighting_coupling_term(sh, sc, scale=1000.0)


def _total_light(problem, x, k, sh, sc):
    terms = energy_terms(x, k, sh, sc, replace(problem, light_scale=1000.0))
    assert "light" in terms
    return total_energy(terms, tau_pol=60.0, tau_gsm=0.1, tau_psm=2.0, tau_light=0.5)


@pytest.mark.parametrize(
    "name, fn, which",
    [
        ("pho", _pho, (0, 1, 2, 3)),
        ("pol", _pol, (0,)),
        ("gsm", _gsm, (0,)),
        ("psm", _psm, (1,)),
        ("total", _total, (0, 1, 2, 3)),
        ("light", _light, (2, 3)),
        ("total with E_light", _total_light, (0, 1, 2, 3)),
    ],
)
def test_gradients_match_finite_differences(small_problem, name, fn, which) -> None:
    """torch.autograd.gradcheck (central differences, float64) of each term and of the total.

    The function is divided by its value at the start so that the tolerances are relative.
    """
    problem, inputs = small_problem
    args = tuple(inputs[i] for i in which)
    value = float(fn(problem, *args).detach())
    assert value > 0.0, f"E_{name} should be positive on the perturbed mesh"
    assert torch.autograd.gradcheck(lambda *a: fn(problem, *a) / value, args, eps=1e-6, atol=1e-7, rtol=1e-4)


def test_lighting_coupling_is_zero_for_shared_lighting_quadratic_and_blind_to_the_higher_terms() -> None:
    rng = np.random.default_rng(0)
    sh = torch.from_numpy(np.tile(rng.normal(0.0, 0.3, 25), (4, 1)))
    sh[:, 0] = 1.0
    scale = torch.from_numpy(np.tile([1.0, 0.9, 0.7], (4, 1)))
    assert float(lighting_coupling_term(sh, scale, scale=10.0)) == pytest.approx(0.0, abs=1e-12)
    varied = sh.clone()
    varied[:, 9:] = torch.from_numpy(rng.normal(0.0, 0.3, (4, 16)))  # order 3-4: view-dependent, free
    assert float(lighting_coupling_term(varied, scale, scale=10.0)) == pytest.approx(0.0, abs=1e-12)
    varied[1, 2] += 0.2  # one view's light from elsewhere
    e = float(lighting_coupling_term(varied, scale, scale=10.0))
    # over 4 views, the squared deviations from the mean sum to 0.2^2 * 3/4 per unit channel scale
    assert e == pytest.approx(10.0 * 0.04 * 0.75 * (1.0 + 0.81 + 0.49), rel=1e-12)
    assert float(lighting_coupling_term(varied, 3.0 * scale, scale=10.0)) == pytest.approx(9.0 * e, rel=1e-12)
    assert float(lighting_coupling_term(varied, scale, scale=20.0)) == pytest.approx(2.0 * e, rel=1e-12)
    brighter = scale.clone()
    brighter[2] *= 1.5  # one view lit more strongly
    assert float(lighting_coupling_term(sh, brighter, scale=10.0)) > 0.0


def test_dop_weighting_is_switchable(small_problem) -> None:
    problem, inputs = small_problem
    x = inputs[0].detach()
    n = vertex_normals(x, problem.faces)
    smp = sample_pairs(x, n, problem.views, problem.pairs)
    weighted = float(
        polarimetric_term(smp.normal_cam, smp.ray_cam, smp.aop, smp.dop, smp.aop_defined, problem.pairs)
    )
    unweighted = float(
        polarimetric_term(smp.normal_cam, smp.ray_cam, smp.aop, None, smp.aop_defined, problem.pairs)
    )
    assert 0 < weighted < unweighted  # DoP < 1 everywhere


# --- E_pho options for non-Lambertian reflectance --------------------------------------------------


def test_fresnel_transmittance_against_brewster_and_the_synth_fresnel_code() -> None:
    """1 at normal emission; at Brewster's angle R_p = 0 and R_s = ((n^2 - 1) / (n^2 + 1))^2 (closed
    form); elsewhere equal to 1 - (R_s + R_p) / 2 from pmvir.synth.materials (complex-index code)."""
    from pmvir.polarization.fresnel import fresnel_reflectance

    n = 1.5
    assert float(fresnel_transmittance(torch.tensor(1.0, dtype=F64), n)) == pytest.approx(1.0, abs=1e-12)
    brewster = math.cos(math.atan(n))
    t0 = 1.0 - ((n - 1) / (n + 1)) ** 2
    expected = (1.0 - 0.5 * ((n * n - 1) / (n * n + 1)) ** 2) / t0
    assert float(fresnel_transmittance(torch.tensor(brewster, dtype=F64), n)) == pytest.approx(expected, rel=1e-9)
    cos = np.linspace(0.05, 1.0, 50)
    r_s, r_p = fresnel_reflectance(cos, n)
    np.testing.assert_allclose(
        fresnel_transmittance(torch.from_numpy(cos), n).numpy(), (1.0 - 0.5 * (r_s + r_p)) / t0, rtol=1e-9
    )


def test_diffuse_min_fraction_is_one_minus_the_synth_diffuse_dop_and_with_fresnel_t_s() -> None:
    """1 - rho_d from pmvir.synth.materials' diffuse DoP (the renderer's), and times the unpolarized
    transmittance it is T_s / T_s(0): the s-polarized transmittance alone is what I_min keeps."""
    from pmvir.polarization.fresnel import diffuse_dop, fresnel_reflectance

    n = 1.5
    cos = np.linspace(0.05, 1.0, 50)
    got = diffuse_min_fraction(torch.from_numpy(cos), n).numpy()
    np.testing.assert_allclose(got, 1.0 - diffuse_dop(cos, n), rtol=1e-9)
    assert got[-1] == pytest.approx(1.0, abs=1e-12)
    assert float(diffuse_min_fraction(torch.tensor(0.5, dtype=F64), n)) == pytest.approx(0.9041, abs=1e-4)
    r_s, _ = fresnel_reflectance(cos, n)
    t_s0 = 1.0 - ((n - 1) / (n + 1)) ** 2
    both = got * fresnel_transmittance(torch.from_numpy(cos), n).numpy()
    np.testing.assert_allclose(both, (1.0 - r_s) / t_s0, rtol=1e-9)


def test_diffuse_dop_factor_fits_the_renderers_i_min_at_the_true_surface() -> None:
    """The built-in renderer's plastic I_min of a diffuse surface is K E (1 - rho_d): with the
    factor E_pho's rendering equals it at every emission angle, without it the residual grows
    toward grazing (what pulls normals off the truth)."""
    from pmvir.synth.materials import material_stokes

    cos = np.linspace(0.3, 1.0, 30)
    n_pts = len(cos)
    k, e = np.full((n_pts, 3), 0.5), np.full((n_pts, 3), 0.8)
    stokes = material_stokes(
        "plastic",
        albedo=k,
        diffuse_shading=e,
        mirror_radiance=np.zeros((n_pts, 3)),
        cos_zenith=cos,
        azimuth=np.zeros(n_pts),
        ior=1.5,
        extinction=0.0,
        specular=1.0,
    ).astype(np.float64)
    i_min = stokes[:, :, 0] - np.hypot(stokes[:, :, 1], stokes[:, :, 2])
    normal = torch.from_numpy(np.stack([np.sqrt(1 - cos**2), np.zeros(n_pts), -cos], 1))
    ray = torch.tensor([0.0, 0.0, 1.0], dtype=F64).expand(n_pts, 3)
    factor = diffuse_view_factor(normal, ray, fresnel_ior=0.0, dop_ior=1.5)
    assert factor is not None
    assert diffuse_view_factor(normal, ray, fresnel_ior=0.0, dop_ior=0.0) is None
    np.testing.assert_allclose(k * e * factor.numpy()[:, None], i_min, rtol=1e-5)
    lambert_err = np.abs(k * e - i_min).max(1)
    assert lambert_err[0] > 0.05 * i_min[0, 0] and lambert_err[-1] < 1e-6


def _pho_options(problem, x, k, sh, sc, *, fresnel=1.5, dop=0.0):
    """E_pho with the diffuse view factors and fixed per-pair weights."""
    from dataclasses import replace

    weight = torch.linspace(0.2, 1.0, problem.pairs.size, dtype=F64)
    opt = replace(
        problem, diffuse_fresnel_ior=fresnel, diffuse_dop_ior=dop, pho_weight=weight, polarimetric=False
    )
    return energy_terms(x, k, sh, sc, opt)["pho"]


@pytest.mark.parametrize("fresnel, dop", [(1.5, 0.0), (0.0, 1.5), (1.5, 1.4)])
def test_gradient_of_the_diffuse_factor_photometric_term(small_problem, fresnel, dop) -> None:
    problem, inputs = small_problem
    value = float(_pho_options(problem, *inputs, fresnel=fresnel, dop=dop).detach())
    plain = float(_pho(problem, *inputs).detach())
    assert value > 0.0 and value != pytest.approx(plain)
    assert torch.autograd.gradcheck(
        lambda *a: _pho_options(problem, *a, fresnel=fresnel, dop=dop) / value,
        inputs,
        eps=1e-6,
        atol=1e-7,
        rtol=1e-4,
    )


def test_gradient_of_the_photometric_term_with_shadow_factors(small_problem) -> None:
    """refine.pho.shadowing's per-pair factor (data, fixed for the stage) scales each pair's rendering."""
    from dataclasses import replace

    problem, inputs = small_problem
    factor = torch.linspace(0.3, 1.0, problem.pairs.size, dtype=F64)
    shadowed = replace(problem, light_factor=factor, polarimetric=False)
    x, k, sh, sc = inputs
    value = float(energy_terms(x, k, sh, sc, shadowed)["pho"].detach())
    # the same as scaling each pair's albedo by its factor
    light = pair_light(vertex_normals(x, problem.faces), sh, sc, problem.pairs)
    samples = sample_pairs(x, vertex_normals(x, problem.faces), problem.views, problem.pairs)

    def pho(scaled: torch.Tensor) -> float:
        term = photometric_term(samples.intensity, scaled, k, problem.pairs, units=problem.units)
        return float(term.detach())

    assert value == pytest.approx(pho(light * factor[:, None]), rel=1e-12)
    assert value != pytest.approx(pho(light), rel=1e-3)
    assert torch.autograd.gradcheck(
        lambda *a: energy_terms(*a, shadowed)["pho"] / value, inputs, eps=1e-6, atol=1e-7, rtol=1e-4
    )


def test_pair_light_is_each_pairs_basis_times_its_views_lighting(small_problem) -> None:
    """pair_light evaluates the SH basis per vertex and gathers one shading per pair: it must equal
    the basis of the pair's own normal times its own view's coefficients and colour scale."""
    problem, inputs = small_problem
    rng = np.random.default_rng(11)
    x = inputs[0].detach()
    n = vertex_normals(x, problem.faces)
    sc = inputs[3].detach()
    for order, terms in ((2, 9), (4, 25)):
        sh = torch.from_numpy(rng.normal(0.0, 0.3, (sc.shape[0], terms)))
        got = pair_light(n, sh, sc, problem.pairs).numpy()
        v, c = problem.pairs.vertex.numpy(), problem.pairs.view.numpy()
        basis = sh_basis(n.numpy()[v], order)
        want = (basis * sh.numpy()[c]).sum(1)[:, None] * sc.numpy()[c]
        assert len(np.unique(c)) > 1
        np.testing.assert_allclose(got, want, rtol=1e-10, atol=1e-12)
    with pytest.raises(ShapeError, match="lighting for"):
        pair_light(n, sh[:-1], sc[:-1], problem.pairs)


def test_gradient_of_the_photometric_term_with_degree_4_lighting(small_problem) -> None:
    """refine.lighting.sh_order 4: E_pho through the 25-term shading basis, against finite differences in
    every input; the degree-3 and degree-4 coefficients change its value."""
    problem, inputs = small_problem
    rng = np.random.default_rng(5)
    sh9 = inputs[2].detach()
    sh25 = torch.cat([sh9, torch.from_numpy(rng.normal(0.0, 0.05, (sh9.shape[0], 16)))], dim=1)
    args = (inputs[0], inputs[1], sh25.requires_grad_(), inputs[3])
    value = float(_pho(problem, *args).detach())
    assert value > 0.0 and value != pytest.approx(float(_pho(problem, *inputs).detach()))
    assert torch.autograd.gradcheck(
        lambda *a: _pho(problem, *a) / value, args, eps=1e-6, atol=1e-7, rtol=1e-4
    )
