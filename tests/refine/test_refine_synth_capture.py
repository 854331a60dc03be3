"""The refinement on a real ``pmvir synth`` capture: decoded mosaics, the geometric stage's surface.

Unlike the scenes of refine_scene.py (rendered with the refinement's own image
model), this capture is rendered by the synthetic-capture renderer: a specular
plastic, a procedural texture, 12-bit mosaics with noise, demosaiced by pmvir.
The initial surface is what the geometric stage makes of it (true poses).
"""

from __future__ import annotations

import numpy as np
import pytest

from pmvir.capture import open_capture
from pmvir.config import DecodeOptions, GeometryOptions, PipelineConfig, RefineOptions
from pmvir.evaluate import evaluate
from pmvir.geometry.stage import run_geometry
from pmvir.io.ply import Mesh, read_mesh
from pmvir.pipeline import decode_views, refinement_observations
from pmvir.refine import make_visibility_fn, refine_surface
from pmvir.synth import synthesize

#: Fewer iterations than the default keep the test short.
OPTIONS = {"solver": {"max_iterations": 10}}


@pytest.fixture(scope="module")
def capture_run(tmp_path_factory: pytest.TempPathFactory):
    root = tmp_path_factory.mktemp("synth-refine")
    path = synthesize(root / "cap", shape="blob", views=24, size=(256, 216), material="plastic", seed=3)
    gopts = GeometryOptions(subdivision={"max_area_px": 8.0})
    with open_capture(path) as cap:
        views = decode_views(cap, PipelineConfig())
        masks = [cap.read_mask(i) for i in range(len(cap.frames))]
        geo = run_geometry(cap, [v.images for v in views], options=gopts, workdir=root / "work")
        reg = [i for i, c in enumerate(geo.cameras) if c is not None]
        # the images the pipeline's refinement fits (refine.demosaic's, by default)
        obs = refinement_observations(cap, views, reg, DecodeOptions(), RefineOptions(**OPTIONS))
    cameras = [geo.cameras[i] for i in reg]
    vis_fn = make_visibility_fn(
        cameras, [masks[i] for i in reg], min_cos=gopts.visibility.min_cos, rel_tol=gopts.visibility.rel_tol
    )
    gt = read_mesh(path / "gt" / "mesh.ply")

    def accuracy(vertices: np.ndarray) -> float:
        return evaluate(Mesh(vertices, geo.faces), gt, n_samples=20_000).accuracy

    runs = {}
    for name, extra in (
        ("full", {}),
        ("mvir", {"pol": {"enabled": False}}),
        ("all_pairs", {"views": {"min_cos": -1.0}}),
    ):
        res = refine_surface(
            geo.vertices,
            geo.faces,
            cameras,
            obs,
            geo.visibility[:, reg],
            options=RefineOptions(**OPTIONS, **extra),
            visibility_fn=vis_fn,
        )
        runs[name] = accuracy(res.vertices)
    runs["initial"] = accuracy(geo.vertices)
    return runs


def test_refinement_lowers_the_accuracy_error_of_the_geometric_surface(capture_run) -> None:
    assert capture_run["full"] < 0.85 * capture_run["initial"]


def test_polarimetric_term_beats_the_mvir_baseline(capture_run) -> None:
    assert capture_run["full"] < capture_run["mvir"]


def test_leaving_out_grazing_pairs_costs_no_accuracy(capture_run) -> None:
    """With every visible pair (min_view_cos -1) the refinement does no better than with the default rule.

    With the robust E_pho and eari frames the two are close on this small capture, and which is
    ahead changes with the initial surface (the ratio of the default's accuracy to every pair's
    ranges over a few percent with small changes of the sparse points). So the test keeps the
    default from falling clearly behind (8%).
    """
    assert capture_run["full"] < 1.08 * capture_run["all_pairs"]
