"""glTF 2.0 binary (``.glb``) writer for one triangle mesh, with no dependency beyond NumPy.

glTF is +Y up; pmvir's capture world has no fixed up axis, but the synthetic
captures and most rigs put it at +Z. The exporter therefore turns the capture
world into glTF's frame with :data:`GLTF_FROM_CAPTURE` (a rotation of -90
degrees about X: ``(x, y, z) -> (x, z, -y)``) and states that matrix in the
file's ``asset.extras.pmvir`` so that a reader can undo it.

Written per vertex: ``POSITION`` (float32, with min/max), ``NORMAL`` (float32,
unit), optionally ``COLOR_0`` (float32 linear RGB: glTF vertex colours are
linear) and ``TEXCOORD_0`` (float32, origin at the image's top-left corner);
triangles as uint32 indices. One material, fully rough and non-metallic, whose
base colour is the vertex colour or an embedded PNG (sRGB, as glTF requires).
"""

from __future__ import annotations

import json
import os
import struct
from pathlib import Path
from typing import Any

import numpy as np

#: Rotation taking capture-world coordinates (+Z up) to glTF coordinates (+Y up).
GLTF_FROM_CAPTURE = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])

_FLOAT, _UINT = 5126, 5125
_ARRAY_BUFFER, _ELEMENT_ARRAY_BUFFER = 34962, 34963


def to_gltf_frame(points: np.ndarray) -> np.ndarray:
    """Capture-world points or directions (N, 3) in glTF's +Y-up frame, (N, 3) float64.

    >>> to_gltf_frame(np.array([[0.0, 0.0, 1.0]])).tolist()
    [[0.0, 1.0, 0.0]]
    """
    return np.asarray(points, dtype=np.float64).reshape(-1, 3) @ GLTF_FROM_CAPTURE.T


def conversion_extras() -> dict[str, Any]:
    """What ``asset.extras.pmvir`` says about the frame and units of the file."""
    return {
        "up": "+Y",
        "gltf_from_capture": GLTF_FROM_CAPTURE.tolist(),
        "conversion": "capture world (x, y, z) with +Z up -> glTF (x, z, -y); multiply by the transpose "
        "of gltf_from_capture to go back. Units are the capture world's.",
    }


class _Builder:
    """Accumulates buffer views and accessors in one binary buffer (4-byte aligned)."""

    def __init__(self) -> None:
        self.blob = bytearray()
        self.views: list[dict[str, Any]] = []
        self.accessors: list[dict[str, Any]] = []

    def view(self, data: bytes, target: int | None = None) -> int:
        while len(self.blob) % 4:
            self.blob.append(0)
        entry: dict[str, Any] = {"buffer": 0, "byteOffset": len(self.blob), "byteLength": len(data)}
        if target is not None:
            entry["target"] = target
        self.blob += data
        self.views.append(entry)
        return len(self.views) - 1

    def accessor(self, array: np.ndarray, kind: str, *, target: int, bounds: bool = False) -> int:
        ctype = _UINT if array.dtype == np.uint32 else _FLOAT
        entry: dict[str, Any] = {
            "bufferView": self.view(np.ascontiguousarray(array).tobytes(), target),
            "componentType": ctype,
            "count": len(array),
            "type": kind,
        }
        if bounds:
            entry["min"] = array.min(axis=0).tolist()
            entry["max"] = array.max(axis=0).tolist()
        self.accessors.append(entry)
        return len(self.accessors) - 1


