"""The initial surface: screened Poisson reconstruction of the dense points, trimmed and cleaned.

:func:`initial_surface` runs, in order:

1. **Screened Poisson** (Kazhdan and Hoppe 2013, Open3D's implementation) on the
   oriented dense points, octree depth ``poisson_depth``.
2. **Trimming to the observed surface**: vertices whose Poisson density (the
   octree's sample density) is below the ``trim_density_quantile`` quantile,
   or farther than ``trim_distance`` (a fraction of the points' bounding-box
   diagonal) from every dense point, are removed (Poisson closes the surface
   where nothing was observed; small holes stay filled, large guesses go).
   With masks, vertices that project inside a view's image but outside its
   (slightly dilated) mask are removed too: they are off the object's silhouette.
3. **Simplification** to at most ``target_faces`` triangles (quadric decimation).
4. **Cleaning** (:func:`pmvir.geometry.surface.clean.clean_mesh`): a single
   edge- and vertex-manifold, consistently oriented component whose slivers
   (smallest angle below ``min_angle_deg``) are repaired by edge flips and
   link-checked edge collapses; faces are then oriented outward
   (counter-clockwise seen from outside, checked against the point normals).
5. **Evening out** (:func:`pmvir.geometry.surface.clean.split_large_faces`,
   optional): faces whose projected
   area exceeds ``max_area_px`` in a view they face are bisected (conforming
   longest-edge bisection). Quadric decimation leaves large triangles on flat
   parts; the uniform sqrt(3) subdivision that follows repeats until the
   *largest* visible triangle is small enough, so evening sizes out first saves
   whole subdivision steps (measured on the bunny: one step and 235k vertices
   instead of two steps and 669k vertices, same accuracy).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from pmvir.camera import Camera
from pmvir.config import SurfaceOptions
from pmvir.errors import ReconstructionError
from pmvir.geometry.mesh_ops import edge_topology
from pmvir.geometry.projection import project_points
from pmvir.geometry.surface.clean import clean_mesh, mesh_arrays, o3d_mesh, orient_outward, split_large_faces

_EPS = 1e-12

#: Poisson vertices are trimmed beyond the larger of ``trim_distance`` and this many typical point
#: spacings (the median distance to a point's 4th nearest neighbour) from every dense point.
_TRIM_SPACINGS = 2.5
#: The silhouette trimming dilates the masks by this many pixels (a vertex on the outline projects up
#: to a pixel or so outside a mask cut to the pixel grid).
SILHOUETTE_PX = 2


@dataclass(frozen=True)
class SurfaceResult:
    """The initial surface and what each step did.

    Attributes:
        vertices: (N, 3) float64.
        faces: (F, 3) int64, counter-clockwise seen from outside.
        counts: the dense point count, vertices / faces after each step (``poisson_*``,
            ``trimmed_*``, ``simplified_*``, ``clean_*``, ``split_*``), the number of collapsed
            slivers and of boundary edges at the end.
        components: per connected component of the cleaned surface (largest first), its faces,
            the fused points nearest to it, whether it was kept and why.
    """

    vertices: np.ndarray
    faces: np.ndarray
    counts: dict[str, int] = field(default_factory=dict)
    components: list[dict[str, object]] = field(default_factory=list)


def poisson_surface(
    points: np.ndarray, normals: np.ndarray, *, depth: int = 8, point_weight: float = 4.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Screened Poisson surface of an oriented point cloud.

    Args:
        points: (P, 3) float positions. normals: (P, 3) unit outward normals.
        depth: octree depth (grid at most 2^depth per side of the bounding cube).
        point_weight: screening weight (interpolation strength of the points).

    Returns:
        vertices (N, 3) float64, faces (F, 3) int64, density (N,) float64 (octree sample density).

    One thread: Open3D's multi-threaded Poisson sums in thread order, so the same points gave
    surfaces that differ in the last digits and, after trimming, by dozens of vertices from run
    to run (about 1.4x slower on 2 cores; the same capture must give the same mesh).
    """
    import open3d as o3d

    pts = np.asarray(points, np.float64)
    centre = pts.mean(0) if len(pts) else np.zeros(3)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts - centre))
    pcd.normals = o3d.utility.Vector3dVector(np.asarray(normals, np.float64))
    mesh, density = o3d.geometry.TriangleMesh.create_from_point_cloud_poisson(
        pcd, depth=depth, point_weight=point_weight, n_threads=1
    )
    v, f = mesh_arrays(mesh)
    return v + centre, f, np.asarray(density, np.float64)


