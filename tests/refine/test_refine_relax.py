"""After the last stage: Taubin fairing (``refine.surface.fair_iterations``, scaled to the mesh's face size) damps wrinkles and keeps the shape;
tangential relaxation (``refine.surface.relax_iterations``) spreads the vertices and keeps the surface."""

from __future__ import annotations

import numpy as np
import pytest
from refine_scene import make_scene

from pmvir.config import RefineOptions
from pmvir.errors import ConfigError
from pmvir.evaluate import SurfaceQuery
from pmvir.geometry.mesh_ops import ReferenceSurface, barycentric, edge_topology, vertex_normals
from pmvir.geometry.surface.clean import facing_projected_areas
from pmvir.progress import Progress
from pmvir.refine import make_visibility_fn, observation_from_decoded
from pmvir.refine.albedo import AlbedoSolver
from pmvir.refine.energy import energy_terms
from pmvir.refine.mesh_ops import unique_edges
from pmvir.refine.relax import (
    FAIR_MAX_SCALE,
    carry_values,
    fair_taubin,
    fairing_scale,
    relax_tangentially,
    taubin_schedule,
)
from pmvir.synth.shapes import geodesic_sphere

ONE_STAGE = {"stages": {"tau_pol": [60.0], "tau_gsm": [0.1], "tau_psm": [2.0], "gsm_exponent": [2.2]}}


def _edge_cv(v: np.ndarray, f: np.ndarray) -> float:
    e = unique_edges(f)
    length = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1)
    return float(length.std() / length.mean())


def _surface_distance(points: np.ndarray, v: np.ndarray, f: np.ndarray) -> np.ndarray:
    closest, _, _ = SurfaceQuery(v, f).closest(points)
    return np.linalg.norm(closest - points, axis=1)


