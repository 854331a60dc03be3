"""Options of the decode stage: demosaicing and the polarization quantities."""

from __future__ import annotations

from pydantic import Field

from pmvir.config.base import DemosaicMethod, _Options


class DecodeOptions(_Options):
    """Demosaicing and polarization quantities (pipeline stage 1)."""

    noise_floor: float = Field(
        default=0.01,
        ge=0.0,
        lt=1.0,
        description="Pixels whose mean intensity (I_int averaged over colours, = s0 / 2, normalized "
        "units) is at or below this are invalid: AoP/DoP are undefined there.",
    )
    demosaic: DemosaicMethod = Field(
        default="guided",
        description="Demosaicing method: 'bilinear' (per-angle Bayer then polarization interpolation, "
        "float32), 'edge-aware' (OpenCV's edge-aware Bayer step, 16-bit, then bilinear), 'guided' "
        "(bilinear intensity; the colour-mean polarization from a guided filter with the intensity as "
        "guide, windows weighted by their fitting error: much less false polarization from texture and "
        "noise, reach 13 px around saturated samples), 'eari' (Morimatsu et al.'s edge-aware residual "
        "interpolation: every angle and colour from an edge-aware guide; keeps each sample and its "
        "noise, reach 16 px) or 'eari-guided' (EARI, then the guided polarization step; reach 27 px). "
        "Measured in bench/demosaic.py. Monochrome sensors: no colour step.",
    )
    max_working_size_px: int = Field(
        default=1024,
        ge=0,
        le=100_000,
        description="Longest image side (px) the geometry and refinement stages work at; larger frames "
        "are binned by the smallest integer factor that fits. 0: full resolution.",
        json_schema_extra={"level": "advanced", "unit": "px"},
    )
