"""The base of every options model: unknown keys are errors, numbers are finite and bounded."""

from __future__ import annotations

import math
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, field_validator
from pydantic.json_schema import JsonDict

#: No numeric option accepts a magnitude above this (fields state narrower ranges of their own).
OPTION_MAGNITUDE_LIMIT = 1e9


class _Options(BaseModel):
    model_config = ConfigDict(extra="forbid", validate_assignment=True)

    @field_validator("*", mode="after")
    @classmethod
    def _finite_and_bounded(cls, value: Any) -> Any:
        """Every number (and every number in a list) is finite and within +-OPTION_MAGNITUDE_LIMIT."""
        numbers = value if isinstance(value, list) else [value]
        for x in numbers:
            is_number = isinstance(x, (int, float)) and not isinstance(x, bool)
            if is_number and (not math.isfinite(x) or abs(x) > OPTION_MAGNITUDE_LIMIT):
                raise ValueError(f"{x!r} is out of range; no option accepts a magnitude above 1e9")
        return value


#: The option levels: "basic" options are the few a user sets; "advanced" ones tune a step.
Level = Literal["basic", "advanced"]


def basic(unit: str | None = None) -> JsonDict:
    """A field's ``json_schema_extra``: an option a user sets (at most 15 of these), with its unit."""
    return {"level": "basic"} if unit is None else {"level": "basic", "unit": unit}


def advanced(unit: str | None = None) -> JsonDict:
    """A field's ``json_schema_extra``: an option that tunes a step, with its unit."""
    return {"level": "advanced"} if unit is None else {"level": "advanced", "unit": unit}


#: The demosaicing methods (:mod:`pmvir.polarization.demosaic`), for decode.demosaic and refine.demosaic.
DemosaicMethod = Literal["bilinear", "edge-aware", "guided", "eari", "eari-guided"]



def merge_options(base: dict[str, Any], changes: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``changes`` applied: nested dicts merged key by key, anything else replaced.

    >>> merge_options({"refine": {"pol": {"k": 0.5, "dop_min": 0.1}}}, {"refine": {"pol": {"k": 0.7}}})
    {'refine': {'pol': {'k': 0.7, 'dop_min': 0.1}}}
    """
    out = dict(base)
    for key, value in changes.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_options(out[key], value)
        else:
            out[key] = value
    return out