def _crowded_sphere() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A geodesic sphere whose vertices slid along its own surface by up to 0.4 edge lengths each, in
    random directions (as free motion crowds them, vertex by vertex): (even vertices, crowded
    vertices, faces); the crowded ones lie on the even mesh."""
    v, f = geodesic_sphere(12)
    e = unique_edges(f)
    h = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean()
    slide = np.random.default_rng(5).uniform(-0.4 * h, 0.4 * h, size=v.shape)
    slide -= np.einsum("ij,ij->i", slide, v)[:, None] * v  # tangential (v is the unit normal)
    crowded, _ = ReferenceSurface(v, f).project(v + slide)
    return v, crowded, f


def test_unique_edges_lists_each_undirected_edge_once_in_order() -> None:
    rng = np.random.default_rng(3)
    f = rng.integers(0, 40, size=(300, 3))
    f[:5, 1] = f[:5, 0]  # degenerate faces: their zero-length edge is left out
    sides = [(tri[k], tri[(k + 1) % 3]) for tri in f.tolist() for k in range(3)]
    expected = sorted({(min(a, b), max(a, b)) for a, b in sides if a != b})
    e = unique_edges(f)
    assert e.dtype == np.int64 and e.tolist() == [list(x) for x in expected]
    assert unique_edges(np.zeros((0, 3), dtype=np.int64)).shape == (0, 2)


def test_relaxation_evens_out_crowded_vertices_and_keeps_them_on_the_surface() -> None:
    even, crowded, f = _crowded_sphere()
    assert _edge_cv(crowded, f) > 1.5 * _edge_cv(even, f)
    relaxed, face_ids, bary = relax_tangentially(crowded, f, 20)
    # On the input surface (to float precision) and so still on the sphere's polyhedron.
    assert _surface_distance(relaxed, crowded, f).max() < 1e-6
    assert np.abs(np.linalg.norm(relaxed, axis=1) - 1.0).max() < 0.01
    # Much of the crowding is gone: the edge-length spread falls most of the way back.
    cv_even, cv_crowded, cv_relaxed = _edge_cv(even, f), _edge_cv(crowded, f), _edge_cv(relaxed, f)
    assert cv_relaxed < cv_even + 0.35 * (cv_crowded - cv_even)
    # The returned faces and weights locate each relaxed vertex on the input mesh.
    located = np.einsum("nk,nkc->nc", bary, crowded[f[face_ids]])
    assert np.abs(located - relaxed).max() < 1e-9
    assert np.all(bary > -1e-9)


def test_relaxation_pins_the_boundary_and_stays_in_a_plane() -> None:
    """A planar grid with its interior jittered within the plane relaxes back toward the regular grid;
    boundary vertices do not move and nothing leaves the plane."""
    n = 12
    x, y = np.meshgrid(np.arange(n, dtype=float), np.arange(n, dtype=float), indexing="ij")
    grid = np.stack([x.ravel(), y.ravel(), np.zeros(n * n)], axis=1)
    idx = np.arange(n * n).reshape(n, n)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)])
    boundary = (grid[:, 0] == 0) | (grid[:, 0] == n - 1) | (grid[:, 1] == 0) | (grid[:, 1] == n - 1)
    rng = np.random.default_rng(3)
    jittered = grid.copy()
    jittered[~boundary, :2] += rng.uniform(-0.3, 0.3, size=(int((~boundary).sum()), 2))
    relaxed, _, _ = relax_tangentially(jittered, f, 60)
    assert np.array_equal(relaxed[boundary], jittered[boundary])
    assert np.abs(relaxed[:, 2]).max() < 1e-12
    before = np.abs(jittered - grid)[~boundary].max()
    after = np.abs(relaxed - grid)[~boundary].max()
    assert after < 0.3 * before


def test_carried_values_interpolate_linear_functions_exactly() -> None:
    _, crowded, f = _crowded_sphere()
    relaxed, face_ids, bary = relax_tangentially(crowded, f, 10)
    coef = np.array([[0.2, -1.0, 0.5], [1.5, 0.3, -0.7], [0.0, 0.4, 2.0]])
    carried = carry_values(crowded @ coef, f, face_ids, bary)
    assert np.abs(carried - relaxed @ coef).max() < 1e-9


def test_zero_iterations_change_nothing_and_negative_ones_are_rejected() -> None:
    _, crowded, f = _crowded_sphere()
    same, face_ids, bary = relax_tangentially(crowded, f, 0)
    assert np.array_equal(same, crowded)
    assert np.abs(carry_values(crowded, f, face_ids, bary) - crowded).max() < 1e-12
    with pytest.raises(ConfigError, match="relaxation iterations"):
        relax_tangentially(crowded, f, -1)


def test_barycentric_weights_rebuild_the_point() -> None:
    rng = np.random.default_rng(0)
    a, b, c = rng.normal(size=(3, 50, 3))
    w = rng.dirichlet(np.ones(3), size=50)
    p = w[:, :1] * a + w[:, 1:2] * b + w[:, 2:] * c
    assert np.abs(barycentric(p, a, b, c) - w).max() < 1e-9


@pytest.fixture(scope="module")
def scene_inputs():
    scene = make_scene(two_colours=True)
    obs = [observation_from_decoded(fr, intensity="min") for fr in scene.frames]
    vis = make_visibility_fn(scene.cameras)(scene.vertices, scene.faces)
    return scene, obs, vis


def _first_stage_solved(scene_inputs, **options):
    """Stage 1 of the test scene solved from the paper's start: (unknowns after it, the stage)."""
    from pmvir.refine.solve import solve_stage
    from pmvir.refine.stage_setup import initial_unknowns, make_setup, prepare_stage

    scene, obs, vis = scene_inputs
    opts = RefineOptions(views={"silhouette_margin_px": 0}, **options)
    faces = scene.faces.astype(np.int64)
    setup = make_setup(faces, len(scene.vertices), scene.cameras, obs, opts=opts, visibility_fn=None)
    state = initial_unknowns(
        scene.vertices, len(scene.cameras), sh_order=opts.lighting.sh_order, device=setup.device, dtype=setup.dtype
    )
    stage, state = prepare_stage(setup, state, vis, 0)
    return solve_stage(setup, stage, state, progress=Progress.none())[0], stage


