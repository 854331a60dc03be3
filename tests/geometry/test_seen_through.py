"""Surface the views see through (a membrane across a ring's opening) found and cut with stereo depths."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import open3d as o3d
import pytest
from scipy.spatial import Delaunay

from pmvir.camera import Camera, look_at
from pmvir.config import GeometryOptions
from pmvir.geometry.mesh_ops import raycasting_scene
from pmvir.geometry.mvs.sweep import DepthMap
from pmvir.geometry.stage import without_seen_through
from pmvir.geometry.surface.initial import SurfaceResult
from pmvir.geometry.surface.seen_through import (
    MAX_AT,
    MIN_PAST,
    cut_seen_through,
    lying_on_support,
    seen_through,
)

RING, TUBE = 0.3, 0.1  # the ring's radius and its tube's: the opening's radius is 0.2


def ring_mesh(radial: int = 60, tubular: int = 24) -> tuple[np.ndarray, np.ndarray]:
    mesh = o3d.geometry.TriangleMesh.create_torus(torus_radius=RING, tube_radius=TUBE, radial_resolution=radial,
                                                  tubular_resolution=tubular)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.triangles, np.int64)


def membrane(radius: float = RING - TUBE - 0.02, rings: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """A disc across the ring's opening (z = 0, facing up), as Poisson closes it."""
    rr, aa = np.meshgrid(np.linspace(0.0, radius, rings + 1)[1:], np.linspace(0, 2 * np.pi, 6 * rings, endpoint=False))
    xy = np.vstack([[0.0, 0.0], np.stack([rr.ravel() * np.cos(aa.ravel()), rr.ravel() * np.sin(aa.ravel())], 1)])
    faces = Delaunay(xy).simplices.astype(np.int64)
    a, b, c = (xy[faces[:, k]] for k in range(3))
    ccw = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (c[:, 0] - a[:, 0]) > 0
    faces[~ccw] = faces[~ccw][:, [0, 2, 1]]
    return np.hstack([xy, np.zeros((len(xy), 1))]), faces


