"""Limited-memory BFGS with a strong-Wolfe line search, on one flat parameter tensor.

Written out (rather than ``torch.optim.LBFGS``) so that every accepted
iteration can be logged with the named energy terms of the point it accepted,
cancellation can be checked at iteration boundaries, and no evaluation is
repeated between iterations. The line search is Nocedal & Wright's algorithms
3.5/3.6 with safeguarded cubic interpolation (as in minFunc and PyTorch).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

#: fun(x) -> (value, gradient, aux): aux is passed through to the iteration callback.
Objective = Callable[[torch.Tensor], tuple[float, torch.Tensor, Any]]


@dataclass(frozen=True)
class LbfgsResult:
    """Outcome of :func:`minimize_lbfgs`.

    Attributes:
        x: the final parameters (the best accepted point).
        value: the objective there.
        iterations: accepted iterations.
        evaluations: objective evaluations (including line-search trials).
        reason: why it stopped: ``"max_iterations"``, ``"relative_decrease"``,
            ``"gradient_norm"`` or ``"line_search"`` (no step decreased the objective).
    """

    x: torch.Tensor
    value: float
    iterations: int
    evaluations: int
    reason: str


def _cubic_min(
    x1: float,
    f1: float,
    g1: float,
    x2: float,
    f2: float,
    g2: float,
    bounds: tuple[float, float] | None = None,
) -> float:
    """Minimizer of the cubic through (x1, f1, g1), (x2, f2, g2), clamped to ``bounds``."""
    lo, hi = bounds if bounds is not None else (min(x1, x2), max(x1, x2))
    if x1 == x2:
        return (lo + hi) / 2.0
    d1 = g1 + g2 - 3.0 * (f1 - f2) / (x1 - x2)
    d2_sq = d1 * d1 - g1 * g2
    if d2_sq < 0 or not math.isfinite(d2_sq):
        return (lo + hi) / 2.0
    d2 = math.sqrt(d2_sq)
    if x1 <= x2:
        den = g2 - g1 + 2.0 * d2
        pos = x2 - (x2 - x1) * ((g2 + d2 - d1) / den) if den != 0 else (lo + hi) / 2.0
    else:
        den = g1 - g2 + 2.0 * d2
        pos = x1 - (x1 - x2) * ((g1 + d2 - d1) / den) if den != 0 else (lo + hi) / 2.0
    if not math.isfinite(pos):
        return (lo + hi) / 2.0
    return min(max(pos, lo), hi)


@dataclass
class _Point:
    t: float
    f: float
    g: torch.Tensor
    gtd: float
    aux: Any


def _bracket_closed(a: _Point, b: _Point, d_norm: float, min_move: float, min_change: float) -> bool:
    """True when the zoom cannot tell its two ends apart: in position (largest component of the
    move between them below ``min_move``), or in value (within ``min_change``)."""
    if abs(b.t - a.t) * d_norm < min_move:
        return True
    return math.isfinite(a.f) and math.isfinite(b.f) and abs(a.f - b.f) <= min_change


def strong_wolfe(
    fun: Objective,
    x: torch.Tensor,
    t: float,
    d: torch.Tensor,
    f: float,
    g: torch.Tensor,
    gtd: float,
    *,
    c1: float = 1e-4,
    c2: float = 0.9,
    tolerance_change: float = 1e-12,
    f_tolerance: float = 0.0,
    max_evaluations: int = 25,
) -> tuple[_Point, int]:
    """Step length along ``d`` satisfying the strong Wolfe conditions (or the best one found).

    The zoom stops early, keeping the best point so far, once the bracket's two ends differ in
    value by at most ``f_tolerance * |f|``: a cost evaluated in float32 sums (and with an inner
    solve to a tolerance) is only known to about that, and zooming further probes noise.

    Returns:
        the accepted point (t may be 0 when nothing decreased the objective) and the
        number of evaluations made.
    """

    def probe(step: float) -> _Point:
        fv, gv, aux = fun(x + step * d)
        return _Point(step, fv, gv, float(gv @ d), aux)

    d_norm = float(d.abs().max())
    start = _Point(0.0, f, g, gtd, None)
    prev = start
    new = probe(t)
    n_eval = 1
    bracket: list[_Point] = []
    done = False
    while n_eval < max_evaluations:
        if not math.isfinite(new.f) or new.f > f + c1 * new.t * gtd or (n_eval > 1 and new.f >= prev.f):
            bracket = [prev, new]
            break
        if abs(new.gtd) <= -c2 * gtd:
            bracket, done = [new], True
            break
        if new.gtd >= 0:
            bracket = [prev, new]
            break
        lo, hi = new.t + 0.01 * (new.t - prev.t), new.t * 10.0
        step = _cubic_min(prev.t, prev.f, prev.gtd, new.t, new.f, new.gtd, bounds=(lo, hi))
        prev, new = new, probe(step)
        n_eval += 1
    else:
        bracket = [start, new] if not math.isfinite(new.f) or new.f > f else [new]
        done = len(bracket) == 1

    insufficient = False
    while not done and n_eval < max_evaluations:
        a, b = bracket
        low, high = (0, 1) if a.f <= b.f else (1, 0)
        if _bracket_closed(a, b, d_norm, tolerance_change, f_tolerance * abs(f)):
            break
        fa = a.f if math.isfinite(a.f) else 1e300
        fb = b.f if math.isfinite(b.f) else 1e300
        step = _cubic_min(a.t, fa, a.gtd, b.t, fb, b.gtd)
        tmax, tmin = max(a.t, b.t), min(a.t, b.t)
        eps = 0.1 * (tmax - tmin)
        if min(tmax - step, step - tmin) < eps:
            if insufficient or step >= tmax or step <= tmin:
                step = tmax - eps if abs(step - tmax) < abs(step - tmin) else tmin + eps
                insufficient = False
            else:
                insufficient = True
        else:
            insufficient = False
        new = probe(step)
        n_eval += 1
        if not math.isfinite(new.f) or new.f > f + c1 * new.t * gtd or new.f >= bracket[low].f:
            bracket[high] = new
        else:
            if abs(new.gtd) <= -c2 * gtd:
                done = True
            elif new.gtd * (bracket[high].t - bracket[low].t) >= 0:
                bracket[high] = bracket[low]
            bracket[low] = new
    best = min(bracket, key=lambda p: p.f if math.isfinite(p.f) else math.inf)
    if not math.isfinite(best.f) or best.f >= f:
        return start, n_eval
    return best, n_eval


def _two_loop(
    g: torch.Tensor,
    pg: torch.Tensor,
    s_hist: list[torch.Tensor],
    y_hist: list[torch.Tensor],
    py_hist: list[torch.Tensor],
    rho_hist: list[float],
    *,
    gamma: float,
) -> torch.Tensor:
    """The L-BFGS direction -H g by the two-loop recursion, H0 = gamma * P (Nocedal & Wright, Alg. 7.4).

    P is linear, so P q of the middle step is assembled from ``pg`` = P g and the history's
    ``py_hist`` = P y (each the difference of two iterates' P g) instead of applying P again.
    """
    q = -g.clone()
    pq = -pg.clone()
    alphas = []
    for s, y, py, rho in zip(reversed(s_hist), reversed(y_hist), reversed(py_hist), reversed(rho_hist), strict=True):
        a = rho * float(s @ q)
        q.add_(y, alpha=-a)
        pq.add_(py, alpha=-a)
        alphas.append(a)
    q = pq.mul_(gamma)
    for (s, y, rho), a in zip(zip(s_hist, y_hist, rho_hist, strict=True), reversed(alphas), strict=True):
        b = rho * float(y @ q)
        q.add_(s, alpha=a - b)
    return q


def minimize_lbfgs(
    fun: Objective,
    x0: torch.Tensor,
    *,
    max_iterations: int = 50,
    history_size: int = 10,
    rel_tolerance: float = 1e-6,
    grad_tolerance: float = 1e-10,
    on_iteration: Callable[[int, float, float, Any], None] | None = None,
    precondition: Callable[[torch.Tensor], torch.Tensor] | None = None,
    first_step: float | None = None,
) -> LbfgsResult:
    """Minimize ``fun`` from ``x0`` with L-BFGS and a strong-Wolfe line search.

    Stopping rule: after ``max_iterations`` accepted iterations; when an iteration
    lowers the objective by less than ``rel_tolerance`` times its magnitude; when the
    gradient's largest component is at most ``grad_tolerance``; or when the line
    search finds no decrease (its zoom ends once the trial values differ by at most
    ``rel_tolerance`` times the objective).

    Args:
        fun: objective returning (value, flat gradient, aux).
        x0: flat starting parameters.
        on_iteration: called as (iteration, value, gradient max-norm, aux) for the
            starting point (iteration 0) and after every accepted iteration; it may
            raise to abort (e.g. :class:`pmvir.errors.CanceledError`).
        precondition: a symmetric positive-definite linear map P (an approximate inverse
            Hessian up to scale); the initial inverse-Hessian estimate of every iteration
            is gamma * P with gamma = s.y / y.P y (identity when None).
        first_step: the largest component of the first (steepest-descent) trial step, for
            unknowns scaled to O(1); None: PyTorch's choice, a step of L1 norm 1.

    Returns:
        :class:`LbfgsResult`.
    """
    apply_p = precondition if precondition is not None else (lambda v: v)
    x = x0.detach().clone()
    f, g, aux = fun(x)
    pg = apply_p(g)  # P at each accepted gradient only: one application per iteration
    n_eval = 1
    if on_iteration is not None:
        on_iteration(0, f, float(g.abs().max()), aux)
    if not math.isfinite(f):
        return LbfgsResult(x, f, 0, n_eval, "line_search")
    if float(g.abs().max()) <= grad_tolerance:
        return LbfgsResult(x, f, 0, n_eval, "gradient_norm")
    s_hist: list[torch.Tensor] = []
    y_hist: list[torch.Tensor] = []
    py_hist: list[torch.Tensor] = []
    rho_hist: list[float] = []
    gamma = 1.0
    reason = "max_iterations"
    it = 0
    for it in range(1, max_iterations + 1):
        d = _two_loop(g, pg, s_hist, y_hist, py_hist, rho_hist, gamma=gamma)
        gtd = float(g @ d)
        if not s_hist or gtd > -1e-30:
            s_hist, y_hist, py_hist, rho_hist = [], [], [], []
            d = -pg
            gtd = float(g @ d)
            if first_step is not None:
                t0 = first_step / max(float(d.abs().max()), 1e-30)
            else:
                t0 = min(1.0, 1.0 / max(float(d.abs().sum()), 1e-30))
        else:
            t0 = 1.0
        point, n = strong_wolfe(fun, x, t0, d, f, g, gtd, f_tolerance=rel_tolerance)
        n_eval += n
        if point.t == 0.0:
            reason = "line_search"
            it -= 1
            break
        step = point.t * d
        y = point.g - g
        pg_new = apply_p(point.g)
        ys = float(y @ step)
        if ys > 1e-10 * float(step @ step) ** 0.5 * float(y @ y) ** 0.5:
            if len(s_hist) == history_size:
                s_hist.pop(0), y_hist.pop(0), py_hist.pop(0), rho_hist.pop(0)
            py = pg_new - pg
            s_hist.append(step)
            y_hist.append(y)
            py_hist.append(py)
            rho_hist.append(1.0 / ys)
            gamma = ys / max(float(y @ py), 1e-300)
        x = x + step
        decrease = f - point.f
        f_prev = f
        f, g, pg = point.f, point.g, pg_new
        gmax = float(g.abs().max())
        if on_iteration is not None:
            on_iteration(it, f, gmax, point.aux)
        if gmax <= grad_tolerance:
            reason = "gradient_norm"
            break
        if decrease <= rel_tolerance * max(abs(f_prev), abs(f), 1e-300):
            reason = "relative_decrease"
            break
    return LbfgsResult(x, f, it, n_eval, reason)
