"""Photometric and polarimetric refinement (paper section 4.3): Polarimetric MVIR on arrays.

Entry point: :func:`refine_surface`. The cost's terms live in
:mod:`pmvir.refine.energy`, image sampling in :mod:`pmvir.refine.sampling`, the
optimizer in :mod:`pmvir.refine.lbfgs`, the schedule in :mod:`pmvir.refine.schedule`.
"""

from pmvir.refine.sampling import Observation, observation_from_decoded
from pmvir.refine.schedule import RefineResult, StageLog, make_visibility_fn, refine_surface

__all__ = [
    "Observation",
    "RefineResult",
    "StageLog",
    "make_visibility_fn",
    "observation_from_decoded",
    "refine_surface",
]
