"""The library's exception hierarchy.

The library raises; the CLI and the service answer. Every message says what was
expected, what came, and (for capture problems) which file.
"""

from __future__ import annotations

from pathlib import Path


class PmvirError(Exception):
    """Base class of every error pmvir raises on purpose."""


class ConfigError(PmvirError, ValueError):
    """An option or parameter is out of range or inconsistent."""


class InputError(PmvirError, ValueError):
    """An array or value handed to a function is malformed (non-finite, out of its range)."""


class ShapeError(InputError):
    """An array has the wrong shape, or arrays that must agree do not (kornia's ``ShapeError``).

    The message names the argument, the shape expected and the shape that came, e.g.
    ``"expected (..., 3) normals, got (5, 2)"``.
    """


class DTypeError(InputError, TypeError):
    """An array has the wrong dtype (a TypeError too, as numpy's AxisError is also an IndexError)."""


class CaptureError(PmvirError):
    """A capture (manifest, frame, mask) is missing, malformed or inconsistent.

    Args:
        path: the file the problem is in (relative to the capture where possible).
        problem: what was expected and what came.
    """

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}" if self.path else problem)


class ManifestError(CaptureError):
    """capture.json is missing, not JSON, or fails validation."""


class FrameError(CaptureError):
    """A frame file cannot be decoded, has the wrong size or the wrong data."""


class ReconstructionError(PmvirError):
    """A pipeline stage could not produce a usable result from the capture."""


class MeshError(PmvirError):
    """A mesh file cannot be read, or a mesh is degenerate."""


class CanceledError(PmvirError):
    """The caller asked the pipeline to stop (checked at stage/iteration boundaries)."""


class ResourceLimitError(PmvirError):
    """A run would need more memory than its limit allows (checked before it starts)."""
