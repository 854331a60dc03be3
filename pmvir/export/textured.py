"""A decimated, UV-mapped copy of the result with its albedo baked into a texture.

For tools that want a light mesh and an image rather than 300k coloured
vertices (game engines, Blender, web viewers):

1. quadric decimation (Open3D) to at most ``face_budget`` faces;
2. a UV atlas of the decimated mesh (xatlas), no chart over 1 % of its area;
3. baking: every texel covered by a chart is mapped through its triangle to a
   point on the decimated surface, and the albedo there is taken from the
   full-resolution mesh at its closest point (barycentric interpolation of the
   per-vertex albedo), so the texture keeps the detail the decimation removed;
4. padding: texels outside every chart take the mean of their filled
   neighbours, repeated ``padding`` times, so bilinear filtering and mipmaps do
   not bleed background colour across seams.

The texture holds the linear albedo sRGB-encoded (8 bits), as OBJ/MTL readers
and glTF's ``baseColorTexture`` expect.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from pmvir.geometry.mesh_ops import barycentric, face_areas, raycasting_scene, vertex_normals
from pmvir.io.ply import Mesh, linear_to_srgb

#: Sub-pixel bits of the rasterizer (OpenCV's ``shift``).
_SHIFT = 4


@dataclass
class TexturedMesh:
    """A UV-mapped mesh and its albedo texture.

    Attributes:
        vertices: (M, 3) float64 positions (capture world); vertices are split at UV seams.
        faces: (G, 3) int64 indices.
        normals: (M, 3) float64 unit vertex normals.
        uvs: (M, 2) float64 texture coordinates in [0, 1], (0, 0) = the image's top-left corner.
        texture: (H, W, 3) uint8 sRGB albedo, RGB order.
        coverage: (H, W) bool, texels inside a chart (before padding).
    """

    vertices: np.ndarray
    faces: np.ndarray
    normals: np.ndarray
    uvs: np.ndarray
    texture: np.ndarray
    coverage: np.ndarray


def decimate(mesh: Mesh, face_budget: int) -> tuple[np.ndarray, np.ndarray]:
    """Quadric decimation to at most ``face_budget`` faces (the mesh as it is when already below).

    Returns:
        (N', 3) float64 vertices and (F', 3) int64 faces.
    """
    if face_budget < 4:
        raise ValueError(f"face_budget must be at least 4, got {face_budget}")
    if len(mesh.faces) <= face_budget:
        return mesh.vertices.copy(), mesh.faces.copy()
    import open3d as o3d

    o3 = o3d.geometry.TriangleMesh(
        o3d.utility.Vector3dVector(mesh.vertices), o3d.utility.Vector3iVector(mesh.faces.astype(np.int32))
    )
    o3 = o3.simplify_quadric_decimation(target_number_of_triangles=int(face_budget))
    o3.remove_degenerate_triangles()
    o3.remove_unreferenced_vertices()
    return np.asarray(o3.vertices, dtype=np.float64), np.asarray(o3.triangles, dtype=np.int64)


#: The largest share of the mesh's area one UV chart may take. xatlas grows charts as large as their
#: distortion allows, and flattening such charts took nearly all of the export's time: on the demo's
#: refined blob decimated to 100k faces, 65 s without a limit against 6.7 s with this one, at the
#: texels per unit area within 1 % (201 charts instead of 1,316; 59 % of the atlas covered instead of 66 %).
MAX_CHART_SHARE = 0.01


def uv_atlas(
    vertices: np.ndarray, faces: np.ndarray, *, resolution: int, padding: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """xatlas charts and packing.

    Returns:
        vmapping (M,) index of the input vertex each output vertex copies,
        faces (G, 3) int64 into the output vertices, uvs (M, 2) in [0, 1],
        and the atlas size (width, height) in texels.
    """
    import xatlas

    atlas = xatlas.Atlas()
    atlas.add_mesh(np.ascontiguousarray(vertices, np.float32), np.ascontiguousarray(faces, np.uint32))
    charts = xatlas.ChartOptions()
    charts.max_chart_area = MAX_CHART_SHARE * float(face_areas(vertices, faces).sum())
    pack = xatlas.PackOptions()
    pack.resolution = int(resolution)
    pack.padding = int(padding)
    atlas.generate(charts, pack)
    vmapping, indices, uvs = atlas[0]
    return (
        vmapping.astype(np.int64),
        indices.astype(np.int64),
        uvs.astype(np.float64),
        (int(atlas.width), int(atlas.height)),
    )


def rasterize_faces(uv_px: np.ndarray, faces: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Which face covers each texel: (H, W) int32 face index, -1 where none.

    Args:
        uv_px: (M, 2) vertex positions in texel units (x right, y down; texel centres at +0.5).
        faces: (G, 3) indices into ``uv_px``.
        size: (width, height).
    """
    width, height = size
    ids = np.full((height, width), -1, np.int32)
    pts = np.round((uv_px[faces] - 0.5) * (1 << _SHIFT)).astype(np.int32)  # centre of texel (0,0) -> 0
    for g in range(len(faces)):
        cv2.fillConvexPoly(ids, pts[g], int(g), lineType=cv2.LINE_8, shift=_SHIFT)
    return ids


