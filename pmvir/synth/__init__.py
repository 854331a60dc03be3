"""Synthetic polarization captures with ground truth (``pmvir synth``).

:func:`synthesize` (in :mod:`pmvir.synth.generate`, imported on first use so
that ``import pmvir.synth`` stays light) writes a capture; the pieces are
:mod:`~pmvir.synth.shapes`, :mod:`~pmvir.synth.texture`, :mod:`~pmvir.synth.rig`,
:mod:`~pmvir.synth.lighting`, :mod:`~pmvir.synth.materials`,
:mod:`~pmvir.synth.raycast`, :mod:`~pmvir.synth.builtin_renderer`,
:mod:`~pmvir.synth.mitsuba_renderer` (optional) and :mod:`~pmvir.synth.sensor`.
"""

from __future__ import annotations

from typing import Any

__all__ = ["synthesize"]


def __getattr__(name: str) -> Any:
    if name == "synthesize":
        from pmvir.synth.generate import synthesize

        return synthesize
    raise AttributeError(f"module 'pmvir.synth' has no attribute {name!r}")
