"""Per-frame lighting as ``illumination.json`` (spec section 3, "pmvir-illumination/1")."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from pmvir.errors import PmvirError
from pmvir.sh import SH_BASIS_NAME


class FrameLighting(BaseModel):
    """Lighting of one frame: S(N) = sh . basis(N), colour = albedo * S * rgb_scale."""

    model_config = ConfigDict(extra="forbid")
    file: str = Field(description="The frame's file, as in capture.json")
    sh: list[float] = Field(min_length=9, max_length=9, description="pmvir-sh9 coefficients L0..L8")
    rgb_scale: list[float] = Field(min_length=3, max_length=3, description="RGB colour scale LR, LG, LB")
    sh_high: list[float] | None = Field(
        default=None,
        min_length=7,
        max_length=16,
        description="Only when the refinement fitted a richer shading (refine.lighting.sh_order 3 or 4): the "
        "coefficients of pmvir.sh.sh_basis's degree-3 (7) and degree-4 (9) terms. They are orthogonal to "
        "pmvir-sh9 over the sphere, so 'sh' is the least-squares pmvir-sh9 part of the full shading.",
    )


class Illumination(BaseModel):
    """The whole file."""

    model_config = ConfigDict(extra="forbid")
    format: str = Field(default="pmvir-illumination/1", pattern=r"^pmvir-illumination/1$")
    sh_basis: str = Field(default=SH_BASIS_NAME, pattern=rf"^{SH_BASIS_NAME}$")
    frame: str = Field(default="world", pattern=r"^world$")
    frames: list[FrameLighting]

    def sh_array(self) -> np.ndarray:
        """(n_frames, 9) float64 coefficients."""
        return np.array([f.sh for f in self.frames], dtype=np.float64).reshape(-1, 9)

    def scale_array(self) -> np.ndarray:
        """(n_frames, 3) float64 RGB scales."""
        return np.array([f.rgb_scale for f in self.frames], dtype=np.float64).reshape(-1, 3)


def illumination_from_arrays(
    files: list[str], sh: np.ndarray, rgb_scale: np.ndarray, sh_high: np.ndarray | None = None
) -> Illumination:
    """Build the document from (n, 9) coefficients, (n, 3) scales and, for a shading richer than
    pmvir-sh9, its (n, 7) or (n, 16) degree-3/4 coefficients (None or (n, 0): none)."""
    sh = np.asarray(sh, dtype=np.float64).reshape(len(files), 9)
    rgb_scale = np.asarray(rgb_scale, dtype=np.float64).reshape(len(files), 3)
    high: list[list[float] | None] = [None] * len(files)
    if sh_high is not None and np.size(sh_high) > 0:
        high = [list(row) for row in np.asarray(sh_high, dtype=np.float64).reshape(len(files), -1)]
    return Illumination(
        frames=[
            FrameLighting(file=f, sh=s.tolist(), rgb_scale=c.tolist(), sh_high=h)
            for f, s, c, h in zip(files, sh, rgb_scale, high, strict=True)
        ]
    )


def write_illumination(path: str | Path, illum: Illumination) -> None:
    """Write atomically (temporary name, then rename)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(json.dumps(illum.model_dump(exclude_none=True), indent=1))
    os.replace(tmp, path)


def read_illumination(path: str | Path) -> Illumination:
    """Read and validate; raises PmvirError naming the file and the problem."""
    path = Path(path)
    try:
        return Illumination.model_validate_json(path.read_bytes())
    except FileNotFoundError as exc:
        raise PmvirError(f"{path}: no such illumination file") from exc
    except ValidationError as exc:
        raise PmvirError(f"{path}: not a pmvir-illumination/1 document: {exc}") from exc
