"""Exports of a result: mesh.glb, textured.glb/.obj/.mtl/.png, previews and residual images."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest
from export_helpers import albedo_field, validate

from pmvir.export import write_mesh_glb, write_textured
from pmvir.export.glb import GLTF_FROM_CAPTURE, read_glb_json, to_gltf_frame
from pmvir.export.textured import pad_texture, rasterize_faces
from pmvir.export.views import diverging, reduce_mean, reduced_camera, reduction_factor
from pmvir.io.ply import Mesh, read_mesh
from pmvir.result import RESULT_FILES, ResultFolder


def _accessor(path: Path, doc: dict, index: int) -> np.ndarray:
    """Read an accessor of a .glb back (float32 VEC3/VEC2 or uint32 SCALAR)."""
    data = path.read_bytes()
    json_len = struct.unpack_from("<I", data, 12)[0]
    bin_start = 20 + json_len + 8
    acc = doc["accessors"][index]
    view = doc["bufferViews"][acc["bufferView"]]
    width = {"VEC3": 3, "VEC2": 2, "SCALAR": 1}[acc["type"]]
    dtype = np.uint32 if acc["componentType"] == 5125 else np.float32
    start = bin_start + view["byteOffset"]
    return np.frombuffer(data, dtype=dtype, count=acc["count"] * width, offset=start).reshape(
        acc["count"], width
    )


def test_every_export_is_registered_in_the_result_table() -> None:
    names = {f.name for f in RESULT_FILES}
    for name in ("mesh.glb", "textured.glb", "textured.obj", "textured.mtl", "textured_albedo.png"):
        assert name in names
    assert "previews/" in names and "residuals/" in names


def test_mesh_glb_is_valid_and_holds_every_vertex_turned_to_y_up(sphere_mesh: Mesh, tmp_path: Path) -> None:
    # a mesh whose +Z pole is marked, to check the turn to +Y up
    result = ResultFolder(tmp_path)
    write_mesh_glb(result, sphere_mesh)
    path = tmp_path / "mesh.glb"
    report = validate(path)
    assert report["errors"] == 0, report["messages"]
    assert report["warnings"] == 0, report["messages"]
    doc = read_glb_json(path)
    prim = doc["meshes"][0]["primitives"][0]
    pos = _accessor(path, doc, prim["attributes"]["POSITION"])
    col = _accessor(path, doc, prim["attributes"]["COLOR_0"])
    nrm = _accessor(path, doc, prim["attributes"]["NORMAL"])
    idx = _accessor(path, doc, prim["indices"]).reshape(-1, 3)
    assert len(pos) == len(sphere_mesh.vertices) and len(idx) == len(sphere_mesh.faces)
    np.testing.assert_array_equal(idx, sphere_mesh.faces)
    # +Y up: the capture's +Z pole is the glTF +Y pole; the stated matrix undoes the turn
    top = int(np.argmax(sphere_mesh.vertices[:, 2]))
    np.testing.assert_allclose(pos[top], [0.0, 1.0, 0.0], atol=1e-6)
    m = np.array(doc["asset"]["extras"]["pmvir"]["gltf_from_capture"])
    np.testing.assert_allclose(m, GLTF_FROM_CAPTURE)
    np.testing.assert_allclose(pos @ m, sphere_mesh.vertices, atol=1e-6)  # back: p_capture = M^T p_gltf
    np.testing.assert_allclose(col, sphere_mesh.albedo, atol=1e-7)  # linear, as glTF's COLOR_0 is
    np.testing.assert_allclose(np.linalg.norm(nrm, axis=1), 1.0, atol=1e-6)
    np.testing.assert_allclose(nrm, to_gltf_frame(sphere_mesh.normals), atol=1e-6)


def test_textured_exports_validate_and_their_texture_matches_the_ply_albedo(
    sphere_mesh: Mesh, tmp_path: Path
) -> None:
    import trimesh

    result = ResultFolder(tmp_path)
    result.write_mesh("mesh.ply", sphere_mesh)
    counts = write_textured(result, sphere_mesh, face_budget=4000, texture_size=512)
    assert counts["faces"] <= 4000 and counts["faces"] > 3000
    report = validate(tmp_path / "textured.glb")
    assert report["errors"] == 0, report["messages"]
    assert report["info"]["hasTextures"]
    assert "map_Kd textured_albedo.png" in (tmp_path / "textured.mtl").read_text()

    loaded = trimesh.load(tmp_path / "textured.obj", process=False, force="mesh")
    image = np.asarray(loaded.visual.material.image.convert("RGB"), dtype=np.float64) / 255.0
    assert image.shape[:2] == tuple(reversed(counts["texture"]))
    # sample the texture at points inside every face (centroids, in UV and in 3-D) and compare with the
    # albedo the PLY holds there: the full mesh's per-vertex albedo interpolated at the closest point
    uv = loaded.visual.uv[loaded.faces].mean(axis=1)
    points = loaded.vertices[loaded.faces].mean(axis=1)
    h, w = image.shape[:2]
    px = np.clip((uv[:, 0] * w).astype(int), 0, w - 1)
    py = np.clip(((1.0 - uv[:, 1]) * h).astype(int), 0, h - 1)
    srgb = image[py, px]
    linear = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    ply = read_mesh(tmp_path / "mesh.ply")
    expected = albedo_field(points / np.linalg.norm(points, axis=1, keepdims=True))
    from pmvir.export.textured import sample_albedo

    from_ply = sample_albedo(ply, points)
    assert np.abs(from_ply - expected).mean() < 0.01  # the PLY's albedo is the field
    err = np.abs(linear - from_ply)
    assert np.median(err) < 0.01, np.median(err)
    assert np.percentile(err, 95) < 0.04, np.percentile(err, 95)


def test_textured_keeps_small_meshes_whole(sphere_mesh: Mesh, tmp_path: Path) -> None:
    result = ResultFolder(tmp_path)
    counts = write_textured(result, sphere_mesh, face_budget=10**6, texture_size=256)
    assert counts["faces"] == len(sphere_mesh.faces)


def test_padding_fills_seams_from_the_chart_side() -> None:
    img = np.zeros((8, 8, 3), np.float32)
    filled = np.zeros((8, 8), bool)
    img[2:4, 2:4] = [1.0, 0.5, 0.25]
    filled[2:4, 2:4] = True
    out = pad_texture(img, filled, iterations=2)
    np.testing.assert_allclose(out[1, 1], [1.0, 0.5, 0.25])  # grown in from the chart
    np.testing.assert_allclose(out[0, 7], [1.0, 0.5, 0.25])  # beyond the passes: the mean colour
    np.testing.assert_array_equal(out[2:4, 2:4], img[2:4, 2:4])


def test_rasterizer_covers_a_triangle_and_nothing_else() -> None:
    uv_px = np.array([[1.0, 1.0], [9.0, 1.0], [1.0, 9.0]])
    ids = rasterize_faces(uv_px, np.array([[0, 1, 2]]), (12, 12))
    assert ids[2, 2] == 0 and ids[10, 10] == -1 and ids[0, 11] == -1
    inside = (ids == 0).sum()
    assert 25 <= inside <= 45  # area 32 texels


def test_reduced_camera_keeps_pixel_centres_exact() -> None:
    from pmvir.camera import Camera

    cam = Camera(
        K=np.array([[100.0, 0, 40], [0, 110.0, 30], [0, 0, 1]]),
        R=np.eye(3),
        t=np.zeros(3),
        width=80,
        height=60,
    )
    small = reduced_camera(cam, 4)
    assert (small.width, small.height) == (20, 15)
    p = np.array([[0.1, -0.2, 2.0]])
    uv, _ = cam.project(p)
    uv4, _ = small.project(p)
    np.testing.assert_allclose(uv4, uv / 4.0)
    assert reduction_factor(2448, 512) == 5
    np.testing.assert_allclose(reduce_mean(np.arange(16.0).reshape(4, 4), 2), [[2.5, 4.5], [10.5, 12.5]])


def test_diverging_map_is_blue_white_red() -> None:
    out = diverging(np.array([[-1.0, 0.0, 1.0, 5.0]]), 1.0, np.array([[True, True, True, False]]))
    assert out[0, 0].tolist() == [0, 0, 255] and out[0, 1].tolist() == [255, 255, 255]
    assert out[0, 2].tolist() == [255, 0, 0] and out[0, 3].tolist() == [0, 0, 0]


@pytest.mark.parametrize("name", ["previews/", "residuals/"])
def test_folders_are_zipped_for_download(name: str) -> None:
    from pmvir.result import result_file

    assert result_file(name).download_name == name.rstrip("/") + ".zip"


def test_the_bake_runs_in_a_child_that_a_cancel_stops(sphere_mesh: Mesh, tmp_path: Path) -> None:
    from pmvir.errors import CanceledError
    from pmvir.export.textured import bake_textured_in_child

    calls = []

    def stop() -> None:
        calls.append(1)
        raise CanceledError("canceled during the bake")

    with pytest.raises(CanceledError):
        bake_textured_in_child(
            sphere_mesh,
            face_budget=4000,
            texture_size=512,
            workdir=tmp_path,
            should_stop=stop,
            poll_seconds=0.05,
        )
    assert calls == [1] and not (tmp_path / "bake-out.npz").exists()


def test_no_uv_chart_covers_more_than_its_share_of_the_surface(sphere_mesh: Mesh) -> None:
    """xatlas flattens charts as large as their distortion allows, which took nearly all of the
    export's time; the atlas is made of charts of at most MAX_CHART_SHARE of the area each."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    from pmvir.export.textured import MAX_CHART_SHARE, uv_atlas
    from pmvir.geometry.mesh_ops import face_areas

    vmapping, faces, uvs, _ = uv_atlas(sphere_mesh.vertices, sphere_mesh.faces, resolution=512, padding=2)
    area = face_areas(sphere_mesh.vertices[vmapping], faces)
    # a chart: the faces joined through the atlas's vertices (a seam splits a vertex in two)
    rows = np.repeat(np.arange(len(faces)), 3)
    link = coo_matrix((np.ones(rows.size), (rows, faces.reshape(-1))), shape=(len(faces), len(uvs))).tocsr()
    n, label = connected_components(link @ link.T, directed=False)
    share = np.bincount(label, weights=area) / area.sum()
    assert n > 1 / MAX_CHART_SHARE  # without the limit the sphere is a handful of charts
    assert share.max() <= 1.05 * MAX_CHART_SHARE, share.max()