def _barycentric(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Barycentric coordinates (P, 3) of points p (P, 2) in triangles tri (P, 3, 2), clamped to the triangle."""
    bary = np.clip(barycentric(p, tri[:, 0], tri[:, 1], tri[:, 2]), 0.0, None)
    return bary / np.maximum(bary.sum(1, keepdims=True), 1e-12)


def sample_albedo(mesh: Mesh, points: np.ndarray) -> np.ndarray:
    """Linear albedo (P, 3) of ``mesh`` at the surface points closest to ``points`` (P, 3)."""
    import open3d as o3d

    if mesh.albedo is None:
        raise ValueError("the mesh has no albedo")
    local = raycasting_scene(mesh.vertices, mesh.faces)
    albedo = mesh.albedo
    out = np.empty((len(points), 3), np.float32)
    for s in range(0, len(points), 1 << 20):
        q = local.local(points[s : s + (1 << 20)])
        ans = local.scene.compute_closest_points(o3d.core.Tensor.from_numpy(q))
        prim = ans["primitive_ids"].numpy().astype(np.int64)
        uv = ans["primitive_uvs"].numpy().astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)
        out[s : s + len(q)] = np.einsum("pk,pkj->pj", bary, albedo[mesh.faces[prim]])
    return out


def pad_texture(image: np.ndarray, filled: np.ndarray, *, iterations: int) -> np.ndarray:
    """Grow the filled texels outwards: each pass gives every empty texel next to filled ones their mean.

    Args:
        image: (H, W, C) float32.
        filled: (H, W) bool.
        iterations: passes (each grows by one texel).

    Returns:
        (H, W, C) float32; texels still empty afterwards take the mean of the filled ones.
    """
    img = image.astype(np.float32).copy()
    mask = filled.astype(np.float32)
    kernel = np.ones((3, 3), np.float32)
    for _ in range(iterations):
        if mask.all():
            break
        total = cv2.filter2D(img * mask[..., None], -1, kernel, borderType=cv2.BORDER_CONSTANT)
        count = cv2.filter2D(mask, -1, kernel, borderType=cv2.BORDER_CONSTANT)
        grow = (mask == 0) & (count > 0)
        img[grow] = total[grow] / count[grow][:, None]
        mask[grow] = 1.0
    if filled.any():
        img[mask == 0] = img[filled].mean(axis=0)
    return img


def bake_textured(
    mesh: Mesh, *, face_budget: int = 100_000, texture_size: int = 2048, padding: int = 8
) -> TexturedMesh:
    """Decimate ``mesh``, give it a UV atlas and bake its per-vertex albedo into a texture.

    Args:
        mesh: a result mesh with per-vertex linear albedo.
        face_budget: most faces of the output.
        texture_size: the atlas resolution asked of xatlas (its charts are packed into about this many
            texels per side).
        padding: texels between charts, and passes of seam padding.

    Returns:
        The textured mesh (vertices in the capture world's frame).
    """
    if mesh.albedo is None:
        raise ValueError("the mesh has no albedo to bake")
    dv, df = decimate(mesh, face_budget)
    vmapping, faces, uvs, (width, height) = uv_atlas(
        dv, df, resolution=texture_size, padding=max(padding // 2, 1)
    )
    vertices = dv[vmapping]
    normals = vertex_normals(dv, df)[vmapping]
    uv_px = uvs * np.array([width, height], np.float64)
    ids = rasterize_faces(uv_px, faces, (width, height))
    rows, cols = np.nonzero(ids >= 0)
    g = ids[rows, cols].astype(np.int64)
    centres = np.stack([cols + 0.5, rows + 0.5], axis=1)
    bary = _barycentric(centres, uv_px[faces[g]])
    points = np.einsum("pk,pkj->pj", bary, vertices[faces[g]])
    linear = np.zeros((height, width, 3), np.float32)
    linear[rows, cols] = sample_albedo(mesh, points)
    coverage = ids >= 0
    linear = pad_texture(linear, coverage, iterations=padding)
    texture = np.round(linear_to_srgb(linear) * 255.0).astype(np.uint8)
    return TexturedMesh(vertices, faces, normals, uvs, texture, coverage)


def obj_text(textured: TexturedMesh, *, mtl_name: str) -> str:
    """``textured.obj``: v, vt, vn and ``f v/vt/vn``, using material ``albedo`` of ``mtl_name``.

    OBJ's texture origin is the image's bottom-left corner, so ``vt`` is ``(u, 1 - v)``.
    """
    v = textured.vertices
    vt = np.column_stack([textured.uvs[:, 0], 1.0 - textured.uvs[:, 1]])
    f = textured.faces + 1
    return (
        "\n".join(
            [
                f"# pmvir textured mesh: {len(v)} vertices, {len(f)} faces",
                f"mtllib {mtl_name}",
                "usemtl albedo",
                *(f"v {a:.7g} {b:.7g} {c:.7g}" for a, b, c in v),
                *(f"vt {a:.7g} {b:.7g}" for a, b in vt),
                *(f"vn {a:.6g} {b:.6g} {c:.6g}" for a, b, c in textured.normals),
                *(f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}" for a, b, c in f),
            ]
        )
        + "\n"
    )


def mtl_text(texture_name: str) -> str:
    """The ``.mtl`` of :func:`obj_text`: a diffuse material whose colour is the texture."""
    return (
        "# pmvir: the albedo baked into a texture (sRGB); no specular part\n"
        "newmtl albedo\nKa 0 0 0\nKd 1 1 1\nKs 0 0 0\nNs 0\nd 1\nillum 1\n"
        f"map_Kd {texture_name}\n"
    )


def encode_png(image: np.ndarray) -> bytes:
    """PNG bytes of an (H, W, 3) uint8 RGB image."""
    ok, buf = cv2.imencode(".png", cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover - OpenCV failure
        raise OSError("could not encode the texture as PNG")
    return buf.tobytes()


def bake_textured_in_child(
    mesh: Mesh,
    *,
    face_budget: int,
    texture_size: int,
    workdir: Path,
    should_stop: Callable[[], None] | None = None,
    poll_seconds: float = 0.5,
) -> TexturedMesh:
    """:func:`bake_textured` in a child Python process.

    xatlas and Open3D's decimation hold the GIL for tens of seconds on large
    meshes; in a child process they leave the caller's threads (a worker's
    heartbeat) running, and the bake can be stopped: ``should_stop()`` is called
    every ``poll_seconds`` and may raise (e.g. ``CanceledError``), which kills the child.

    Args:
        mesh: a mesh with per-vertex albedo.
        face_budget, texture_size: as :func:`bake_textured`.
        workdir: a folder for the two .npz files that carry the mesh and the answer.
        should_stop: called while waiting; raising stops the bake.
        poll_seconds: how often it is called.

    Raises:
        ReconstructionError: the child failed (its last output lines are in the message).
    """
    import subprocess
    import sys

    from pmvir.errors import ReconstructionError

    if mesh.albedo is None:
        raise ValueError("the mesh has no albedo to bake")
    src, dst = workdir / "bake-in.npz", workdir / "bake-out.npz"
    np.savez(src, vertices=mesh.vertices, faces=mesh.faces, albedo=mesh.albedo)
    argv = [
        sys.executable,
        "-m",
        "pmvir.export.textured",
        str(src),
        str(dst),
        str(face_budget),
        str(texture_size),
    ]
    with subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True) as child:
        try:
            while True:
                try:
                    _, err = child.communicate(timeout=poll_seconds)
                    break
                except subprocess.TimeoutExpired:
                    if should_stop is not None:
                        should_stop()
        except BaseException:
            child.kill()
            raise
    if child.returncode != 0 or not dst.is_file():
        tail = "\n".join(err.strip().splitlines()[-5:])
        raise ReconstructionError(f"baking the textured export failed (exit {child.returncode}): {tail}")
    with np.load(dst) as d:
        return TexturedMesh(
            d["vertices"], d["faces"], d["normals"], d["uvs"], d["texture"], d["coverage"].astype(bool)
        )


def _child_main(argv: list[str]) -> int:
    """``python -m pmvir.export.textured IN.npz OUT.npz FACE_BUDGET TEXTURE_SIZE`` (see :func:`bake_textured_in_child`)."""
    src, dst, budget, size = argv
    with np.load(src) as d:
        mesh = Mesh(d["vertices"], d["faces"], albedo=d["albedo"])
    t = bake_textured(mesh, face_budget=int(budget), texture_size=int(size))
    tmp = Path(dst).with_name(Path(dst).name + ".part.npz")
    np.savez(
        tmp,
        vertices=t.vertices,
        faces=t.faces,
        normals=t.normals,
        uvs=t.uvs,
        texture=t.texture,
        coverage=t.coverage,
    )
    tmp.replace(dst)
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(_child_main(sys.argv[1:]))
