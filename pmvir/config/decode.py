"""Options of the decode stage: demosaicing and the polarization quantities."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from pmvir.config.base import DemosaicMethod, _Options, advanced, basic


class DecodeOptions(_Options):
    """Demosaicing and polarization quantities (pipeline stage 1)."""

    noise_floor: float = Field(
        default=0.01, ge=0.0, lt=1.0,
        description="Pixels whose mean intensity (I_int averaged over colours, = s0 / 2, normalized units) "
        "is at or below this are invalid: AoP/DoP are undefined there.",
        json_schema_extra=advanced(),
    )
    demosaic: DemosaicMethod = Field(
        default="guided",
        description="Demosaicing: 'bilinear', 'edge-aware' (OpenCV Bayer step), 'guided' (guided-filter "
        "polarization: less false polarization), 'eari' (edge-aware residual interpolation) or "
        "'eari-guided'.",
        json_schema_extra=basic(),
    )
    dop_estimator: Literal["plain", "unbiased"] = Field(
        default="plain",
        description="DoP from demosaiced Stokes: 'plain' sqrt(s1^2 + s2^2) / s0, or 'unbiased': the noise's "
        "expected share (from the polarizer closure residual) taken out of s1^2 + s2^2 first.",
        json_schema_extra=advanced(),
    )
    max_working_size_px: int = Field(
        default=1024, ge=0, le=100_000,
        description="Longest image side (px) the geometry and refinement stages work at; larger frames are "
        "binned by the smallest integer factor that fits. 0: full resolution.",
        json_schema_extra=advanced("px"),
    )
