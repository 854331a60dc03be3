"""SfM's poses held to the masks: a bundle adjustment with epipolar-tangency (frontier) residuals.

Two cameras i and j and their baseline span a pencil of planes. The outermost planes of the
pencil that touch the object are tangent to it at its *frontier points*, and they are seen as
the outermost epipolar lines that touch the silhouette in **both** views. So with right poses
the extreme epipolar planes through silhouette i equal those through silhouette j; with wrong
poses they differ. The residual is that difference, per pair and side, as an angle around the
baseline converted to pixels (``f * sin(angle between baseline and view) * dphi``).

SIFT tracks bend where the texture is poor: the built-in dragon's hue texture leaves 10% of its
tracks' observations more than 2 px from the true poses, and its SfM poses come out 1.1% of the
rig off with every track reprojecting within 0.45 px (README, Geometry). Its masks disagree with
those poses by 7.5 px RMS in these residuals (0.34 px with the true poses). The adjustment
minimizes, over the poses and the sparse points,

    E = sum_obs rho_cauchy(|reprojection|^2; 1 px) + w * sum_pairs huber(frontier residual; 3 px)

with the intrinsics held, by Levenberg-Marquardt on the robust costs' reweighted Gauss-Newton model,
the points eliminated by their Schur complement (Jacobians by PyTorch autograd). The extremes are
found over every contour point without gradients and differentiated at their contour points (the
envelope theorem: the derivative of a maximum is the derivative of its maximizer's value). Pairs whose
baseline passes near the object (an epipole inside or near a silhouette) have no frontier points
and are left out, as are extremes on the image border (a truncated silhouette).

Only views with a mask take part; the silhouettes must be the whole object's. Used by
:func:`pmvir.geometry.sfm.estimate_poses` after SfM (``sfm.frontier_weight``; 0 turns it off).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cv2
import numpy as np
import pycolmap
import torch

#: Cauchy scale of the track reprojection residuals (px), as COLMAP's robust adjustment in pmvir.
TRACK_SCALE_PX = 1.0
#: Huber scale of the frontier residuals (px): masks from a segmentation are off by a pixel or two.
FRONTIER_SCALE_PX = 3.0
#: A pair takes part when every contour point of both views lies within this angle (rad) of the
#: plane through the baseline and the sparse points' median, and the pencil the silhouette spans is
#: narrower than ``MAX_SPAN``: near the epipole (baseline through the object) the extremes are
#: undefined.
MAX_ANGLE = 1.5
MAX_SPAN = 2.5
#: The adjustment stops after a step that lowered the energy by less than this fraction of it (dragon,
#: 32 views from SfM: 17 iterations, the largest camera-centre error 0.31 % of the rig, against 0.30 %
#: after 30 iterations at 1e-6).
CONVERGED_FRACTION = 1e-5
#: Weight of the soft gauge (first view's pose, the centres' mean distance to their centroid).
GAUGE_WEIGHT = 1e4


@dataclass(frozen=True)
class FrontierReport:
    """What the adjustment did: views and pairs used, RMS frontier residual (px) and median track
    reprojection error (px) before and after, iterations, seconds, and whether it was kept."""

    views: int
    pairs: int
    frontier_rms_before: float
    frontier_rms_after: float
    track_median_before: float
    track_median_after: float
    iterations: int
    seconds: float
    accepted: bool

    def as_dict(self) -> dict[str, float | int | bool]:
        return dict(self.__dict__)


def frontier_adjust(
    rec: pycolmap.Reconstruction,
    masks: dict[str, np.ndarray],
    *,
    weight: float,
    iterations: int,
) -> FrontierReport | None:
    """Adjust ``rec``'s registered poses and points (in place) to their tracks and the masks.

    Args:
        rec: the SfM model; its intrinsics are held.
        masks: image name -> (H, W) bool silhouette of the whole object; views without one are
            left out of the frontier term (their tracks still count).
        weight: w above (> 0).
        iterations: most Levenberg-Marquardt iterations; it stops earlier once converged
            (``CONVERGED_FRACTION``).

    Returns:
        The report, or None when fewer than 3 masked views or no usable pair (nothing changed).
        The new poses are kept only when they fit the masks better and keep the tracks' median
        reprojection error within 1 px (``accepted``); otherwise ``rec`` is left as it was.
    """
    t0 = time.perf_counter()
    problem = _Problem.build(rec, masks)
    if problem is None:
        return None
    with torch.no_grad():
        before = problem.measure(problem.state0())
    if not problem.pairs:
        return None
    params, n_iter = _levenberg_marquardt(problem, weight, iterations)
    with torch.no_grad():
        state = problem.state(*problem.unscaled(*params))
        after = problem.measure(state)
    accepted = bool(after[0] < before[0] and after[1] <= max(1.0, before[1]))
    if accepted:
        problem.write_back(rec, state)
    return FrontierReport(
        views=problem.n_masked, pairs=len(problem.pairs),
        frontier_rms_before=before[0], frontier_rms_after=after[0],
        track_median_before=before[1], track_median_after=after[1],
        iterations=n_iter, seconds=time.perf_counter() - t0, accepted=accepted,
    )


def _levenberg_marquardt(
    problem: _Problem, weight: float, iterations: int
) -> tuple[tuple[torch.Tensor, torch.Tensor, torch.Tensor], int]:
    """The increments (w, dc, dx) in the optimizer's pixel units (:meth:`_Problem.unscaled`) that
    minimize :meth:`_Problem.energy`, and the iterations taken.

    Levenberg-Marquardt on the robust costs' iteratively reweighted Gauss-Newton model (Cauchy weights
    on the tracks, Huber on the frontier residuals, whose extremes are chosen anew each iteration),
    with the points eliminated by their Schur complement as in bundle adjustment: a 6 V x 6 V system
    per iteration. It stops after a step that lowered the energy by less than ``CONVERGED_FRACTION``
    of it, or when no damping lowers it."""
    n_view, n_point = len(problem.C0), len(problem.X0)
    dtype = torch.float64
    w = torch.zeros(n_view, 3, dtype=dtype)
    dc = torch.zeros(n_view, 3, dtype=dtype)
    dx = torch.zeros(n_point, 3, dtype=dtype)
    structure = _SchurStructure.of(problem)

    def energy(w: torch.Tensor, dc: torch.Tensor, dx: torch.Tensor) -> float:
        with torch.no_grad():
            return float(problem.energy(*problem.unscaled(w, dc, dx), weight=weight))

    current = energy(w, dc, dx)
    damping = 1e-4
    n_iter = 0
    for n_iter in range(1, iterations + 1):
        system = _normal_equations(problem, structure, weight, w, dc, dx)
        while True:
            step = system.solve(damping)
            if step is None:
                damping *= 4
            else:
                trial = (w + step[0], dc + step[1], dx + step[2])
                value = energy(*trial)
                if value < current:
                    break
                damping *= 4
            if damping > 1e8:  # no step lowers the energy: converged
                return (w, dc, dx), n_iter
        w, dc, dx = trial
        decrease, current = current - value, value
        damping = max(damping / 3, 1e-9)
        if decrease <= CONVERGED_FRACTION * current:
            break
    return (w, dc, dx), n_iter


@dataclass
class _SchurStructure:
    """Which observations share a point (every ordered pair of them, itself included): the point
    blocks' contributions to the reduced camera system."""

    first: torch.Tensor
    second: torch.Tensor

    @classmethod
    def of(cls, problem: _Problem) -> _SchurStructure:
        point = problem.obs_point.numpy()
        order = np.argsort(point, kind="stable")
        counts = np.bincount(point, minlength=len(problem.X0))
        starts = np.r_[0, np.cumsum(counts)[:-1]]
        k = counts[point[order]]  # each observation's track length, in point order
        first = np.repeat(order, k)
        offset = np.arange(len(first)) - np.repeat(np.cumsum(k) - k, k)
        second = order[np.repeat(starts[point[order]], k) + offset]
        return cls(torch.from_numpy(first), torch.from_numpy(second))


