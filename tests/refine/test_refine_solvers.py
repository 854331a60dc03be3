"""L-BFGS with strong-Wolfe line search, the graph preconditioner and the projected albedo."""

from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch

from pmvir.refine.albedo import AlbedoSolver
from pmvir.refine.energy import photometric_smoothness_term, photometric_term
from pmvir.refine.lbfgs import _two_loop, minimize_lbfgs, strong_wolfe
from pmvir.refine.mesh_ops import GraphSmoother, face_adjacency, unique_edges
from pmvir.refine.sampling import PairSet
from pmvir.synth.shapes import geodesic_sphere

F64 = torch.float64


def _rosenbrock(x: torch.Tensor):
    x = x.detach().requires_grad_(True)
    f = (100.0 * (x[1:] - x[:-1] ** 2) ** 2 + (1.0 - x[:-1]) ** 2).sum()
    (g,) = torch.autograd.grad(f, x)
    return float(f.detach()), g, {"f": float(f.detach())}


def test_lbfgs_minimizes_rosenbrock_and_logs_every_iteration() -> None:
    log = []
    res = minimize_lbfgs(
        _rosenbrock,
        torch.tensor([-1.2, 1.0, -0.5, 0.8], dtype=F64),
        max_iterations=200,
        rel_tolerance=0.0,
        grad_tolerance=1e-8,
        on_iteration=lambda it, f, g, aux: log.append((it, f, aux)),
    )
    np.testing.assert_allclose(res.x.numpy(), np.ones(4), atol=1e-5)
    assert res.reason == "gradient_norm"
    assert [it for it, _, _ in log] == list(range(res.iterations + 1))
    values = [f for _, f, _ in log]
    assert all(b < a for a, b in itertools.pairwise(values))  # the line search only accepts decreases
    assert log[-1][2]["f"] == pytest.approx(res.value)


def test_lbfgs_stops_on_max_iterations_and_relative_decrease() -> None:
    x0 = torch.tensor([-1.2, 1.0], dtype=F64)
    assert minimize_lbfgs(_rosenbrock, x0, max_iterations=3, rel_tolerance=0.0).reason == "max_iterations"
    res = minimize_lbfgs(_rosenbrock, x0, max_iterations=500, rel_tolerance=0.05, grad_tolerance=0.0)
    assert res.reason == "relative_decrease" and res.iterations < 500


def test_line_search_stops_zooming_into_noise() -> None:
    """A cost known to 1e-5 of itself (float32 sums, an inner solve): once the trial values differ by
    less than that, more probes buy nothing; without the floor the zoom runs to its cap."""
    rng = np.random.default_rng(0)

    def noisy(x):  # flat up to noise of 1e-5 of the value, with a gradient that promises a decrease
        return 1.0 + 1e-5 * rng.standard_normal(), torch.ones_like(x), None

    x = torch.zeros(1, dtype=F64)
    f, g, _ = noisy(x)
    d = -g
    counts = {}
    for floor in (0.0, 1e-5):
        _, counts[floor] = strong_wolfe(noisy, x, 1.0, d, f, g, float(g @ d), f_tolerance=floor)
    assert counts[0.0] >= 10
    assert counts[1e-5] <= 3


def test_lbfgs_with_exact_preconditioner_solves_a_quadratic_at_once() -> None:
    rng = np.random.default_rng(0)
    a = rng.normal(size=(30, 30))
    h = torch.from_numpy(a @ a.T + 30 * np.eye(30))
    b = torch.from_numpy(rng.normal(size=30))
    hinv = torch.linalg.inv(h)

    def quad(x):
        return float(0.5 * x @ h @ x - b @ x), h @ x - b, None

    res = minimize_lbfgs(
        quad,
        torch.zeros(30, dtype=F64),
        precondition=lambda v: hinv @ v,
        max_iterations=5,
        grad_tolerance=1e-9,
    )
    assert res.iterations <= 2
    np.testing.assert_allclose(res.x.numpy(), torch.linalg.solve(h, b).numpy(), atol=1e-8)