def test_a_relaxed_stage_keeps_its_surface_and_solves_the_albedo_at_the_new_vertices(scene_inputs) -> None:
    """One short (and last) stage from the same start with and without relaxation: the relaxed
    vertices lie on the unrelaxed result's surface, spread at least as evenly, and carry the
    projected albedo's exact minimizer at their own positions."""
    faces = scene_inputs[0].faces.astype(np.int64)
    # One stage, so it is the last: the relaxation follows it.
    plain_state, _ = _first_stage_solved(
        scene_inputs, surface={"relax_iterations": 0, "fair_iterations": 0}, solver={"max_iterations": 15},
        **ONE_STAGE,
    )
    relaxed_state, stage = _first_stage_solved(
        scene_inputs, surface={"relax_iterations": 20, "fair_iterations": 0}, solver={"max_iterations": 15},
        **ONE_STAGE,
    )
    plain = plain_state.vertices.numpy().astype(np.float64)
    relaxed = relaxed_state.vertices.numpy().astype(np.float64)
    assert np.abs(relaxed - plain).max() > 0  # it did move them
    assert _surface_distance(relaxed, plain, faces).max() < 1e-5
    assert _edge_cv(relaxed, faces) <= _edge_cv(plain, faces)
    solver = AlbedoSolver(
        stage.pairs, unique_edges(faces), stage.psm_weight, stage.weights.tau_psm, relaxed_state.albedo
    )
    energy_terms(relaxed_state.vertices, solver, relaxed_state.sh, relaxed_state.rgb_scale, stage.problem)
    np.testing.assert_allclose(solver.current.numpy(), relaxed_state.albedo.numpy(), atol=2e-3)


def test_only_the_last_stage_is_relaxed(scene_inputs) -> None:
    """Stages before the last end where L-BFGS left them: relaxing between stages measured worse."""
    plain, _ = _first_stage_solved(
        scene_inputs, surface={"relax_iterations": 0}, solver={"max_iterations": 5}
    )
    relaxed, _ = _first_stage_solved(
        scene_inputs, surface={"relax_iterations": 20}, solver={"max_iterations": 5}
    )
    assert np.array_equal(plain.vertices.numpy(), relaxed.vertices.numpy())


def _sphere_normal_error(v: np.ndarray, f: np.ndarray) -> float:
    """Median angle (degrees) between the mesh's vertex normals and the unit sphere's normals at them."""
    n = vertex_normals(v, f)
    true = v / np.linalg.norm(v, axis=1, keepdims=True)
    return float(np.degrees(np.median(np.arccos(np.clip((n * true).sum(1), -1.0, 1.0)))))


