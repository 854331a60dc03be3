"""Coarse to fine: the first stages on a coarser surface, their motion then carried to the subdivided one.

With ``refine.stages.coarse`` = k > 0 the refinement runs its first k stages on
the surface one sqrt(3) step before the last (a third of the faces), where an
evaluation costs about a third, and the later stages on the subdivided surface.
The vertices of the subdivided surface lie on the coarse one's faces or within a
chord's sagitta of them, so each is tied to the closest point of the coarse
surface at the start (:meth:`Lift.between`: its face, barycentric weights and the
small offset from that point) and follows that face's corners
(:meth:`Lift.apply`): the coarse stages' motion, interpolated linearly over each
face, the albedo likewise. The lighting is per view and carries over as it is.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from pmvir.errors import ConfigError
from pmvir.geometry.mesh_ops import ReferenceSurface


@dataclass(frozen=True)
class CoarseMesh:
    """The surface the coarse stages run on.

    Attributes:
        vertices: (M, 3) float64 positions.
        faces: (G, 3) int64, counter-clockwise seen from outside.
        visibility: (M, V) bool per-vertex visibility in the refinement's views.
    """

    vertices: np.ndarray
    faces: np.ndarray
    visibility: np.ndarray

    def check(self, n_views: int) -> None:
        """Raises ConfigError where the arrays disagree with each other or with the ``n_views`` views."""
        m = len(self.vertices)
        if self.vertices.shape != (m, 3) or self.faces.ndim != 2 or self.faces.shape[1] != 3:
            raise ConfigError(f"coarse mesh: expected (M, 3) vertices and (G, 3) faces, got "
                              f"{self.vertices.shape} and {self.faces.shape}")
        if self.visibility.shape != (m, n_views):
            raise ConfigError(f"coarse mesh: expected ({m}, {n_views}) visibility, got {self.visibility.shape}")


@dataclass(frozen=True)
class Lift:
    """Each fine vertex as a point of a coarse face: corners, barycentric weights and the offset off it.

    Attributes:
        corners: (N, 3) int64 coarse vertex indices of the face each fine vertex is tied to.
        weights: (N, 3) float64 barycentric weights (>= 0, summing to 1).
        offsets: (N, 3) float64 fine position minus the weighted coarse corners, at the start.
    """

    corners: np.ndarray
    weights: np.ndarray
    offsets: np.ndarray

    @classmethod
    def between(cls, coarse_vertices: np.ndarray, coarse_faces: np.ndarray, fine_vertices: np.ndarray) -> Lift:
        """Tie every fine vertex to the closest point of the coarse surface (both at their start positions)."""
        surface = ReferenceSurface(coarse_vertices, coarse_faces)
        fine = np.asarray(fine_vertices, dtype=np.float64)
        closest, face_ids = surface.project(fine)
        corners = surface.faces[face_ids]
        weights = barycentric(closest, *(surface.vertices[corners[:, i]] for i in range(3)))
        at = np.einsum("nk,nkd->nd", weights, surface.vertices[corners])
        return cls(corners=corners, weights=weights, offsets=fine - at)

    def apply(self, coarse: torch.Tensor, *, offsets: bool) -> torch.Tensor:
        """(N, C) values at the fine vertices from (M, C) values at the coarse ones; ``offsets`` adds
        the start offsets (for positions, not for albedo)."""
        idx = torch.from_numpy(self.corners).to(coarse.device)
        w = torch.from_numpy(self.weights).to(device=coarse.device, dtype=coarse.dtype)
        out = (coarse[idx] * w[:, :, None]).sum(dim=1)
        if offsets:
            out = out + torch.from_numpy(self.offsets).to(device=coarse.device, dtype=coarse.dtype)
        return out


def barycentric(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(N, 3) barycentric weights of points ``p`` on triangles ``(a, b, c)``, clipped to the triangle
    (>= 0, sum 1); a degenerate triangle gives its centroid's weights."""
    e0, e1, d = b - a, c - a, p - a
    d00, d01, d11 = (e0 * e0).sum(1), (e0 * e1).sum(1), (e1 * e1).sum(1)
    d20, d21 = (d * e0).sum(1), (d * e1).sum(1)
    den = d00 * d11 - d01 * d01
    ok = den > 1e-30 * np.maximum(d00 * d11, 1e-300)
    safe = np.where(ok, den, 1.0)
    v = np.where(ok, (d11 * d20 - d01 * d21) / safe, 1.0 / 3.0)
    w = np.where(ok, (d00 * d21 - d01 * d20) / safe, 1.0 / 3.0)
    out = np.clip(np.stack([1.0 - v - w, v, w], axis=1), 0.0, None)
    return out / out.sum(axis=1, keepdims=True)
