"""Photometric and polarimetric refinement (paper section 4.3): Polarimetric MVIR on arrays.

Entry point: :func:`refine_surface`. The cost's terms live in
:mod:`pmvir.refine.energy`, image sampling in :mod:`pmvir.refine.sampling`, the
optimizer in :mod:`pmvir.refine.lbfgs`, the schedule in :mod:`pmvir.refine.schedule` (its state in :mod:`~pmvir.refine.state`, each stage's set-up in :mod:`~pmvir.refine.stage_setup`,
E_pol's evidence floors in :mod:`~pmvir.refine.floors`, a stage's solve in :mod:`~pmvir.refine.solve`,
the lighting fits in :mod:`~pmvir.refine.lighting_fit`, the whole-surface moves in
:mod:`~pmvir.refine.surface_moves`).
"""

from pmvir.refine.sampling import Observation, observation_from_decoded
from pmvir.refine.schedule import refine_surface
from pmvir.refine.state import RefineResult, StageLog, make_visibility_fn

__all__ = [
    "Observation",
    "RefineResult",
    "StageLog",
    "make_visibility_fn",
    "observation_from_decoded",
    "refine_surface",
]
