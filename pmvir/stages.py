"""The pipeline's stages, named once.

>>> [str(s) for s in Stage]
['decode', 'geometry', 'refine']
>>> Stage("geometry").position
1
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["AVAILABLE_STAGES", "STAGES", "Stage", "stages_through"]


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
#: Stages this build can run (the service refuses a job naming another before it queues it).
AVAILABLE_STAGES: tuple[Stage, ...] = STAGES


def stages_through(last: Stage | str) -> list[Stage]:
    """The stages a run that stops after ``last`` executes, in order.

    >>> [str(s) for s in stages_through("geometry")]
    ['decode', 'geometry']
    """
    return list(STAGES[: Stage(last).position + 1])