def test_fairing_damps_wrinkles_without_shrinking_and_keeps_wide_bumps() -> None:
    """A unit sphere with a bump ten edges wide and radial noise of a fifth of an edge: fairing brings
    the normals back toward the true ones, keeps the radius (plain umbrella smoothing shrinks it by
    more) and most of the bump's height."""
    v, f = geodesic_sphere(12)
    e = unique_edges(f)
    h = np.linalg.norm(v[e[:, 0]] - v[e[:, 1]], axis=1).mean()
    axis = np.array([0.0, 0.0, 1.0])
    bump = 3 * h * np.exp(-(np.arccos(np.clip(v @ axis, -1, 1)) / (5 * h)) ** 2)
    shaped = v * (1.0 + bump)[:, None]
    noisy = shaped * (1.0 + np.random.default_rng(2).normal(0.0, 0.2 * h, len(v)))[:, None]
    faired = fair_taubin(noisy, f, 16)
    assert _sphere_normal_error(faired, f) < 0.6 * _sphere_normal_error(noisy, f)
    top = int(np.argmax(v @ axis))
    radius = np.linalg.norm(faired, axis=1)
    far = bump < 1e-3 * h
    assert abs(np.median(radius[far]) - 1.0) < 0.05 * h
    assert radius[top] - 1.0 > 0.7 * (np.linalg.norm(shaped[top]) - 1.0)
    degree = np.bincount(e.reshape(-1), minlength=len(v))[:, None]
    mean = noisy.copy()
    for _ in range(32):  # the same number of umbrella steps, all shrinking
        ring = np.zeros_like(mean)
        np.add.at(ring, e[:, 0], mean[e[:, 1]])
        np.add.at(ring, e[:, 1], mean[e[:, 0]])
        mean = mean + 0.5 * (ring / degree - mean)
    assert 1.0 - np.median(np.linalg.norm(mean, axis=1)[far]) > 4 * abs(np.median(radius[far]) - 1.0)


def test_fairing_keeps_boundary_vertices_and_zero_iterations_is_the_input() -> None:
    v, f = geodesic_sphere(6)
    keep = v[:, 2] < 0.3
    f = f[keep[f].all(axis=1)]  # an open cap: its rim is a boundary
    noisy = v + np.random.default_rng(1).normal(0.0, 0.01, v.shape)
    faired = fair_taubin(noisy, f, 8)
    used = np.unique(f)
    topo = edge_topology(f, len(v))
    boundary = np.unique(topo.edges[~topo.interior])
    assert len(boundary) > 0
    np.testing.assert_array_equal(faired[boundary], noisy[boundary])
    unused = np.setdiff1d(np.arange(len(v)), used)
    np.testing.assert_array_equal(faired[unused], noisy[unused])
    interior = np.setdiff1d(used, boundary)
    assert np.abs(faired[interior] - noisy[interior]).max() > 0
    np.testing.assert_array_equal(fair_taubin(noisy, f, 0), noisy)
    with pytest.raises(ConfigError, match="fairing iterations"):
        fair_taubin(noisy, f, -1)


def test_fairing_is_the_refinements_last_move_of_the_surface(scene_inputs) -> None:
    """One short stage refined with and without fairing: the faired result is the unfaired one faired
    at the scale of its median projected face area (or unscaled, or at the largest scale, as the
    reference area sets), each vertex keeping its albedo, and report.json's timings name the step."""
    from pmvir.refine import refine_surface

    scene, obs, vis = scene_inputs
    faces = scene.faces.astype(np.int64)

    def refined(fair: int, reference: float = 2.0):
        surface = {"fair_iterations": fair, "fair_reference_area_px": reference}
        opts = RefineOptions.model_validate({"surface": surface, "solver": {"max_iterations": 5}, **ONE_STAGE})
        return refine_surface(scene.vertices, faces, scene.cameras, obs, vis, options=opts)

    plain, faired = refined(0), refined(4)
    assert plain.fairing is None and faired.fairing is not None
    areas = facing_projected_areas(plain.vertices, faces, scene.cameras)
    assert faired.fairing.median_face_area_px == pytest.approx(np.median(areas[areas > 0]), rel=1e-5)
    assert faired.fairing.scale == pytest.approx(fairing_scale(faired.fairing.median_face_area_px, 2.0))
    assert faired.fairing.pairs == round(4 * faired.fairing.scale**2)
    np.testing.assert_allclose(
        faired.vertices, fair_taubin(plain.vertices, faces, 4, scale=faired.fairing.scale), atol=1e-6
    )
    assert np.abs(faired.vertices - plain.vertices).max() > 0
    np.testing.assert_array_equal(faired.albedo, plain.albedo)
    assert "fairing" in faired.timings and "fairing" not in plain.timings
    # scaling off: no areas, the reference's 4 pairs; a reference far above the mesh's faces: the largest scale
    unscaled, finest = refined(4, 0.0), refined(4, 1e3)
    assert unscaled.fairing is not None and finest.fairing is not None
    assert (unscaled.fairing.median_face_area_px, unscaled.fairing.scale, unscaled.fairing.pairs) == (0.0, 1.0, 4)
    np.testing.assert_allclose(unscaled.vertices, fair_taubin(plain.vertices, faces, 4), atol=1e-6)
    assert finest.fairing.scale == FAIR_MAX_SCALE and finest.fairing.pairs == 4 * round(FAIR_MAX_SCALE**2)
    np.testing.assert_allclose(finest.vertices, fair_taubin(plain.vertices, faces, 4, scale=FAIR_MAX_SCALE), atol=1e-6)


