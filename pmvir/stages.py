"""The pipeline's stages, named once.

>>> [str(s) for s in Stage]
['decode', 'geometry', 'refine']
>>> Stage("geometry").position
1
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["STAGES", "Stage"]


class Stage(StrEnum):
    """A pipeline stage; members are listed in the order the pipeline runs them."""

    DECODE = "decode"
    GEOMETRY = "geometry"
    REFINE = "refine"

    @property
    def position(self) -> int:
        """0-based place in the run order."""
        return list(Stage).index(self)


#: Every stage, in order.
STAGES: tuple[Stage, ...] = tuple(Stage)
