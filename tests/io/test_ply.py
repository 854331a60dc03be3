"""Spec PLY (section 3): the writer's exact layout, read back by plyfile, Open3D and our reader;
polygon faces and a truncated file still read or fail by name."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from plyfile import PlyData

from pmvir.errors import MeshError
from pmvir.io.ply import Mesh, read_mesh, write_mesh_ply


def _mesh(n: int = 500, f: int = 900) -> Mesh:
    rng = np.random.default_rng(3)
    return Mesh(rng.normal(size=(n, 3)), rng.integers(0, n, (f, 3)), albedo=rng.random((n, 3)))


def test_the_written_file_has_the_spec_properties_and_round_trips(tmp_path: Path) -> None:
    mesh = _mesh()
    write_mesh_ply(tmp_path / "m.ply", mesh)
    ply = PlyData.read(str(tmp_path / "m.ply"))  # the general reader, row by row
    assert [p.name for p in ply["vertex"].properties] == [
        "x", "y", "z", "nx", "ny", "nz", "red", "green", "blue", "albedo_r", "albedo_g", "albedo_b"
    ]
    face_prop = ply["face"].properties[0]
    assert (face_prop.name, face_prop.len_dtype, face_prop.val_dtype) == ("vertex_indices", "u1", "i4")
    assert np.array_equal(np.stack(list(ply["face"].data["vertex_indices"])), mesh.faces)
    back = read_mesh(tmp_path / "m.ply")
    assert np.allclose(back.vertices, mesh.vertices, atol=1e-6)
    assert np.array_equal(back.faces, mesh.faces)
    assert np.array_equal(back.albedo, mesh.albedo)
    normals = np.linalg.norm(back.normals, axis=1)
    assert np.allclose(normals[normals > 0], 1.0, atol=1e-5)


def test_open3d_reads_the_same_triangles(tmp_path: Path) -> None:
    o3d = pytest.importorskip("open3d")
    mesh = _mesh()
    write_mesh_ply(tmp_path / "m.ply", mesh)
    read = o3d.io.read_triangle_mesh(str(tmp_path / "m.ply"))
    assert np.array_equal(np.asarray(read.triangles), mesh.faces)
    assert np.allclose(np.asarray(read.vertices), mesh.vertices, atol=1e-6)


def test_quads_are_fan_triangulated(tmp_path: Path) -> None:
    path = tmp_path / "quad.ply"
    header = "ply\nformat binary_little_endian 1.0\nelement vertex 5\nproperty float x\nproperty float y\n"
    header += "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
    verts = np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0], [2, 0, 0]], "<f4")
    body = verts.tobytes() + np.array([4], "u1").tobytes() + np.array([0, 1, 2, 3], "<i4").tobytes()
    body += np.array([3], "u1").tobytes() + np.array([1, 4, 2], "<i4").tobytes()
    path.write_bytes(header.encode() + body)
    mesh = read_mesh(path)
    assert mesh.faces.tolist() == [[0, 1, 2], [0, 2, 3], [1, 4, 2]]


def test_a_truncated_file_is_named(tmp_path: Path) -> None:
    write_mesh_ply(tmp_path / "m.ply", _mesh())
    data = (tmp_path / "m.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[: len(data) - 100])
    with pytest.raises(MeshError, match=r"cut\.ply"):
        read_mesh(tmp_path / "cut.ply")
