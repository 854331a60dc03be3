"""The one typed configuration tree.

The CLI (`pmvir reconstruct`), the HTTP job options (`POST /v1/jobs`) and the
pipeline all read these models: one place defines each parameter, its default,
its range and its meaning. Unknown keys are errors (``extra="forbid"``).
"""

from __future__ import annotations

from pydantic import Field

from pmvir.config.base import OPTION_MAGNITUDE_LIMIT, DemosaicMethod, _Options, basic, merge_options
from pmvir.config.catalog import OptionInfo, nearest_option, option_catalog
from pmvir.config.decode import DecodeOptions
from pmvir.config.export import ExportOptions
from pmvir.config.geometry import (
    GeometryOptions,
    MvsOptions,
    SubdivisionOptions,
    SurfaceOptions,
    VisibilityOptions,
)
from pmvir.config.refine import (
    LightingOptions,
    OffsetScanOptions,
    PhoOptions,
    PolOptions,
    RefineOptions,
    SolverOptions,
    StageOptions,
    SurfaceMoveOptions,
    ViewOptions,
)
from pmvir.config.sfm import SfmOptions
from pmvir.stages import Stage

__all__ = [
    "OPTION_MAGNITUDE_LIMIT",
    "DecodeOptions",
    "DemosaicMethod",
    "ExportOptions",
    "GeometryOptions",
    "LightingOptions",
    "MvsOptions",
    "OffsetScanOptions",
    "OptionInfo",
    "PhoOptions",
    "PipelineConfig",
    "PolOptions",
    "RefineOptions",
    "SfmOptions",
    "SolverOptions",
    "StageOptions",
    "SubdivisionOptions",
    "SurfaceMoveOptions",
    "SurfaceOptions",
    "ViewOptions",
    "VisibilityOptions",
    "merge_options",
    "nearest_option",
    "option_catalog",
]


class PipelineConfig(_Options):
    """Everything a reconstruction run is told."""

    decode: DecodeOptions = Field(default_factory=DecodeOptions)
    geometry: GeometryOptions = Field(default_factory=GeometryOptions)
    refine: RefineOptions = Field(default_factory=RefineOptions)
    export: ExportOptions = Field(default_factory=ExportOptions)
    stop_after: Stage = Field(
        default=Stage.REFINE,
        description="Last stage to run.",
        json_schema_extra=basic(),
    )
