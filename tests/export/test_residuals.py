"""Residual images against a known answer: observations rendered from the same mesh and lighting."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from pmvir.camera import Camera, look_at
from pmvir.config import RefineOptions
from pmvir.export.views import pixel_epol, write_residuals, write_view_previews
from pmvir.io.ply import Mesh
from pmvir.polarization.stokes import PolarizationImages
from pmvir.refine.forward import render_decoded

SH = np.array([0.8, 0.1, 0.3, 0.2, 0.0, 0.05, 0.1, 0.0, 0.02])
SCALE = np.array([0.5, 0.45, 0.4])


def _cameras() -> list[Camera]:
    cams = []
    for az in (0.0, 2.0):
        centre = 3.0 * np.array([np.cos(az), np.sin(az), 0.4])
        r, t = look_at(centre, np.zeros(3))
        cams.append(Camera.from_intrinsics(160.0, 160.0, 64.0, 48.0, 128, 96, r, t))
    return cams


def _observed(mesh: Mesh, cams: list[Camera]) -> list[tuple[str, PolarizationImages]]:
    frames = render_decoded(mesh.vertices, mesh.faces, mesh.albedo, cams, SH, SCALE, dop_scale=1.0)
    return [
        (f"{k:03d}", PolarizationImages(f["i_int"], f["i_min"], f["aop"], f["dop"], f["valid"]))
        for k, f in enumerate(frames)
    ]


def _read_rgb(path: Path) -> np.ndarray:
    return cv2.cvtColor(cv2.imread(str(path)), cv2.COLOR_BGR2RGB)


def test_residuals_of_the_true_model_vanish_and_a_too_bright_model_shows_blue(
    sphere_mesh: Mesh, tmp_path: Path
) -> None:
    cams = _cameras()
    views = _observed(sphere_mesh, cams)
    sh, scale = np.tile(SH, (2, 1)), np.tile(SCALE, (2, 1))
    exact = write_residuals(
        tmp_path,
        views,
        cams,
        sphere_mesh.vertices,
        sphere_mesh.faces,
        sphere_mesh.albedo,
        sh,
        scale,
        options=RefineOptions(),
        max_size=64,
    )
    for row in exact["views"]:
        assert row["pixels"] > 500  # 64x48 images, the sphere covers a good part of them
        assert row["rms"] < 2e-3 and row["mean_epol"] < 1e-3
    assert json.loads((tmp_path / "summary.json").read_text())["intensity"] == "i_min"
    image = _read_rgb(tmp_path / "000_intensity.png")
    assert image.shape == (48, 64, 3)

    bright = tmp_path / "bright"
    bright.mkdir()
    too_bright = write_residuals(
        bright,
        views,
        cams,
        sphere_mesh.vertices,
        sphere_mesh.faces,
        sphere_mesh.albedo * 1.3,
        sh,
        scale,
        options=RefineOptions(),
        max_size=64,
    )
    assert all(row["mean"] < 0 for row in too_bright["views"])  # observed - rendered < 0
    image = _read_rgb(bright / "000_intensity.png").astype(int)
    on = image.sum(axis=2) > 0
    assert (image[on][:, 2] >= image[on][:, 0]).mean() > 0.95  # blue side of the map


def test_pixel_epol_is_zero_on_agreement_and_largest_halfway() -> None:
    options = RefineOptions(pol={"dop_min": 0.0})
    model = np.array([[0.3, 0.3, 0.3]])
    aop = np.array([[0.3, 0.3 + np.pi / 2, 0.3 + np.pi / 4]])
    dop = np.full((1, 3), 0.5)
    e = pixel_epol(model, aop, dop, options)
    np.testing.assert_allclose(e[0, :2], 0.0, atol=1e-12)  # phi and phi + pi/2 both agree
    assert e[0, 2] == pytest.approx(0.5)  # rho * 1 halfway between candidates
    assert pixel_epol(model, aop, np.full((1, 3), 0.01), RefineOptions()).max() == 0.0  # below dop_min


def test_previews_are_reduced_to_the_size_asked(sphere_mesh: Mesh, tmp_path: Path) -> None:
    stem, images = _observed(sphere_mesh, _cameras())[0]
    paths = write_view_previews(tmp_path, stem, images, max_size=50)
    assert [p.name for p in paths] == ["000_int.png", "000_dop.png", "000_aop.png"]
    for p in paths:
        assert cv2.imread(str(p)).shape[:2] == (32, 42)  # 128x96 reduced by 3