def auto_poisson_depth(
    points: np.ndarray, cameras: Sequence[Camera], *, voxel_px: float = 3.0, lo: int = 6, hi: int = 10
) -> int:
    """Octree depth whose finest cell spans about ``voxel_px`` pixels.

    The Poisson cube is 1.1 times the points' largest bounding-box side; a pixel spans
    (median depth of the points) / (focal length) world units, the median over the views.

    Returns:
        ``round(log2(cube / (voxel_px * pixel)))`` clamped to [lo, hi].
    """
    pts = np.asarray(points, np.float64)
    cube = 1.1 * float((pts.max(0) - pts.min(0)).max())
    spans = []
    for cam in cameras:
        _, z = project_points(cam, pts)
        z = z[z > 0]
        if len(z):
            spans.append(float(np.median(z)) / float(np.sqrt(cam.K[0, 0] * cam.K[1, 1])))
    if not spans or cube <= 0:
        return hi
    depth = round(float(np.log2(cube / (voxel_px * float(np.median(spans))))))
    return int(min(max(depth, lo), hi))


def off_silhouette(
    vertices: np.ndarray,
    cameras: Sequence[Camera],
    masks: Sequence[np.ndarray | None],
    *,
    dilate_px: int = SILHOUETTE_PX,
    outside_share: float = 0.0,
) -> np.ndarray:
    """(N,) bool: the vertex projects outside the masks (dilated by ``dilate_px``) of more than
    ``floor(outside_share * n)`` of the ``n`` views whose image it projects into (0: of any)."""
    v = np.asarray(vertices, np.float64)
    outside = np.zeros(len(v), np.int64)
    seeing = np.zeros(len(v), np.int64)
    kernel = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
    for cam, mask in zip(cameras, masks, strict=True):
        if mask is None:
            continue
        m = cv2.dilate(np.asarray(mask, np.uint8), kernel) > 0
        uv, z = project_points(cam, v)
        c, r = np.floor(uv[:, 0]).astype(np.int64), np.floor(uv[:, 1]).astype(np.int64)
        inside = (z > 0) & (c >= 0) & (c < cam.width) & (r >= 0) & (r < cam.height)
        seeing += inside
        outside[inside] += ~m[r[inside], c[inside]]
    return np.asarray(outside > np.floor(outside_share * seeing))


