"""Result files for people and other tools, written with every result.

* :func:`write_previews`: ``previews/`` (decoded I_int, DoP, AoP per view, small);
* :func:`write_refined_outputs`: ``residuals/`` (observed minus rendered per view),
  ``mesh.glb`` (every vertex of ``mesh.ply``, linear albedo as ``COLOR_0``, +Y up),
  and, unless ``export.textured`` is off, ``textured.glb`` and
  ``textured.obj`` + ``textured.mtl`` + ``textured_albedo.png`` (decimated, UV atlas,
  baked albedo).

Every file is registered in :data:`pmvir.result.RESULT_FILES` and written
through :class:`pmvir.result.ResultFolder` (temporary name, then rename).
"""

from __future__ import annotations

import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from pmvir.camera import Camera
from pmvir.config import PipelineConfig
from pmvir.export.glb import conversion_extras, to_gltf_frame, write_glb
from pmvir.export.textured import bake_textured_in_child, encode_png, mtl_text, obj_text
from pmvir.export.views import write_residuals, write_view_previews
from pmvir.geometry.mesh_ops import vertex_normals
from pmvir.io.ply import Mesh
from pmvir.polarization.stokes import PolarizationImages
from pmvir.progress import Progress
from pmvir.result import ResultFolder

__all__ = ["write_mesh_glb", "write_previews", "write_refined_outputs", "write_textured"]


def write_previews(
    result: ResultFolder,
    views: Sequence[tuple[str, PolarizationImages]],
    *,
    max_size: int,
    progress: Progress,
) -> None:
    """``previews/<stem>_{int,dop,aop}.png`` of every decoded view."""

    def fill(folder: Path) -> None:
        for k, (stem, images) in enumerate(views):
            write_view_previews(folder, stem, images, max_size=max_size)
            progress.update((k + 1) / len(views), f"preview of {stem}")

    result.write_folder("previews", fill)


def write_mesh_glb(result: ResultFolder, mesh: Mesh) -> None:
    """``mesh.glb``: the refined mesh as it is (same vertices and faces), +Y up, linear albedo as COLOR_0."""
    normals = mesh.normals if mesh.normals is not None else vertex_normals(mesh.vertices, mesh.faces)
    extras = {**conversion_extras(), "source": "mesh.ply", "color_0": "linear RGB albedo"}
    result.write_file(
        "mesh.glb",
        lambda tmp: write_glb(
            tmp,
            to_gltf_frame(mesh.vertices),
            mesh.faces,
            normals=to_gltf_frame(normals),
            colors=mesh.albedo,
            extras=extras,
            name="pmvir-mesh",
        ),
    )


def write_textured(
    result: ResultFolder, mesh: Mesh, *, face_budget: int, texture_size: int, progress: Progress | None = None
) -> dict[str, Any]:
    """``textured.glb``, ``textured.obj``, ``textured.mtl`` and ``textured_albedo.png``; returns counts.

    The bake runs in a child process (:func:`~pmvir.export.textured.bake_textured_in_child`): it
    holds the GIL for long, and ``progress`` may cancel it.
    """
    result.root.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix=".bake-", dir=result.root) as work:
        textured = bake_textured_in_child(
            mesh,
            face_budget=face_budget,
            texture_size=texture_size,
            workdir=Path(work),
            should_stop=None if progress is None else progress.check_cancel,
        )
    png = encode_png(textured.texture)
    result.write_file("textured_albedo.png", lambda tmp: tmp.write_bytes(png))
    result.write_file("textured.mtl", lambda tmp: tmp.write_text(mtl_text("textured_albedo.png")))
    result.write_file("textured.obj", lambda tmp: tmp.write_text(obj_text(textured, mtl_name="textured.mtl")))
    extras = {**conversion_extras(), "source": "mesh.ply, decimated", "texture": "albedo, sRGB"}
    result.write_file(
        "textured.glb",
        lambda tmp: write_glb(
            tmp,
            to_gltf_frame(textured.vertices),
            textured.faces,
            normals=to_gltf_frame(textured.normals),
            uvs=textured.uvs,
            texture_png=png,
            extras=extras,
            name="pmvir-textured",
        ),
    )
    h, w = textured.texture.shape[:2]
    return {
        "faces": len(textured.faces),
        "vertices": len(textured.vertices),
        "texture": [int(w), int(h)],
        "coverage": float(textured.coverage.mean()),
    }


def write_refined_outputs(
    result: ResultFolder,
    mesh: Mesh,
    views: Sequence[tuple[str, PolarizationImages]],
    cameras: Sequence[Camera],
    sh: np.ndarray,
    rgb_scale: np.ndarray,
    *,
    config: PipelineConfig,
    progress: Progress,
) -> dict[str, Any]:
    """Residual images, ``mesh.glb`` and the textured meshes of a refined result.

    Args:
        result: the result folder.
        mesh: the refined mesh with albedo.
        views: per registered view its stem and decoded images; cameras: theirs.
        sh, rgb_scale: (V, T) shading coefficients (T = 9, 16 or 25, as refine.lighting.sh_order) and (V, 3) scales of those views.
        config: the run's configuration (``refine`` for the residuals, ``export``).
        progress: reports per file written.

    Returns:
        The ``exports`` section of report.json (residual summary, textured counts, seconds).
    """
    import time

    if mesh.albedo is None:
        raise ValueError("the refined mesh has no albedo")
    albedo = mesh.albedo
    options = config.export
    section: dict[str, Any] = {"seconds": {}}
    with progress.step("residuals", 0.3):
        t = time.perf_counter()
        summary: dict[str, Any] = {}

        def fill(folder: Path) -> None:
            summary.update(
                write_residuals(
                    folder,
                    views,
                    cameras,
                    mesh.vertices,
                    mesh.faces,
                    albedo,
                    sh,
                    rgb_scale,
                    options=config.refine,
                    max_size=options.preview_max_size,
                )
            )

        result.write_folder("residuals", fill)
        section["residuals"] = {k: summary[k] for k in ("intensity", "scale")}
        section["seconds"]["residuals"] = time.perf_counter() - t
    with progress.step("mesh.glb", 0.1):
        t = time.perf_counter()
        write_mesh_glb(result, mesh)
        section["seconds"]["mesh.glb"] = time.perf_counter() - t
    if options.textured:
        with progress.step("textured", 0.6) as p:
            t = time.perf_counter()
            section["textured"] = write_textured(
                result, mesh, face_budget=options.face_budget, texture_size=options.texture_size, progress=p
            )
            section["seconds"]["textured"] = time.perf_counter() - t
    return section
