"""Triangle meshes with per-vertex albedo as PLY (spec section 3, `mesh.ply`).

Binary little-endian PLY with vertex properties ``x y z nx ny nz`` (float32),
``red green blue`` (uchar, albedo encoded sRGB for viewers) and
``albedo_r albedo_g albedo_b`` (float32, linear), faces as ``vertex_indices``
(uchar count, int32 indices). Reading also accepts any PLY or OBJ triangle mesh
(e.g. the Stanford models) without albedo.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from pmvir.errors import MeshError
from pmvir.geometry.mesh_ops import vertex_normals


@dataclass
class Mesh:
    """A triangle mesh.

    Attributes:
        vertices: (N, 3) float64 positions.
        faces: (F, 3) int64 vertex indices, counter-clockwise seen from outside.
        albedo: optional (N, 3) float32 linear RGB albedo.
        normals: optional (N, 3) float32 unit normals.
    """

    vertices: np.ndarray
    faces: np.ndarray
    albedo: np.ndarray | None = None
    normals: np.ndarray | None = field(default=None)

    def __post_init__(self) -> None:
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        if self.albedo is not None:
            self.albedo = np.asarray(self.albedo, dtype=np.float32).reshape(-1, 3)
            if len(self.albedo) != len(self.vertices):
                raise MeshError(f"albedo has {len(self.albedo)} rows for {len(self.vertices)} vertices")
        if self.normals is not None:
            self.normals = np.asarray(self.normals, dtype=np.float32).reshape(-1, 3)
        if len(self.faces) and (self.faces.min() < 0 or self.faces.max() >= len(self.vertices)):
            raise MeshError("face indices out of range")




def linear_to_srgb(x: np.ndarray) -> np.ndarray:
    """sRGB encoding of linear values in [0, 1] (clipped), float."""
    x = np.clip(np.asarray(x, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


def write_mesh_ply(path: str | Path, mesh: Mesh) -> None:
    """Write ``mesh`` as spec PLY, atomically (temporary name, then rename)."""
    path = Path(path)
    normals = mesh.normals if mesh.normals is not None else vertex_normals(mesh.vertices, mesh.faces)
    albedo = mesh.albedo if mesh.albedo is not None else np.full((len(mesh.vertices), 3), 0.5, np.float32)
    vdtype = [(n, "<f4") for n in ("x", "y", "z", "nx", "ny", "nz")]
    vdtype += [(n, "u1") for n in ("red", "green", "blue")]
    vdtype += [(n, "<f4") for n in ("albedo_r", "albedo_g", "albedo_b")]
    vert = np.empty(len(mesh.vertices), dtype=vdtype)
    for i, n in enumerate("xyz"):
        vert[n] = mesh.vertices[:, i]
        vert["n" + n] = normals[:, i]
    rgb = np.round(linear_to_srgb(albedo) * 255).astype(np.uint8)
    for i, n in enumerate(("red", "green", "blue")):
        vert[n] = rgb[:, i]
        vert["albedo_" + "rgb"[i]] = albedo[:, i]
    # faces as (uchar 3, int32 a, b, c) records, packed: the bytes of spec PLY's list property,
    # written in one block (plyfile writes list properties row by row)
    face = np.empty(len(mesh.faces), dtype=np.dtype([("count", "u1"), ("abc", "<i4", (3,))], align=False))
    face["count"] = 3
    face["abc"] = mesh.faces
    header = ["ply", "format binary_little_endian 1.0", f"element vertex {len(vert)}"]
    header += [f"property {'float' if t == '<f4' else 'uchar'} {n}" for n, t in vdtype]
    header += [f"element face {len(face)}", "property list uchar int vertex_indices", "end_header"]
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        fh.write(vert.tobytes())
        fh.write(face.tobytes())
    os.replace(tmp, path)


def read_mesh(path: str | Path) -> Mesh:
    """Read a triangle mesh from PLY (with spec albedo if present) or OBJ.

    Raises:
        MeshError: the file is missing, unreadable, or holds no triangles.
    """
    path = Path(path)
    if not path.is_file():
        raise MeshError(f"{path}: no such mesh file")
    suffix = path.suffix.lower()
    try:
        if suffix == ".ply":
            return _read_ply(path)
        if suffix == ".obj":
            return _read_obj(path)
    except MeshError:
        raise
    except Exception as exc:  # plyfile raises several types for corrupt files
        raise MeshError(f"{path}: cannot read mesh ({exc})") from exc
    raise MeshError(f"{path}: unsupported mesh format {suffix!r}; expected .ply or .obj")


def _read_ply(path: Path) -> Mesh:
    from plyfile import PlyData, PlyElementParseError

    try:  # triangle faces in one block (the list length known), not row by row
        ply = PlyData.read(str(path), known_list_len={"face": {"vertex_indices": 3, "vertex_index": 3}})
    except PlyElementParseError:  # polygons of other sizes: the general reader
        ply = PlyData.read(str(path))
    names = [e.name for e in ply.elements]
    if "vertex" not in names or "face" not in names:
        raise MeshError(f"{path}: PLY needs vertex and face elements, has {names}")
    v = ply["vertex"].data
    verts = np.stack([v["x"], v["y"], v["z"]], axis=1).astype(np.float64)
    fprops = [p.name for p in ply["face"].properties]
    key = "vertex_indices" if "vertex_indices" in fprops else ("vertex_index" if "vertex_index" in fprops else None)
    if key is None:
        raise MeshError(f"{path}: face element has no vertex_indices")
    data = ply["face"].data[key]
    if data.dtype != object and data.ndim == 2:  # read as one (F, 3) block
        faces = np.array(data, dtype=np.int64)
        if not len(faces):
            raise MeshError(f"{path}: mesh has no faces")
    else:
        faces = _triangulate(list(data), path)
    vprops = set(v.dtype.names)
    albedo = None
    if {"albedo_r", "albedo_g", "albedo_b"} <= vprops:
        albedo = np.stack([v["albedo_r"], v["albedo_g"], v["albedo_b"]], axis=1)
    normals = None
    if {"nx", "ny", "nz"} <= vprops:
        normals = np.stack([v["nx"], v["ny"], v["nz"]], axis=1)
    return Mesh(verts, faces, albedo=albedo, normals=normals)


def _triangulate(polys: list, path: Path) -> np.ndarray:
    if not polys:
        raise MeshError(f"{path}: mesh has no faces")
    lengths = np.fromiter((len(p) for p in polys), dtype=np.int64, count=len(polys))
    if np.all(lengths == 3):
        return np.asarray(np.stack(polys), dtype=np.int64)
    tris: list[list[int]] = []
    for p in polys:  # fan-triangulate polygons (rare in our inputs)
        p = list(p)
        tris.extend([p[0], p[i], p[i + 1]] for i in range(1, len(p) - 1))
    return np.asarray(tris, dtype=np.int64)


def _read_obj(path: Path) -> Mesh:
    verts, polys = [], []
    with open(path, encoding="utf-8", errors="replace") as fh:
        for line in fh:
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                polys.append([int(tok.split("/")[0]) - 1 for tok in line.split()[1:]])
    if not verts:
        raise MeshError(f"{path}: OBJ has no vertices")
    return Mesh(np.asarray(verts), _triangulate(polys, path))