def _keep_vertices(
    vertices: np.ndarray, faces: np.ndarray, keep: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Drop vertices not in ``keep`` with their faces, and unreferenced vertices; reindex."""
    f = faces[keep[faces].all(1)]
    used = np.zeros(len(vertices), bool)
    used[f.ravel()] = True
    index = np.cumsum(used) - 1
    return vertices[used], index[f]


def initial_surface(
    points: np.ndarray,
    normals: np.ndarray,
    *,
    cameras: Sequence[Camera] | None = None,
    masks: Sequence[np.ndarray | None] | None = None,
    options: SurfaceOptions | None = None,
    max_area_px: float | None = None,
    mask_slack_px: int = 0,
    mask_outside_share: float = 0.0,
) -> SurfaceResult:
    """Screened Poisson, trimming, simplification and cleaning (module docstring).

    Args:
        points: (P, 3) float dense points. normals: (P, 3) unit normals facing the cameras.
        cameras, masks: views and their object masks, for silhouette trimming (optional).
        options: the ``geometry.surface`` group (default ``SurfaceOptions()``): ``poisson_depth``
            (None: :func:`auto_poisson_depth` with ``poisson_voxel_px``; needs ``cameras``, else 8),
            ``trim_density_quantile``, ``trim_distance`` (a fraction of the points' bounding-box
            diagonal), ``target_faces``, ``min_angle_deg`` (sliver threshold of
            :func:`~pmvir.geometry.surface.clean.clean_mesh`).
        max_area_px: with ``cameras``, faces projecting larger than this (pixels^2, in a view
            they face) are bisected afterwards (:func:`split_large_faces`).
        mask_slack_px: pixels the masks are dilated by in the silhouette trimming beyond
            ``SILHOUETTE_PX`` (for masks drawn from the images, which miss a pixel or two of the outline).
        mask_outside_share: share of the views seeing a vertex whose masks it may fall outside and stay
            (:func:`off_silhouette`; for masks drawn from the images, which cut into the object here and there).

    Returns:
        :class:`SurfaceResult`.

    Raises:
        ReconstructionError: too few points, or nothing left after trimming/cleaning.
    """
    from scipy.spatial import cKDTree

    opts = options or SurfaceOptions()
    pts = np.asarray(points, np.float64)
    if len(pts) < 100:
        raise ReconstructionError(
            f"the dense point cloud has {len(pts)} points; at least 100 are needed for a surface"
        )
    counts: dict[str, int] = {"points": len(pts)}
    poisson_depth = opts.poisson_depth
    if poisson_depth is None:
        poisson_depth = auto_poisson_depth(pts, cameras, voxel_px=opts.poisson_voxel_px) if cameras else 8
    v, f, density = poisson_surface(pts, normals, depth=poisson_depth)
    counts.update(poisson_depth=int(poisson_depth), poisson_vertices=len(v), poisson_faces=len(f))
    keep = density >= np.quantile(density, opts.trim_density_quantile)
    diag = float(np.linalg.norm(pts.max(0) - pts.min(0)))
    tree = cKDTree(pts)
    dist, _ = tree.query(v, k=1)
    spacing = float(np.median(tree.query(pts[:: max(1, len(pts) // 5000)], k=5)[0][:, -1]))
    trim = max(opts.trim_distance * diag, _TRIM_SPACINGS * spacing)  # sparse points: no holes between them
    keep &= dist <= trim
    if cameras is not None and masks is not None:
        keep &= ~off_silhouette(
            v, cameras, masks, dilate_px=SILHOUETTE_PX + mask_slack_px, outside_share=mask_outside_share
        )
    v, f = _keep_vertices(v, f, keep)
    counts.update(trimmed_vertices=len(v), trimmed_faces=len(f))
    if len(f) == 0:
        raise ReconstructionError(
            "trimming removed the whole Poisson surface: the dense points do not form a surface"
        )
    if len(f) > opts.target_faces:
        mesh = o3d_mesh(v, f).simplify_quadric_decimation(target_number_of_triangles=int(opts.target_faces))
        v, f = mesh_arrays(mesh)
    counts.update(simplified_vertices=len(v), simplified_faces=len(f))
    components: list[dict[str, object]] = []
    v, f, slivers = clean_mesh(
        v,
        f,
        min_angle_deg=opts.min_angle_deg,
        support=pts,
        min_support=opts.min_component_points,
        components=components,
    )
    f = orient_outward(v, f, pts, np.asarray(normals, np.float64))
    counts.update(clean_vertices=len(v), clean_faces=len(f), slivers_collapsed=slivers)
    if cameras is not None and max_area_px is not None:
        v, f = split_large_faces(v, f, cameras, max_area_px=max_area_px)
        counts.update(split_vertices=len(v), split_faces=len(f))
    counts.update(boundary_edges=int(edge_topology(f, len(v)).boundary.sum()))
    return SurfaceResult(vertices=v, faces=f, counts=counts, components=components)
