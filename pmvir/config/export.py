"""Options of the files written beside the result."""

from __future__ import annotations

from pydantic import Field

from pmvir.config.base import _Options, advanced, basic


class ExportOptions(_Options):
    """Files written beside the result for people and other tools (previews, residuals, glTF, OBJ)."""

    textured: bool = Field(
        default=True,
        description="Write textured.glb and textured.obj/.mtl/_albedo.png: the refined mesh decimated to "
        "face_budget faces, UV-mapped with xatlas and its albedo baked into a texture.",
        json_schema_extra=basic(),
    )
    face_budget: int = Field(
        default=100_000, ge=100, le=5_000_000,
        description="Most faces of the textured meshes.",
        json_schema_extra=basic(),
    )
    texture_size: int = Field(
        default=2048, ge=64, le=8192,
        description="Texels per side the UV atlas is packed into (about).",
        json_schema_extra=advanced("texels"),
    )
    preview_max_size: int = Field(
        default=512, ge=32, le=4096,
        description="Widest per-view preview and residual image (frames are reduced by an integer factor).",
        json_schema_extra=advanced("px"),
    )