@dataclass
class _NormalEquations:
    """The Gauss-Newton system at one state: camera blocks U (6 V, 6 V), point blocks (P, 3, 3), the
    observations' camera-point blocks (N, 6, 3) and the gradients (6 V,), (P, 3)."""

    U: torch.Tensor
    Vp: torch.Tensor
    W: torch.Tensor
    g_cam: torch.Tensor
    g_point: torch.Tensor
    obs_view: torch.Tensor
    obs_point: torch.Tensor
    structure: _SchurStructure

    def solve(self, damping: float) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """The damped step (w, dc, dx), or None where the damped system is singular."""
        n_view, n_point = len(self.U) // 6, len(self.Vp)
        U = self.U + damping * torch.diag(torch.diagonal(self.U) + 1e-9)
        Vp = self.Vp + damping * torch.diag_embed(torch.diagonal(self.Vp, dim1=1, dim2=2) + 1e-9)
        Vinv, info = torch.linalg.inv_ex(Vp)
        if bool((info != 0).any()):
            return None
        Y = self.W @ Vinv[self.obs_point]  # (N, 6, 3)
        a, b = self.structure.first, self.structure.second
        blocks = Y[a] @ self.W[b].transpose(1, 2)  # (M, 6, 6)
        reduced = torch.zeros(n_view, n_view, 6, 6, dtype=U.dtype)
        reduced.index_put_((self.obs_view[a], self.obs_view[b]), blocks, accumulate=True)
        S = U - reduced.permute(0, 2, 1, 3).reshape(6 * n_view, 6 * n_view)
        rhs = -self.g_cam + torch.zeros(n_view, 6, dtype=U.dtype).index_add_(
            0, self.obs_view, (Y @ self.g_point[self.obs_point][:, :, None])[:, :, 0]
        ).reshape(-1)
        step, info = torch.linalg.solve_ex(S, rhs)
        if bool(info != 0) or not bool(torch.isfinite(step).all()):
            return None
        cam = step.reshape(n_view, 6)
        back = torch.zeros(n_point, 3, dtype=U.dtype).index_add_(
            0, self.obs_point, (self.W.transpose(1, 2) @ cam[self.obs_view][:, :, None])[:, :, 0]
        )
        point = (Vinv @ (-self.g_point - back)[:, :, None])[:, :, 0]
        return cam[:, :3], cam[:, 3:], point