def write_glb(
    path: str | Path,
    vertices: np.ndarray,
    faces: np.ndarray,
    *,
    normals: np.ndarray,
    colors: np.ndarray | None = None,
    uvs: np.ndarray | None = None,
    texture_png: bytes | None = None,
    extras: dict[str, Any] | None = None,
    name: str = "pmvir",
) -> Path:
    """Write one triangle mesh as a ``.glb``, atomically (temporary name, then rename).

    Coordinates are written as given: convert them first (:func:`to_gltf_frame`).

    Args:
        path: the file to write.
        vertices: (N, 3) positions in glTF's frame.
        faces: (F, 3) vertex indices, counter-clockwise seen from outside.
        normals: (N, 3) normals in glTF's frame (normalized here; zero ones become +Y).
        colors: optional (N, 3) linear RGB in [0, 1] (clipped), written as ``COLOR_0``.
        uvs: optional (N, 2) texture coordinates, (0, 0) = the image's top-left corner.
        texture_png: PNG bytes of the base-colour texture (sRGB); needs ``uvs``.
        extras: stored as ``asset.extras.pmvir``.
        name: the mesh's and node's name.

    Returns:
        ``path``.
    """
    v = np.asarray(vertices, dtype=np.float32).reshape(-1, 3)
    f = np.asarray(faces, dtype=np.uint32).reshape(-1)
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    if len(n) != len(v):
        raise ValueError(f"normals has {len(n)} rows for {len(v)} vertices")
    if len(f) and int(f.max()) >= len(v):
        raise ValueError("face indices out of range")
    if texture_png is not None and uvs is None:
        raise ValueError("a texture needs uvs")
    length = np.linalg.norm(n, axis=1, keepdims=True)
    n = np.where(length > 1e-12, n / np.maximum(length, 1e-12), np.array([0.0, 1.0, 0.0]))
    b = _Builder()
    attributes = {
        "POSITION": b.accessor(v, "VEC3", target=_ARRAY_BUFFER, bounds=True),
        "NORMAL": b.accessor(n.astype(np.float32), "VEC3", target=_ARRAY_BUFFER),
    }
    if colors is not None:
        c = np.clip(np.asarray(colors, dtype=np.float32).reshape(-1, 3), 0.0, 1.0)
        attributes["COLOR_0"] = b.accessor(c, "VEC3", target=_ARRAY_BUFFER)
    if uvs is not None:
        attributes["TEXCOORD_0"] = b.accessor(
            np.asarray(uvs, dtype=np.float32).reshape(-1, 2), "VEC2", target=_ARRAY_BUFFER
        )
    indices = b.accessor(f, "SCALAR", target=_ELEMENT_ARRAY_BUFFER)
    pbr: dict[str, Any] = {
        "baseColorFactor": [1.0, 1.0, 1.0, 1.0],
        "metallicFactor": 0.0,
        "roughnessFactor": 1.0,
    }
    doc: dict[str, Any] = {
        "asset": {"version": "2.0", "generator": "pmvir", "extras": {"pmvir": extras or {}}},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0, "name": name}],
        "meshes": [
            {"name": name, "primitives": [{"attributes": attributes, "indices": indices, "material": 0}]}
        ],
        "materials": [{"name": "albedo", "pbrMetallicRoughness": pbr, "doubleSided": False}],
    }
    if texture_png is not None:
        image_view = b.view(texture_png)
        doc["images"] = [{"bufferView": image_view, "mimeType": "image/png"}]
        doc["samplers"] = [{"magFilter": 9729, "minFilter": 9987, "wrapS": 33071, "wrapT": 33071}]
        doc["textures"] = [{"sampler": 0, "source": 0}]
        pbr["baseColorTexture"] = {"index": 0, "texCoord": 0}
    while len(b.blob) % 4:
        b.blob.append(0)
    doc["buffers"] = [{"byteLength": len(b.blob)}]
    doc["bufferViews"] = b.views
    doc["accessors"] = b.accessors
    text = json.dumps(doc, separators=(",", ":")).encode()
    text += b" " * (-len(text) % 4)
    total = 12 + 8 + len(text) + 8 + len(b.blob)
    path = Path(path)
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(struct.pack("<4sII", b"glTF", 2, total))
        fh.write(struct.pack("<I4s", len(text), b"JSON"))
        fh.write(text)
        fh.write(struct.pack("<I4s", len(b.blob), b"BIN\x00"))
        fh.write(bytes(b.blob))
    os.replace(tmp, path)
    return path


def read_glb_json(path: str | Path) -> dict[str, Any]:
    """The JSON chunk of a ``.glb`` (for tests and tools)."""
    data = Path(path).read_bytes()
    magic, version, _ = struct.unpack_from("<4sII", data, 0)
    if magic != b"glTF" or version != 2:
        raise ValueError(f"{path}: not a glTF 2.0 binary")
    length, kind = struct.unpack_from("<I4s", data, 12)
    if kind != b"JSON":
        raise ValueError(f"{path}: the first chunk is not JSON")
    return json.loads(data[20 : 20 + length])
