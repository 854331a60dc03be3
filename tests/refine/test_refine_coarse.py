"""Coarse to fine (``refine.stages.coarse``): the lift from the coarse surface and the staged run on both."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from pydantic import ValidationError
from refine_scene import accuracy, make_scene

from pmvir.config import RefineOptions
from pmvir.errors import ConfigError, PmvirError
from pmvir.geometry.subdivision import sqrt3_subdivide, subdivide_until
from pmvir.refine import make_visibility_fn, observation_from_decoded, refine_surface
from pmvir.refine.coarse import CoarseMesh, Lift, barycentric

NO_MOSAIC = {"views": {"silhouette_margin_px": 0}}


def _octahedron() -> tuple[np.ndarray, np.ndarray]:
    v = np.array([[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]], dtype=np.float64)
    f = np.array(
        [[0, 2, 4], [2, 1, 4], [1, 3, 4], [3, 0, 4], [2, 0, 5], [1, 2, 5], [3, 1, 5], [0, 3, 5]], dtype=np.int64
    )
    return v, f


def test_barycentric_weights_rebuild_points_and_clip_outside_ones() -> None:
    rng = np.random.default_rng(0)
    a, b, c = (rng.normal(size=(50, 3)) for _ in range(3))
    w_true = rng.dirichlet([1.0, 1.0, 1.0], size=50)
    p = w_true[:, :1] * a + w_true[:, 1:2] * b + w_true[:, 2:] * c
    np.testing.assert_allclose(barycentric(p, a, b, c), w_true, atol=1e-9)
    outside = barycentric(a + 2.0 * (b - a), a, b, c)  # beyond corner b, on the edge's line
    assert (outside >= 0).all()
    np.testing.assert_allclose(outside.sum(axis=1), 1.0)
    degenerate = barycentric(a, a, a, a)
    np.testing.assert_allclose(degenerate, 1.0 / 3.0)


def test_lift_carries_an_affine_motion_of_the_coarse_surface_exactly() -> None:
    v, f = _octahedron()
    step = sqrt3_subdivide(v, f)  # new vertices at face centroids: on the coarse faces, no offset
    lift = Lift.between(v, f, step.vertices)
    np.testing.assert_allclose(lift.offsets, 0.0, atol=1e-12)
    a = np.array([[1.1, 0.2, 0.0], [0.0, 0.9, 0.1], [0.05, 0.0, 1.3]])
    t = np.array([0.3, -0.2, 0.5])
    moved = lift.apply(torch.from_numpy(v @ a.T + t), offsets=True).numpy()
    np.testing.assert_allclose(moved, step.vertices @ a.T + t, atol=1e-12)
    colours = torch.from_numpy(np.arange(18, dtype=np.float64).reshape(6, 3))
    lifted = lift.apply(colours, offsets=False).numpy()
    np.testing.assert_allclose(lifted[:6], colours.numpy())  # the old vertices keep their own values


def test_lift_keeps_the_offset_of_vertices_off_the_coarse_faces() -> None:
    v, f = _octahedron()
    step = sqrt3_subdivide(v, f)
    fine = step.vertices * 1.01  # slightly off every face
    lift = Lift.between(v, f, fine)
    np.testing.assert_allclose(lift.apply(torch.from_numpy(v), offsets=True).numpy(), fine, atol=1e-12)


@pytest.fixture(scope="module")
def scene_and_inputs():
    scene = make_scene(two_colours=True)
    obs = [observation_from_decoded(fr, intensity="min") for fr in scene.frames]
    vis_fn = make_visibility_fn(scene.cameras)
    vis = vis_fn(scene.vertices, scene.faces)
    fine = subdivide_until(scene.vertices, scene.faces, vis, scene.cameras, max_area_px=1e-6, max_rounds=1,
                           max_vertices=10**7)
    return scene, obs, vis_fn, vis, fine


def test_coarse_stages_run_on_the_coarse_surface_and_the_last_refines_the_subdivided_one(scene_and_inputs) -> None:
    scene, obs, vis_fn, vis, fine = scene_and_inputs
    opts = RefineOptions(stages={"coarse": 2}, solver={"max_iterations": 25}, **NO_MOSAIC)
    coarse = CoarseMesh(scene.vertices, scene.faces, vis)
    res = refine_surface(fine.vertices, fine.faces, scene.cameras, obs, fine.visibility, options=opts,
                         visibility_fn=vis_fn, coarse=coarse)
    all_fine = refine_surface(fine.vertices, fine.faces, scene.cameras, obs, fine.visibility, options=opts.model_copy(
        update={"stages": opts.stages.model_copy(update={"coarse": 0})}), visibility_fn=vis_fn)
    n_coarse, n_fine = len(scene.vertices), len(fine.vertices)
    assert res.vertices.shape == (n_fine, 3) and res.albedo.shape == (n_fine, 3)
    assert res.coarse_vertices == n_coarse and all_fine.coarse_vertices == 0
    assert [st.n_observed <= n_coarse for st in res.stages] == [True, True, False]
    assert "lift" in res.stage_timings[2] and all("lift" not in t for t in res.stage_timings[:2])
    before = accuracy(fine.vertices, scene.true_vertices, scene.true_faces)
    acc = accuracy(res.vertices, scene.true_vertices, scene.true_faces)
    acc_fine = accuracy(all_fine.vertices, scene.true_vertices, scene.true_faces)
    assert acc < 0.8 * before
    assert acc < 1.15 * acc_fine


def test_a_coarse_mesh_of_the_wrong_shape_is_a_config_error(scene_and_inputs) -> None:
    scene, obs, _, vis, fine = scene_and_inputs
    bad = CoarseMesh(scene.vertices, scene.faces, vis[:, :-1])
    with pytest.raises(ConfigError, match="coarse mesh"):
        refine_surface(fine.vertices, fine.faces, scene.cameras, obs, fine.visibility,
                       options=RefineOptions(stages={"coarse": 1}), coarse=bad)


def test_coarse_stages_must_leave_a_stage_for_the_subdivided_surface() -> None:
    with pytest.raises(ValidationError, match="coarse must be below the stage count 3"):
        RefineOptions(stages={"coarse": 3})


def test_the_pipelines_coarse_surface_is_the_subdivision_one_step_short(scene_and_inputs) -> None:
    from types import SimpleNamespace

    from pmvir.pipeline import coarse_surface

    scene = scene_and_inputs[0]
    two = subdivide_until(scene.vertices, scene.faces, scene_and_inputs[3], scene.cameras, max_area_px=1e-6,
                          max_rounds=2, max_vertices=10**7)
    assert two.rounds == 2 and two.before_last is not None
    vertices, faces, visibility = two.before_last
    np.testing.assert_array_equal(faces, scene_and_inputs[4].faces)  # the one-step mesh of the fixture
    np.testing.assert_allclose(vertices, scene_and_inputs[4].vertices)
    assert visibility.shape == (len(vertices), 8)
    # the geometry stage keeps it over all frames; the refinement takes the registered views' columns
    frames = np.zeros((len(vertices), 9), bool)
    frames[:, [0, 1, 2, 3, 5, 6, 7, 8]] = visibility
    geometry = SimpleNamespace(subdivision_rounds=2, coarse=(vertices, faces, frames))
    one = coarse_surface(geometry, [0, 1, 2, 3, 5, 6, 7, 8])
    assert one is not None
    np.testing.assert_array_equal(one.visibility, visibility)
    assert coarse_surface(SimpleNamespace(subdivision_rounds=0, coarse=None), list(range(8))) is None
    with pytest.raises(PmvirError, match="run the geometry stage again"):
        coarse_surface(SimpleNamespace(subdivision_rounds=2, coarse=None), list(range(8)))


def test_subdivision_without_a_step_keeps_no_coarse_surface(scene_and_inputs) -> None:
    scene = scene_and_inputs[0]
    none = subdivide_until(scene.vertices, scene.faces, scene_and_inputs[3], scene.cameras, max_area_px=1e-6,
                           max_rounds=0, max_vertices=10**7)
    assert none.rounds == 0 and none.before_last is None