def _normal_equations(
    problem: _Problem, structure: _SchurStructure, weight: float, w: torch.Tensor, dc: torch.Tensor, dx: torch.Tensor
) -> _NormalEquations:
    """The robust Gauss-Newton system of :meth:`_Problem.energy` at (w, dc, dx) (pixel units).

    Each residual depends on one or two cameras and at most one point, so its Jacobian comes from
    one backward pass per residual component through per-residual copies of those variables."""
    n_view, n_point = len(problem.C0), len(problem.X0)
    dtype = torch.float64
    v, p = problem.obs_view, problem.obs_point
    # tracks: (N, 2) residuals, Jacobians (N, 2, 6) camera and (N, 2, 3) point
    cw, cc, cx = (t.detach().clone().requires_grad_(True) for t in (w[v], dc[v], dx[p]))
    rw, rc, rx = problem.unscaled(cw, cc, cx)
    R = torch.einsum("nij,njk->nik", problem.R0[v], _rodrigues(rw))
    cam = torch.einsum("nij,nj->ni", R, problem.X0[p] + rx - problem.C0[v] - rc)
    img = torch.einsum("nij,nj->ni", problem.K[v], cam)
    e = img[:, :2] / img[:, 2:] - problem.obs_xy
    rows = [torch.autograd.grad(e[:, k].sum(), (cw, cc, cx), retain_graph=k == 0) for k in range(2)]
    Jc = torch.stack([torch.cat(r[:2], dim=1) for r in rows], dim=1)  # (N, 2, 6)
    Jp = torch.stack([r[2] for r in rows], dim=1)  # (N, 2, 3)
    e = e.detach()
    s2 = TRACK_SCALE_PX**2
    rho = 1.0 / (1.0 + (e * e).sum(-1) / s2)  # the Cauchy loss's weight
    U = torch.zeros(n_view, n_view, 6, 6, dtype=dtype)
    blocks = torch.einsum("n,nki,nkj->nij", rho, Jc, Jc)
    U.index_put_((v, v), blocks, accumulate=True)
    Vp = torch.zeros(n_point, 3, 3, dtype=dtype).index_add_(0, p, torch.einsum("n,nki,nkj->nij", rho, Jp, Jp))
    Wb = torch.einsum("n,nki,nkj->nij", rho, Jc, Jp)
    g_cam = torch.zeros(n_view, 6, dtype=dtype).index_add_(0, v, torch.einsum("n,nki,nk->ni", rho, Jc, e))
    g_point = torch.zeros(n_point, 3, dtype=dtype).index_add_(0, p, torch.einsum("n,nki,nk->ni", rho, Jp, e))
    # frontier: (P, 2) residuals, Jacobians (P, 2, 12) over both cameras of each pair
    pair = problem._pair
    with torch.no_grad():
        R_now, C_now, _ = problem.state(*problem.unscaled(w, dc, dx))
    sel, on_border = problem.extremes(R_now, C_now)
    pw, pc = w[pair].detach().clone().requires_grad_(True), dc[pair].detach().clone().requires_grad_(True)
    qw, qc, _ = problem.unscaled(pw, pc, dx[:0])
    Rp = torch.einsum("psij,psjk->psik", problem.R0[pair], _rodrigues(qw.reshape(-1, 3)).reshape(-1, 2, 3, 3))
    Cp = problem.C0[pair] + qc
    valid = (~on_border).to(dtype) * problem.pair_scale[:, None]
    f = _pencil_differences(
        Rp[:, :, None].expand(-1, -1, 2, -1, -1), Cp[:, 0], Cp[:, 1], problem.centre, problem._all_rays[sel]
    ) * valid
    rows = [torch.autograd.grad(f[:, k].sum(), (pw, pc), retain_graph=k == 0) for k in range(2)]
    Jf = torch.stack([torch.cat([r[0], r[1]], dim=2) for r in rows], dim=1)  # (P, 2, side, 6)
    f = f.detach()
    huber = weight * torch.clamp(FRONTIER_SCALE_PX / f.abs().clamp_min(1e-12), max=1.0)  # the Huber loss's weight
    for a in range(2):
        for b in range(2):
            U.index_put_((pair[:, a], pair[:, b]), torch.einsum("pk,pki,pkj->pij", huber, Jf[:, :, a], Jf[:, :, b]),
                         accumulate=True)
        g_cam.index_add_(0, pair[:, a], torch.einsum("pk,pki,pk->pi", huber, Jf[:, :, a], f))
    U = U.permute(0, 2, 1, 3).reshape(6 * n_view, 6 * n_view)
    g_cam = g_cam.reshape(-1)
    # the soft gauge: GAUGE_WEIGHT * |g|^2 with g = (dc_0, w_0, spread - spread0), unscaled
    x_cam = torch.cat([w, dc], dim=1).detach().clone().requires_grad_(True)
    gw, gc, _ = problem.unscaled(x_cam[:, :3], x_cam[:, 3:], dx[:0])
    C = problem.C0 + gc
    g = torch.cat([gc[0], gw[0], ((C - C.mean(0)).norm(dim=-1).mean() - problem.spread0)[None]])
    Jg = torch.stack([torch.autograd.grad(g[k], x_cam, retain_graph=k < len(g) - 1)[0].reshape(-1) for k in range(len(g))])
    U = U + GAUGE_WEIGHT * Jg.T @ Jg
    g_cam = g_cam + GAUGE_WEIGHT * Jg.T @ g.detach()
    return _NormalEquations(U, Vp, Wb, g_cam, g_point, v, p, structure)


