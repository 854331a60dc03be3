"""The known cameras' visual hull (pmvir.geometry.silhouette.hull): it holds the object, bounds depths, names bad views."""

from __future__ import annotations

import numpy as np
import pytest

from pmvir.errors import ReconstructionError
from pmvir.geometry.silhouette.hull import carve_hull
from pmvir.io.ply import Mesh
from pmvir.synth.raycast import MeshScene
from pmvir.synth.rig import ring_cameras
from pmvir.synth.shapes import builtin_shape


def _masks(mesh, cams):
    from pmvir.synth.builtin_renderer import render_view
    from pmvir.synth.lighting import sh_lights

    albedo = np.full((len(mesh.vertices), 3), 0.5, np.float32)
    scene = MeshScene.from_mesh(Mesh(mesh.vertices, mesh.faces, albedo=albedo, normals=mesh.normals))
    lights = sh_lights(len(cams), seed=0)
    return [
        render_view(scene, c, li, material="lambert").geometry.mask
        for c, li in zip(cams, lights, strict=True)
    ]


def test_hull_holds_the_object_and_bounds_every_views_depth():
    mesh = builtin_shape("knot")
    cams = ring_cameras(12, 160, 128, object_radius=float(np.linalg.norm(mesh.vertices, axis=1).max()))
    masks = _masks(mesh, cams)
    hull = carve_hull(cams, masks)
    assert hull.from_masks and len(hull.surface) < len(hull.points)
    # every true vertex lies within a cell of a kept cell
    from scipy.spatial import cKDTree

    d, _ = cKDTree(hull.points).query(mesh.vertices)
    assert d.max() <= np.sqrt(3) * hull.cell
    for cam in cams:
        near, far = hull.depth_range(cam)
        _, z = cam.project(mesh.vertices)
        assert near <= z.min() and z.max() <= far
        assert far - near < 3.0 * (z.max() - z.min())  # a bound, not the whole frustum
    frustum = carve_hull(cams, None)  # without masks: the common field of view, larger
    assert not frustum.from_masks and frustum.diagonal > hull.diagonal
    for cam in cams:
        near, far = frustum.depth_range(cam)
        _, z = cam.project(mesh.vertices)
        assert near <= z.min() and z.max() <= far


def test_masks_that_share_no_volume_raise_naming_views():
    mesh = builtin_shape("sphere")
    cams = ring_cameras(6, 96, 80, object_radius=float(np.linalg.norm(mesh.vertices, axis=1).max()))
    masks = _masks(mesh, cams)
    for m in masks:  # the object in every frame's corner: masks that do not belong to these poses
        m[:] = False
        m[:6, :6] = True
    with pytest.raises(
        ReconstructionError, match=r"share no volume \(views whose masks removed most of it: \d"
    ):
        carve_hull(cams, masks, names=[str(i) for i in range(6)])
