"""Fixtures of the export tests: a small closed mesh with a known albedo field."""

from __future__ import annotations

import numpy as np
import pytest
from export_helpers import albedo_field

from pmvir.io.ply import Mesh


@pytest.fixture(scope="session")
def sphere_mesh() -> Mesh:
    """An Open3D sphere of radius 1 (about 20k faces) with :func:`albedo_field` per vertex."""
    import open3d as o3d

    s = o3d.geometry.TriangleMesh.create_sphere(1.0, resolution=60)
    v = np.asarray(s.vertices, dtype=np.float64)
    f = np.asarray(s.triangles, dtype=np.int64)
    return Mesh(v, f, albedo=albedo_field(v), normals=v / np.linalg.norm(v, axis=1, keepdims=True))