def _rodrigues(w: torch.Tensor) -> torch.Tensor:
    """(V, 3) axis-angle -> (V, 3, 3) rotations (exact at 0)."""
    theta2 = (w * w).sum(-1)[:, None, None]
    kx = torch.zeros(w.shape[0], 3, 3, dtype=w.dtype)
    kx[:, 0, 1], kx[:, 0, 2], kx[:, 1, 2] = -w[:, 2], w[:, 1], -w[:, 0]
    kx = kx - kx.transpose(1, 2)
    theta = torch.sqrt(theta2 + 1e-30)
    small = theta2 < 1e-12
    a = torch.where(small, 1 - theta2 / 6, torch.sin(theta) / theta)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(theta)) / (theta2 + 1e-30))
    return torch.eye(3, dtype=w.dtype) + a * kx + b * kx @ kx


def _pencils(Ci: torch.Tensor, Cj: torch.Tensor, centre: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The pencils' frames of camera pairs (..., 3): baseline direction b, a1 normal to it toward the
    centre, a2 = b x a1."""
    b = Cj - Ci
    b = b / b.norm(dim=-1, keepdim=True)
    a1 = centre - Ci
    a1 = a1 - (a1 * b).sum(-1, keepdim=True) * b
    a1 = a1 / a1.norm(dim=-1, keepdim=True)
    return b, a1, torch.linalg.cross(b, a1, dim=-1)


def _pencil_differences(
    R: torch.Tensor, Ci: torch.Tensor, Cj: torch.Tensor, centre: torch.Tensor, rays: torch.Tensor
) -> torch.Tensor:
    """(..., hi/lo) radians: the angle about the baseline of side i's extreme ray less side j's.
    R (..., side, hi/lo, 3, 3) world -> camera, rays (..., side, hi/lo, 3) camera frame."""
    _, a1, a2 = _pencils(Ci, Cj, centre)
    d = torch.einsum("...ji,...j->...i", R, rays)  # R^T r
    phi = torch.atan2((d * a2[..., None, None, :]).sum(-1), (d * a1[..., None, None, :]).sum(-1))
    return phi[..., 0, :] - phi[..., 1, :]


def _contour_rays(mask: np.ndarray, K: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit camera-frame rays (M, 3) through the vertices of the convex hull of ``mask``'s contour
    pixels and (M,) whether each lies on the image border (a truncated silhouette)."""
    contours, _ = cv2.findContours(mask.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
    if not contours:
        return np.zeros((0, 3)), np.zeros(0, dtype=bool)
    # The outermost tangent lines from a point outside a silhouette touch its convex hull: its
    # vertices are the only candidates for the extremes (tens of points instead of thousands).
    px = cv2.convexHull(np.concatenate([c.reshape(-1, 2) for c in contours])).reshape(-1, 2).astype(np.float64)
    h, w = mask.shape
    border = (px[:, 0] <= 0) | (px[:, 1] <= 0) | (px[:, 0] >= w - 1) | (px[:, 1] >= h - 1)
    rays = np.linalg.solve(K, np.c_[px + 0.5, np.ones(len(px))].T).T
    return rays / np.linalg.norm(rays, axis=1, keepdims=True), border


@dataclass
class _Problem:
    """The adjustment's data as tensors (float64): poses, points, observations, contour rays, pairs."""

    image_ids: list[int]
    K: torch.Tensor  # (V, 3, 3)
    R0: torch.Tensor  # (V, 3, 3) world -> camera
    C0: torch.Tensor  # (V, 3) centres
    point_ids: list[int]
    X0: torch.Tensor  # (P, 3)
    obs_view: torch.Tensor
    obs_point: torch.Tensor
    obs_xy: torch.Tensor
    rays: list[torch.Tensor | None]  # per view (M, 3) camera-frame contour rays, or None (no mask)
    border: list[torch.Tensor | None]
    pairs: list[tuple[int, int]]
    pair_scale: torch.Tensor  # (pairs,) px per radian
    centre: torch.Tensor  # (3,) the sparse points' median
    spread0: torch.Tensor
    n_masked: int

    @classmethod
    def build(cls, rec: pycolmap.Reconstruction, masks: dict[str, np.ndarray]) -> _Problem | None:
        image_ids = sorted(rec.reg_image_ids(), key=lambda i: rec.images[i].name)
        if rec.num_points3D() == 0 or sum(rec.images[i].name in masks for i in image_ids) < 3:
            return None
        index = {iid: k for k, iid in enumerate(image_ids)}
        Ks = np.stack([rec.cameras[rec.images[i].camera_id].calibration_matrix() for i in image_ids])
        poses = [rec.images[i].cam_from_world() for i in image_ids]
        R0 = np.stack([p.rotation.matrix() for p in poses])
        C0 = np.stack([rec.images[i].projection_center() for i in image_ids])
        point_ids = sorted(rec.points3D.keys())
        X0 = np.stack([rec.points3D[p].xyz for p in point_ids])
        ov, op, oxy = [], [], []
        for k, pid in enumerate(point_ids):
            for el in rec.points3D[pid].track.elements:
                ov.append(index[el.image_id])
                op.append(k)
                oxy.append(rec.images[el.image_id].points2D[el.point2D_idx].xy)
        rays: list[torch.Tensor | None] = []
        border: list[torch.Tensor | None] = []
        for k, iid in enumerate(image_ids):
            mask = masks.get(rec.images[iid].name)
            if mask is None or not mask.any():
                rays.append(None)
                border.append(None)
                continue
            r, b = _contour_rays(mask, Ks[k])
            rays.append(torch.from_numpy(r))
            border.append(torch.from_numpy(b))
        C0t = torch.from_numpy(C0)
        problem = cls(
            image_ids=image_ids, K=torch.from_numpy(Ks), R0=torch.from_numpy(R0), C0=C0t,
            point_ids=point_ids, X0=torch.from_numpy(X0),
            obs_view=torch.tensor(ov, dtype=torch.long), obs_point=torch.tensor(op, dtype=torch.long),
            obs_xy=torch.from_numpy(np.asarray(oxy, dtype=np.float64).reshape(-1, 2)),
            rays=rays, border=border, pairs=[], pair_scale=torch.zeros(0, dtype=torch.float64),
            centre=torch.from_numpy(np.median(X0, axis=0)),
            spread0=(C0t - C0t.mean(0)).norm(dim=-1).mean(),
            n_masked=sum(r is not None for r in rays),
        )
        problem._select_pairs()
        return problem

    def unscaled(
        self, w: torch.Tensor, dc: torch.Tensor, dx: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The increments from the optimizer's variables, which are in pixels: a unit step of each
        moves an image point about a pixel (rotations by 1/f, positions by depth/f): the damping of
        Levenberg-Marquardt, proportional to the diagonal, treats them alike."""
        f = self.K[:, 0, 0].mean()
        unit = (self.centre - self.C0).norm(dim=-1).median() / f
        return w / f, dc * unit, dx * unit

    def state0(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        return self.R0, self.C0, self.X0

    def state(
        self, w: torch.Tensor, dc: torch.Tensor, dx: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(R, C, X) at the increments: R = R0 exp(w), C = C0 + dc, X = X0 + dx."""
        return torch.einsum("vij,vjk->vik", self.R0, _rodrigues(w)), self.C0 + dc, self.X0 + dx

    def _angles(self, R: torch.Tensor, k: int, a1: torch.Tensor, a2: torch.Tensor) -> torch.Tensor:
        rays = self.rays[k]
        assert rays is not None
        d = rays @ R[k]  # world directions R^T r
        return torch.atan2(d @ a2, d @ a1)

    def _select_pairs(self) -> None:
        pairs, scales = [], []
        masked = [k for k, r in enumerate(self.rays) if r is not None]
        for a, i in enumerate(masked):
            for j in masked[a + 1:]:
                b, a1, a2 = _pencils(self.C0[i], self.C0[j], self.centre)
                spans = [self._angles(self.R0, k, a1, a2) for k in (i, j)]
                if all(s.abs().max() < MAX_ANGLE and (s.max() - s.min()) < MAX_SPAN for s in spans):
                    to_centre = self.centre - self.C0[i]
                    sin = (to_centre - (to_centre @ b) * b).norm() / to_centre.norm()
                    pairs.append((i, j))
                    scales.append(float(self.K[i, 0, 0] * sin))
        self.pairs = pairs
        self.pair_scale = torch.tensor(scales, dtype=torch.float64)
        sizes = [0 if r is None else len(r) for r in self.rays]
        offsets = np.r_[0, np.cumsum(sizes)]
        self._all_rays = torch.cat([r for r in self.rays if r is not None])
        self._all_border = torch.cat([b for b in self.border if b is not None])
        # every view's rays as flat indices padded to the longest with its first (a repeated ray
        # leaves the extremes as they are): the extremes of all pairs and sides in one search
        width = max(sizes)
        self._padded = torch.from_numpy(np.stack([
            offsets[k] + np.minimum(np.arange(width), max(sizes[k] - 1, 0)) for k in range(len(sizes))
        ]))
        self._pair = torch.tensor(pairs, dtype=torch.long).reshape(-1, 2)  # (P, 2): i, j

    def extremes(self, R: torch.Tensor, C: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Per pair, side and high/low extreme the flat index of its contour ray (P, 2, 2), found over
        every contour point without gradients; and (P, 2) whether a high/low extreme lies on the border."""
        with torch.no_grad():
            R, C = R.detach(), C.detach()
            _, a1, a2 = _pencils(C[self._pair[:, 0]], C[self._pair[:, 1]], self.centre)
            candidates = self._padded[self._pair]  # (P, side, M) flat ray indices
            d = torch.einsum("psmj,psji->psmi", self._all_rays[candidates], R[self._pair])  # R^T r
            phi = torch.atan2(torch.einsum("psmi,pi->psm", d, a2), torch.einsum("psmi,pi->psm", d, a1))
            sel = torch.stack([
                candidates.gather(2, phi.argmax(dim=2, keepdim=True))[..., 0],
                candidates.gather(2, phi.argmin(dim=2, keepdim=True))[..., 0],
            ], dim=2)  # (P, side, hi/lo)
        return sel, self._all_border[sel].any(dim=1)

    def frontier_residuals(self, R: torch.Tensor, C: torch.Tensor) -> torch.Tensor:
        """(pairs, 2) px: the max and min angle differences; 0 where an extreme lies on the border."""
        sel, on_border = self.extremes(R, C)
        view = self._pair[:, :, None].expand(-1, -1, 2)
        diff = _pencil_differences(R[view], C[self._pair[:, 0]], C[self._pair[:, 1]], self.centre, self._all_rays[sel])
        return torch.where(on_border, torch.zeros_like(diff), diff) * self.pair_scale[:, None]

    def reprojection(self, R: torch.Tensor, C: torch.Tensor, X: torch.Tensor) -> torch.Tensor:
        """(obs,) px."""
        v = self.obs_view
        cam = torch.einsum("nij,nj->ni", R[v], X[self.obs_point] - C[v])
        img = torch.einsum("nij,nj->ni", self.K[v], cam)
        return (img[:, :2] / img[:, 2:] - self.obs_xy).norm(dim=-1)

    def energy(self, w: torch.Tensor, dc: torch.Tensor, dx: torch.Tensor, *, weight: float) -> torch.Tensor:
        R, C, X = self.state(w, dc, dx)
        r2 = self.reprojection(R, C, X) ** 2
        tracks = (TRACK_SCALE_PX**2 * torch.log1p(r2 / TRACK_SCALE_PX**2)).sum()
        f = self.frontier_residuals(R, C).abs()
        s = FRONTIER_SCALE_PX
        frontier = torch.where(f <= s, f * f, 2 * s * f - s * s).sum()
        gauge = GAUGE_WEIGHT * (
            (dc[0] ** 2).sum() + (w[0] ** 2).sum() + ((C - C.mean(0)).norm(dim=-1).mean() - self.spread0) ** 2
        )
        return tracks + weight * frontier + gauge

    def measure(self, state: tuple[torch.Tensor, torch.Tensor, torch.Tensor]) -> tuple[float, float]:
        """(RMS frontier residual, median track reprojection error), px."""
        R, C, X = state
        f = self.frontier_residuals(R, C) if self.pairs else torch.zeros(1, 2, dtype=torch.float64)
        return float(f.pow(2).mean().sqrt()), float(self.reprojection(R, C, X).median())

    def write_back(self, rec: pycolmap.Reconstruction, state: tuple[torch.Tensor, torch.Tensor, torch.Tensor]) -> None:
        R, C, X = (t.detach().numpy().astype(np.float64) for t in state)
        for k, iid in enumerate(self.image_ids):
            image = rec.images[iid]
            pose = pycolmap.Rigid3d(pycolmap.Rotation3d(R[k]), -R[k] @ C[k])
            rec.frames[image.frame_id].rig_from_world = pose
        for k, pid in enumerate(self.point_ids):
            rec.points3D[pid].xyz = X[k]


