"""The one typed configuration tree.

The CLI (`pmvir reconstruct`), the HTTP job options (`POST /v1/jobs`) and the
pipeline all read these models: one place defines each parameter, its default,
its range and its meaning. Unknown keys are errors (``extra="forbid"``).
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field


class _Options(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)


class DecodeOptions(_Options):
    """Demosaicing and polarization quantities (pipeline stage 1)."""

    noise_floor: float = Field(
        default=0.01,
        ge=0.0,
        lt=1.0,
        description="Pixels whose mean intensity I_int (normalized units) is at or below this are "
        "invalid: AoP/DoP are undefined there.",
    )
    demosaic: Literal["bilinear", "edge-aware"] = Field(
        default="edge-aware",
        description="Interpolation used for the Bayer (colour) and polarization steps.",
    )


class PipelineConfig(_Options):
    """Everything a reconstruction run is told."""

    decode: DecodeOptions = Field(default_factory=DecodeOptions)
    stop_after: Literal["decode", "geometry", "refine"] = Field(
        default="refine", description="Last stage to run."
    )