def test_two_loop_direction_is_the_lbfgs_inverse_hessian_with_the_preconditioner_folded_in() -> None:
    """The two-loop recursion, fed P g and the history's P y instead of applying P, gives -H g with
    H the L-BFGS update of H0 = gamma P written out as matrices."""
    rng = np.random.default_rng(3)
    n, m, gamma = 12, 4, 0.7
    a = rng.normal(size=(n, n))
    p = torch.from_numpy(a @ a.T + n * np.eye(n))
    s_hist, y_hist, rho_hist = [], [], []
    while len(s_hist) < m:
        s, y = torch.from_numpy(rng.normal(size=n)), torch.from_numpy(rng.normal(size=n))
        if float(y @ s) > 0.1:
            s_hist.append(s), y_hist.append(y), rho_hist.append(1.0 / float(y @ s))
    g = torch.from_numpy(rng.normal(size=n))
    d = _two_loop(g, p @ g, s_hist, y_hist, [p @ y for y in y_hist], rho_hist, gamma=gamma)
    h = gamma * p
    eye = torch.eye(n, dtype=F64)
    for s, y, rho in zip(s_hist, y_hist, rho_hist, strict=True):
        h = (eye - rho * torch.outer(s, y)) @ h @ (eye - rho * torch.outer(y, s)) + rho * torch.outer(s, s)
    np.testing.assert_allclose(d.numpy(), (-h @ g).numpy(), rtol=1e-10, atol=1e-12)


def test_lbfgs_applies_the_preconditioner_once_per_iteration() -> None:
    """P is the costly part of an iteration on a large mesh (a 30-term graph smoother): it is applied
    to each accepted gradient only, the start's included."""
    calls = []

    def precondition(v: torch.Tensor) -> torch.Tensor:
        calls.append(1)
        return 0.5 * v

    res = minimize_lbfgs(_rosenbrock, torch.zeros(6, dtype=F64), precondition=precondition, max_iterations=25,
                         rel_tolerance=0.0, grad_tolerance=0.0)
    assert res.iterations == 25
    assert len(calls) == res.iterations + 1


def test_graph_smoother_approximates_the_screened_laplacian_inverse() -> None:
    v, f = geodesic_sphere(4)
    e = unique_edges(f)
    n = len(v)
    lap = np.zeros((n, n))
    lap[e[:, 0], e[:, 1]] = lap[e[:, 1], e[:, 0]] = -1.0
    lap[np.arange(n), np.arange(n)] = -lap.sum(1)
    x = np.random.default_rng(1).normal(size=(n, 3))
    exact = np.linalg.solve(np.eye(n) + 2.0 * lap, x)
    smooth = GraphSmoother(e, n, lam=2.0, iterations=200, device="cpu", dtype=F64)
    np.testing.assert_allclose(smooth(torch.from_numpy(x)).numpy(), exact, atol=1e-6)
    short = GraphSmoother(e, n, lam=2.0, iterations=5, device="cpu", dtype=F64)
    m = np.stack([short(torch.from_numpy(c)).numpy() for c in np.eye(n)], axis=1)
    np.testing.assert_allclose(m, m.T, atol=1e-12)  # symmetric ...
    assert np.linalg.eigvalsh(m).min() > 0  # ... positive definite: a valid preconditioner


def test_face_adjacency_of_a_closed_mesh() -> None:
    _, f = geodesic_sphere(3)
    fp = face_adjacency(f)
    assert np.all(np.bincount(fp[:, 0], minlength=len(f)) == 3)  # three edge neighbours per face
    shared = [len(set(f[a]) & set(f[b])) for a, b in fp]
    assert set(shared) == {2}


def _sorted_pairs(vert: np.ndarray, view: np.ndarray, n: int, n_views: int) -> tuple[PairSet, np.ndarray, np.ndarray]:
    """The pairs (vertex, view) sorted by view, weighted 1/|V(i)|; also their vertices and |V(i)|."""
    order = np.argsort(view, kind="stable")
    vert, view = vert[order], view[order]
    count = np.bincount(vert, minlength=n)
    pairs = PairSet(
        torch.from_numpy(vert),
        torch.from_numpy(view),
        np.concatenate([[0], np.cumsum(np.bincount(view, minlength=n_views))]).tolist(),
        torch.from_numpy(1.0 / count[vert]),
        count,
        torch.from_numpy(vert * n_views + view),
    )
    return pairs, vert, count