def _rippled_grid(n: int, wavelength: float) -> tuple[np.ndarray, np.ndarray]:
    """The unit square as an n x n grid of right triangles, rippled in z with the given wavelength
    (amplitude 1e-3, along x)."""
    x, y = np.meshgrid(np.linspace(0.0, 1.0, n + 1), np.linspace(0.0, 1.0, n + 1))
    v = np.stack([x.ravel(), y.ravel(), 1e-3 * np.sin(2 * np.pi * x.ravel() / wavelength)], axis=1)
    k = (np.arange(n)[:, None] * (n + 1) + np.arange(n)[None, :]).ravel()
    f = np.concatenate([np.stack([k, k + 1, k + n + 2], 1), np.stack([k, k + n + 2, k + n + 1], 1)])
    return v, f


def _kept(v: np.ndarray, faired: np.ndarray) -> float:
    """Share of the ripple's amplitude left away from the pinned boundary."""
    inner = (np.abs(v[:, :2] - 0.5) < 0.3).all(axis=1)
    return float(np.abs(faired[inner, 2]).max() / np.abs(v[inner, 2]).max())


def test_a_finer_mesh_is_faired_to_the_same_ripple_length() -> None:
    """Ripples four and six edges long on a grid; on a grid with edges half as long (faces four times
    smaller) the same ripples are eight and twelve edges long. The reference's pairs keep nearly all
    of them there; the schedule scaled by 4 removes each as on the coarse grid."""
    for coarse_edges in (4, 6):
        coarse = _rippled_grid(40, coarse_edges / 40)
        fine = _rippled_grid(80, coarse_edges / 40)
        kept_coarse = _kept(coarse[0], fair_taubin(*coarse, 16))
        assert kept_coarse < 0.8
        assert _kept(fine[0], fair_taubin(*fine, 16)) > 0.9
        assert _kept(fine[0], fair_taubin(*fine, 16, scale=4.0)) == pytest.approx(kept_coarse, abs=0.1)
    wide = _rippled_grid(80, 20 / 40)
    assert _kept(wide[0], fair_taubin(*wide, 16, scale=4.0)) > 0.95
    assert taubin_schedule(16) == (16, pytest.approx(-0.53))
    pairs, mu = taubin_schedule(16, 4.0)
    assert pairs == 256 and 1 / 0.5 + 1 / mu == pytest.approx((1 / 0.5 - 1 / 0.53) / 4)
    with pytest.raises(ConfigError, match="scale"):
        taubin_schedule(16, 0.5)


def test_fairing_scale_follows_the_median_face_area() -> None:
    assert fairing_scale(2.0, 2.0) == 1.0
    assert fairing_scale(0.5, 2.0) == pytest.approx(4.0)
    assert fairing_scale(0.75, 1.5) == pytest.approx(2.0)
    assert fairing_scale(8.0, 2.0) == 1.0  # a coarser mesh is faired as given
    assert fairing_scale(1e-6, 2.0) == FAIR_MAX_SCALE
    assert fairing_scale(0.0, 2.0) == 1.0  # no face seen
    assert fairing_scale(0.5, 0.0) == 1.0  # scaling off