def table(z: float = -TUBE, half: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]])
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def joined(*parts: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, n = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.vstack(vs), np.vstack(fs)


def cameras(n: int = 12, elevations_deg: tuple[float, ...] = (40.0, 65.0), size: tuple[int, int] = (120, 96)
            ) -> list[Camera]:
    w, h = size
    out = []
    for k in range(n * len(elevations_deg)):
        a = 2 * np.pi * (k + 0.5 * (k // n)) / n
        e = np.radians(elevations_deg[k // n])
        centre = 2.0 * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
        R, t = look_at(centre, np.zeros(3))
        out.append(Camera.from_intrinsics(110.0, 110.0, w / 2, h / 2, w, h, R, t))
    return out


def depth_maps(truth: tuple[np.ndarray, np.ndarray], cams: list[Camera]) -> list[DepthMap]:
    """Each view's depth of the true scene at its pixel centres (ray casting)."""
    scene = raycasting_scene(*truth)
    maps = []
    for cam in cams:
        rows, cols = np.mgrid[0 : cam.height, 0 : cam.width]
        pixels = np.stack([cols.ravel() + 0.5, rows.ravel() + 0.5, np.ones(rows.size)], 1)
        direction = pixels @ np.linalg.inv(cam.K).T @ cam.R  # camera z = 1: t_hit is the depth
        origin = np.broadcast_to(scene.local(cam.center[None]), direction.shape)
        rays = o3d.core.Tensor(np.ascontiguousarray(np.hstack([origin, direction]), np.float32))
        t = scene.scene.cast_rays(rays)["t_hit"].numpy().reshape(cam.height, cam.width)
        depth = np.where(np.isfinite(t), t, 0.0).astype(np.float32)
        maps.append(DepthMap(camera=cam, depth=depth, score=(depth > 0).astype(np.float32)))
    return maps


MARGIN = 0.02


@pytest.fixture(scope="module")
def setup():
    ring, disc = ring_mesh(), membrane()
    surface = joined(ring, disc)
    cams = cameras()
    return surface, len(ring[0]), depth_maps(joined(ring, table()), cams)


def test_the_views_see_through_a_membrane_across_an_opening_and_onto_the_ring(setup):
    (v, f), n_ring, maps = setup
    votes = seen_through(v, f, maps, margin=MARGIN)
    on_ring, on_disc = ~votes.through[:n_ring], votes.through[n_ring:]
    centre = np.linalg.norm(v[n_ring:, :2], axis=1) < 0.12  # the disc's middle, away from the tube
    assert on_ring.mean() > 0.99
    assert on_disc[centre].all()
    assert np.median(votes.at[:n_ring]) >= 2 * MAX_AT  # the ring's own depths vote for it
    assert np.median(votes.past[n_ring:][centre]) >= 2 * MIN_PAST


def test_depths_past_the_surface_in_most_views_do_not_cut_a_surface_others_see(setup):
    """A textureless object: stereo puts most views' depths behind its wall, a few on it."""
    (v, f), n_ring, maps = setup
    rng = np.random.default_rng(0)
    wrong = []
    for k, dm in enumerate(maps):
        if k % 3 == 0:  # a third of the views keep the right depths
            wrong.append(dm)
            continue
        depth = dm.depth.copy()
        depth[depth > 0] += rng.uniform(0.2, 0.6, int((depth > 0).sum())).astype(np.float32)
        wrong.append(DepthMap(camera=dm.camera, depth=depth, score=dm.score))
    votes = seen_through(v[:n_ring], f[: len(ring_mesh()[1])], wrong, margin=MARGIN)
    upper = v[:n_ring, 2] > 0  # the half every view sees (the lower one: a few grazing views)
    assert np.median(votes.past[upper]) > 2 * np.median(votes.at[upper])  # most views see past it ...
    assert not votes.through[upper].any()  # ... and yet it stays


def test_the_cut_takes_the_membrane_and_keeps_the_ring(setup):
    (v, f), n_ring, maps = setup
    ring_v = v[:n_ring]
    v2, _, count = cut_seen_through(v, f, maps, margin=MARGIN, support=ring_v, min_angle_deg=0.0)
    assert count > 0.5 * (len(v) - n_ring)
    assert np.abs(v2[:, 2]).max() > 0.09  # the ring is there ...
    assert (np.linalg.norm(v2[:, :2], axis=1) > RING - TUBE - 1e-6).all()  # ... and nothing inside its opening


def test_a_cut_of_most_of_the_surface_is_not_made(setup):
    (v, f), _, maps = setup
    far = [DepthMap(camera=dm.camera, depth=np.where(dm.depth > 0, dm.depth + 1.0, 0).astype(np.float32),
                    score=dm.score) for dm in maps]
    v2, f2, count = cut_seen_through(v, f, far, margin=MARGIN, support=v, min_angle_deg=0.0)
    assert count == 0 and len(v2) == len(v) and len(f2) == len(f)


def test_the_geometric_stage_cuts_with_its_depth_maps_and_counts_it(setup):
    (v, f), n_ring, maps = setup
    points = v[:n_ring]
    surface = SurfaceResult(vertices=v, faces=f, counts={"clean_vertices": len(v)})
    dense = SimpleNamespace(points=SimpleNamespace(points=points), depth_maps=maps)
    cut = without_seen_through(surface, dense, GeometryOptions())  # type: ignore[arg-type]
    assert cut.counts["seen_through_vertices"] > 0 and cut.counts["cut_vertices"] == len(cut.vertices) < len(v)
    assert cut.counts["clean_vertices"] == len(v)
    none = SimpleNamespace(points=dense.points, depth_maps=[None] * len(maps))  # COLMAP's fusion: no depth maps
    assert without_seen_through(surface, none, GeometryOptions()) is surface  # type: ignore[arg-type]


def test_a_piece_the_cut_separates_stays():
    """A box stands inside the opening; the fill over it lies on its top: the cut leaves it a piece of its own."""
    ring = ring_mesh(240, 48)  # as fine as the disc: the cut takes less than half of the surface
    disc_v, disc_f = membrane(rings=40)
    top = np.linalg.norm(disc_v[:, :2], axis=1) < 0.05
    disc_v = disc_v.copy()
    disc_v[top, 2] = -0.04
    box = o3d.geometry.TriangleMesh.create_box(0.16, 0.16, 0.06).translate((-0.08, -0.08, -TUBE))
    truth = joined(ring, table(), (np.asarray(box.vertices, np.float64), np.asarray(box.triangles, np.int64)))
    v, f = joined(ring, (disc_v, disc_f))
    maps = depth_maps(truth, cameras())
    v2, _, count = cut_seen_through(v, f, maps, margin=MARGIN, support=ring[0], min_angle_deg=0.0)
    assert count > 0
    radius = np.linalg.norm(v2[:, :2], axis=1)
    on_top = (radius < 0.05) & (np.abs(v2[:, 2] + 0.04) < 1e-9)
    assert on_top.sum() > 0.9 * top.sum()  # the box's piece stays, though no ring vertex is near it
    assert not ((radius > 0.1) & (radius < RING - TUBE - 0.03)).any()  # the fill around it goes


def test_a_sheet_lying_on_the_support_is_cut_and_the_object_s_foot_stays(setup):
    """Poisson keeps a patch of the table under a ring's opening: every view's depth lands on it, so only its
    place and facing tell it from the ring's own foot."""
    ring = ring_mesh()
    n_ring = len(ring[0])
    sheet_v, sheet_f = membrane()
    v, f = joined(ring, (sheet_v + [0.0, 0.0, -TUBE + 0.005], sheet_f))
    plane, band = np.array([0.0, 0.0, 1.0, TUBE]), 0.02  # the table: z = -TUBE, normal up
    on = lying_on_support(v, f, plane, band)
    foot = v[:n_ring, 2] < -TUBE + band
    assert on[n_ring:].all()
    assert foot.sum() >= 30 and not on[:n_ring][foot].any()  # the ring's foot faces down or sideways
    assert not lying_on_support(v, f, plane, 0.004).any()  # above the band: not the support's

    maps = setup[2]  # the ring standing on the table
    assert not seen_through(v, f, maps, margin=MARGIN).through[n_ring:].any()  # the depths land on the sheet
    surface = SurfaceResult(vertices=v, faces=f, counts={})
    dense = SimpleNamespace(points=SimpleNamespace(points=ring[0]), depth_maps=maps)
    isolation = SimpleNamespace(plane=plane, clearance=band / GeometryOptions().isolate.plane_clearance)
    cut = without_seen_through(surface, dense, GeometryOptions(), isolation)  # type: ignore[arg-type]
    inside = np.linalg.norm(cut.vertices[:, :2], axis=1) < RING - TUBE - 1e-6
    assert cut.counts["support_sheet_vertices"] == len(sheet_v) and not inside.any()
    assert cut.vertices[:, 2].min() < -TUBE + 0.002  # the ring's foot is there
    kept = without_seen_through(
        surface, dense, GeometryOptions(isolate={"cut_support_sheet": False}), isolation  # type: ignore[arg-type]
    )
    assert "support_sheet_vertices" not in kept.counts
    assert (np.linalg.norm(kept.vertices[:, :2], axis=1) < RING - TUBE - 1e-6).sum() == len(sheet_v)


def test_a_membrane_no_fused_point_supports_goes_where_most_views_see_past_it(setup):
    """A third of the views' depths land on the membrane (stereo's chance matches there): the votes alone keep
    it; far from every fused point, the views that see past it outvote them."""
    (v, f), n_ring, maps = setup
    ring, disc = ring_mesh(), membrane()
    on_disc = depth_maps(joined(ring, disc, table()), cameras())
    mixed = [on_disc[k] if k % 3 == 0 else dm for k, dm in enumerate(maps)]
    spacing = 0.02  # the membrane's middle (radius < 0.1) lies more than UNSUPPORTED_SPACINGS of it from the ring
    votes = seen_through(v, f, mixed, margin=MARGIN, points=ring[0], spacing=spacing)
    middle = np.linalg.norm(v[n_ring:, :2], axis=1) < 0.08
    assert votes.unsupported[n_ring:][middle].all() and not votes.unsupported[:n_ring].any()
    assert (votes.at[n_ring:][middle] >= MAX_AT).all()  # the votes alone would keep it ...
    assert (votes.past[n_ring:][middle] > votes.at[n_ring:][middle]).all()
    assert votes.through[n_ring:][middle].all() and not votes.through[:n_ring].any()  # ... it goes, the ring stays
    assert not seen_through(v, f, mixed, margin=MARGIN).through[n_ring:][middle].any()
    # a fused point on the membrane supports it: the third of the views that land there keep it
    supported = seen_through(v, f, mixed, margin=MARGIN, points=np.vstack([ring[0], disc[0]]), spacing=spacing)
    assert not supported.unsupported.any() and not supported.through[n_ring:][middle].any()
    v2, _, count = cut_seen_through(v, f, mixed, margin=MARGIN, support=ring[0], min_angle_deg=0.0, spacing=spacing)
    assert count > 0 and not (np.linalg.norm(v2[:, :2], axis=1) < 0.08).any()
    assert len(v2) >= n_ring  # the ring stays whole


def test_a_bulge_four_spacings_from_every_fused_point_is_unsupported(setup):
    """Poisson's bulge under a knot's tube lies 3.4-5 point spacings from the nearest fused point: there
    the views that see past a vertex outvote the third of them whose depths land on it."""
    (v, f), n_ring, maps = setup
    ring, disc = ring_mesh(), membrane()
    on_disc = depth_maps(joined(ring, disc, table()), cameras())
    mixed = [on_disc[k] if k % 3 == 0 else dm for k, dm in enumerate(maps)]
    spacing = 0.035
    radius = np.linalg.norm(v[n_ring:, :2], axis=1)
    band = (radius > 0.05) & (radius < 0.08)  # about 0.14 from the ring's inner edge (radius 0.2)
    nearest = np.min(np.linalg.norm(v[n_ring:][band][:, None, :] - ring[0][None], axis=2), axis=1) / spacing
    assert band.any() and (nearest > 3.5).all() and (nearest < 5.0).all()  # the bulge's range
    votes = seen_through(v, f, mixed, margin=MARGIN, points=ring[0], spacing=spacing)
    assert (votes.at[n_ring:][band] >= MAX_AT).all()  # the votes alone would keep it
    assert votes.unsupported[n_ring:][band].all() and not votes.unsupported[:n_ring].any()
    assert votes.through[n_ring:][band].all() and not votes.through[:n_ring].any()
