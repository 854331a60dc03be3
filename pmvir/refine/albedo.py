"""The albedo that minimizes the cost for given geometry and lighting (variable projection).

For fixed vertices X and lighting L, E_pho + tau3 E_psm is quadratic in the
albedo K, channel by channel; without bounds its minimizer solves the sparse
symmetric positive-definite system

    (D + 2 tau3 L_w) K = b,   D_i = sum_{c in V(i)} a_ic^2 / |V(i)|,   b_i = sum_c a_ic I_ic / |V(i)|

with ``a_ic = S(N_i, L_c) L_scale,c`` (per channel) and ``L_w`` the graph Laplacian
weighted by the E_psm weights w_ij. E_pol and E_gsm do not involve K. An albedo
is a reflectance, so K* is the minimizer over K >= 0: where the SH shading of a
vertex is negative (the order-2 expansion can be, facing away from the light)
the unbounded K* is negative, down to several units on a few vertices. The
bounded problem is solved by active sets: entries below zero are held at zero,
the system is solved again over the others (the matrix is an M-matrix, so the
free entries only grow), and held entries whose gradient points into K > 0 are
released, until the set settles. Optimizing the reduced cost E(X, L, K*(X, L))
over X and L has the same minimizers as the joint problem, and by the envelope
(Danskin's) theorem its gradient is the partial gradient at K = K*, so K* is
never differentiated.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from pmvir.refine.mesh_ops import adjacency_csr
from pmvir.refine.sampling import PairSet


class AlbedoSolver:
    """Solves for K*(X, L) >= 0 by Jacobi-preconditioned conjugate gradients inside active sets,
    warm-started, in the dtype of ``initial`` (the refinement's float32).

    Args:
        pairs: the stage's pairs.
        edges: (E, 2) int64 undirected edges (NumPy).
        psm_weight: (E,) E_psm weights w_ij (NumPy).
        tau_psm: tau3.
        initial: (N, 3) starting albedo (tensor); also the anchor of a tiny ridge that keeps
            vertices without observations and without observed neighbours determined.
        tol: relative residual at which CG stops; max_iter: most CG iterations.
        ridge: the ridge relative to the mean diagonal.
        pair_weight: (P,) E_pho's per-pair factor on 1/|V(i)| (``StageProblem.pho_weight``); None: 1.
        max_rounds: most active-set rounds (each one CG solve over the entries not held at zero).

    Attributes:
        current: (N, 3) the last solution, in the dtype of ``initial``.
        iterations: CG iterations of the last solve, all rounds together.
        held: entries (vertex, channel) of the last solution held at zero.
        held_rounds: active-set rounds of the last solve.
    """

    def __init__(
        self,
        pairs: PairSet,
        edges: np.ndarray,
        psm_weight: np.ndarray,
        tau_psm: float,
        initial: torch.Tensor,
        *,
        tol: float = 1e-5,
        max_iter: int = 500,
        ridge: float = 1e-6,
        pair_weight: torch.Tensor | None = None,
        max_rounds: int = 8,
    ):
        n = initial.shape[0]
        device = initial.device
        self.pairs, self.tau, self.tol, self.max_iter, self.ridge = (
            pairs,
            float(tau_psm),
            tol,
            max_iter,
            ridge,
        )
        self.dtype = initial.dtype
        self.current = initial.detach().clone()
        self._x = initial.detach().clone()
        w = np.asarray(psm_weight, dtype=np.float64)
        self.degree = torch.from_numpy(np.bincount(edges[:, 0], w, n) + np.bincount(edges[:, 1], w, n)).to(
            device=device, dtype=self.dtype
        )[:, None]
        # 2 tau3 W: the off-diagonal part of the system's matrix, scaled once.
        self.adjacency = adjacency_csr(edges, 2.0 * self.tau * w, n, device=device, dtype=self.dtype)
        self.max_rounds = max_rounds
        self.iterations = self.held = self.held_rounds = 0
        w_pair = pairs.weight if pair_weight is None else pairs.weight * pair_weight
        self._pair_weight = w_pair.detach().to(self.dtype)[:, None]

    def __call__(self, observed: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        """K* for the pairs' observed colours (P, 3) and lights (P, 3); returns (N, 3), no gradient."""
        with torch.no_grad():
            pv = self.pairs.vertex
            wgt = self._pair_weight
            a = light.to(self.dtype)
            diag = torch.zeros_like(self._x).index_add_(0, pv, wgt * a * a)
            rhs = torch.zeros_like(self._x).index_add_(0, pv, wgt * a * observed.to(self.dtype))
            mean_diag = float(diag.mean())
            mean_diag = mean_diag if mean_diag > 0 else 1.0
            ridge = self.ridge * mean_diag
            rhs = rhs + ridge * self._x
            # The system's diagonal D + 2 tau3 deg (also the Jacobi preconditioner's inverse).
            diagonal = diag + ridge + (2.0 * self.tau) * self.degree
            coupled = self.tau != 0.0

            def matvec(x: torch.Tensor) -> torch.Tensor:
                ax = diagonal * x
                return ax.sub_(self.adjacency @ x) if coupled else ax

            x, it = self._cg(matvec, rhs, self._x.clone(), 1.0 / diagonal)
            held = torch.zeros_like(x, dtype=torch.bool)
            self.held_rounds = 0
            slack = self.tol * rhs.abs().mean(0)  # a gradient this small is rounding, not a pull
            for _ in range(self.max_rounds):
                # KKT at the bound: a held entry stays where the cost's gradient there is >= 0
                release = held & ((matvec(x) - rhs) < -slack) if bool(held.any()) else held
                new_held = (held & ~release) | (x < 0)
                if bool((new_held == held).all()):
                    break
                held = new_held
                free = (~held).to(x.dtype)
                x = x * free

                def bounded(p: torch.Tensor, free: torch.Tensor = free) -> torch.Tensor:
                    return matvec(p * free).mul_(free).add_(p * (1.0 - free))

                x, more = self._cg(bounded, rhs * free, x, free / diagonal + (1.0 - free))
                it += more
                self.held_rounds += 1
            x = x.clamp_min_(0.0)  # rounding in the last solve
            self.held = int(held.sum())
            self.iterations = it
            self._x = x
            self.current = x
            return self.current

    def _cg(
        self,
        matvec: Callable[[torch.Tensor], torch.Tensor],
        rhs: torch.Tensor,
        x: torch.Tensor,
        precond: torch.Tensor,
    ) -> tuple[torch.Tensor, int]:
        """Jacobi-preconditioned conjugate gradients for ``matvec(x) = rhs``, column by column, from ``x``
        (updated in place) to the relative residual ``tol``; returns x and the iterations made."""
        tiny = torch.finfo(self.dtype).tiny
        r = rhs - matvec(x)
        rhs_norm = rhs.norm(dim=0).clamp_min(tiny)
        z = precond * r
        p = z.clone()
        rz = (r * z).sum(0)
        it = 0
        for it in range(1, self.max_iter + 1):
            if bool(((r.norm(dim=0) / rhs_norm) <= self.tol).all()):
                it -= 1
                break
            ap = matvec(p)
            alpha = rz / (p * ap).sum(0).clamp_min(tiny)
            x.addcmul_(p, alpha)
            r.addcmul_(ap, alpha, value=-1.0)
            torch.mul(precond, r, out=z)
            rz_new = (r * z).sum(0)
            p = p.mul_(rz_new / rz.clamp_min(tiny)).add_(z)
            rz = rz_new
        return x, it