def test_projected_albedo_solves_the_normal_equations() -> None:
    """K* from CG equals the dense solution and zeroes the gradient of E_pho + tau3 E_psm in K."""
    rng = np.random.default_rng(2)
    v, f = geodesic_sphere(3)
    n = len(v)
    e = unique_edges(f)
    vert = np.repeat(np.arange(n), 3)[rng.random(3 * n) < 0.7]
    vert = vert[vert != 5]  # vertex 5 has no observation: only E_psm determines it
    view = rng.integers(0, 4, len(vert))
    pairs, vert, count = _sorted_pairs(vert, view, n, 4)
    observed = torch.from_numpy(rng.uniform(0.1, 0.9, (len(vert), 3)))
    light = torch.from_numpy(rng.uniform(0.5, 1.5, (len(vert), 3)))
    w = rng.uniform(0.1, 1.0, len(e))
    tau = 2.0
    solver = AlbedoSolver(pairs, e, w, tau, torch.full((n, 3), 0.5, dtype=F64), tol=1e-12, ridge=0.0)
    k = solver(observed, light)
    lap = np.zeros((n, n))
    np.add.at(lap, (e[:, 0], e[:, 1]), -w)
    np.add.at(lap, (e[:, 1], e[:, 0]), -w)
    lap[np.arange(n), np.arange(n)] = -lap.sum(1)
    wp = 1.0 / count[vert]
    for ch in range(3):
        a = light[:, ch].numpy()
        d = np.bincount(vert, wp * a * a, n)
        b = np.bincount(vert, wp * a * observed[:, ch].numpy(), n)
        np.testing.assert_allclose(
            k[:, ch].numpy(), np.linalg.solve(np.diag(d) + 2 * tau * lap, b), atol=1e-9
        )
    kk = k.clone().requires_grad_(True)
    et = torch.from_numpy(e)
    energy = photometric_term(observed, light, kk, pairs) + tau * photometric_smoothness_term(
        kk, et, torch.from_numpy(w)
    )
    (g,) = torch.autograd.grad(energy, kk)
    assert float(g.abs().max()) < 1e-6 * float(energy.detach())
    # The refinement's float32: the same CG in single precision reaches the default tolerance and
    # the float64 solution to single precision's accuracy.
    pairs32 = PairSet(pairs.vertex, pairs.view, pairs.offsets, pairs.weight.float(), count, pairs.flat)
    single = AlbedoSolver(pairs32, e, w, tau, torch.full((n, 3), 0.5))
    k32 = single(observed.float(), light.float())
    assert k32.dtype == torch.float32 and single.iterations < 500
    np.testing.assert_allclose(k32.numpy(), k.numpy(), atol=2e-5)


def test_projected_albedo_is_the_minimizer_over_nonnegative_albedos() -> None:
    """Where the shading is negative (an SH expansion facing away from its light) the unbounded K* goes
    below zero; the solver's K* >= 0 meets the bounded problem's optimality conditions: zero gradient
    on the free entries, a gradient pointing into K > 0 on those held at zero."""
    rng = np.random.default_rng(3)
    v, f = geodesic_sphere(3)
    n = len(v)
    e = unique_edges(f)
    vert = np.repeat(np.arange(n), 3)
    view = np.tile(np.arange(3), n)
    pairs, vert, count = _sorted_pairs(vert, view, n, 3)
    observed = torch.from_numpy(rng.uniform(0.1, 0.9, (len(vert), 3)))
    # the shading is negative on the vertices with z < -0.5 (every view), and a few others
    shade = np.where(v[vert, 2] < -0.5, -0.3, 1.0)[:, None] * rng.uniform(0.5, 1.5, (len(vert), 3))
    light = torch.from_numpy(shade)
    w = rng.uniform(0.1, 1.0, len(e))
    tau = 0.05
    lap = np.zeros((n, n))
    np.add.at(lap, (e[:, 0], e[:, 1]), -w)
    np.add.at(lap, (e[:, 1], e[:, 0]), -w)
    lap[np.arange(n), np.arange(n)] = -lap.sum(1)
    wp = 1.0 / count[vert]
    solver = AlbedoSolver(pairs, e, w, tau, torch.full((n, 3), 0.5, dtype=F64), tol=1e-12, ridge=0.0)
    k = solver(observed, light).numpy()
    assert solver.held > 0 and solver.held_rounds >= 1
    assert (k >= 0).all()
    for ch in range(3):
        a = light[:, ch].numpy()
        mat = np.diag(np.bincount(vert, wp * a * a, n)) + 2 * tau * lap
        b = np.bincount(vert, wp * a * observed[:, ch].numpy(), n)
        assert (np.linalg.solve(mat, b) < -0.1).any()  # the unbounded minimizer is far below zero
        grad = mat @ k[:, ch] - b
        free = k[:, ch] > 0
        scale = np.abs(b).max()
        assert np.abs(grad[free]).max() < 1e-8 * scale
        assert (~free).any() and grad[~free].min() > -1e-8 * scale
    # warm-started again from that solution with other data, the held set changes and is still optimal
    solver2 = AlbedoSolver(pairs, e, w, tau, torch.from_numpy(k), tol=1e-12, ridge=0.0)
    k2 = solver2(observed, torch.from_numpy(np.abs(shade))).numpy()
    assert solver2.held == 0 and (k2 > 0).all()
