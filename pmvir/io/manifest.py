"""The capture manifest, ``capture.json`` (shared/spec/capture-format.md, section 1).

Public API (re-exported by :mod:`pmvir.capture`): :class:`CaptureManifest` with
:class:`SensorSpec`, :class:`Intrinsics`, :class:`CamFromWorld`,
:class:`RawSpec`, :class:`FrameEntry`; :func:`parse_manifest` (bytes -> model,
ManifestError naming capture.json and every bad field) and
:func:`write_capture_manifest` (model -> ``root/capture.json``, atomic).

Unknown keys are errors at every level. Choices the spec leaves open:

* every path is ``frames/<name>.<ext>`` (png, tif, tiff, dng, raw, bin) or
  ``masks/<name>.png``: relative, ``/``-separated, directly inside its folder,
  no ``..``, no absolute path, no backslash, no drive letter; frame names
  (file stems) are unique;
* ``format`` must be present and equal ``"pmvir-capture/1"`` (the model's
  default, for writers);
* ``black_level`` defaults to 0, ``white_level`` to 2^bit_depth - 1, and
  ``0 <= black_level < white_level <= 2^bit_depth - 1``;
* ``cam_from_world.R`` must be orthonormal with det +1 to within
  :data:`ROTATION_TOLERANCE`; :meth:`CamFromWorld.arrays` returns the nearest
  exact rotation (SVD);
* headerless frames need the top-level ``"raw"`` object;
* intrinsics ``model`` defaults to ``"PINHOLE"`` (the only model); ``"estimated": true``
  marks intrinsics that are a starting point (from EXIF, see :mod:`pmvir.io.inference`):
  SfM refines their focal length instead of holding them fixed.
"""

from __future__ import annotations

import json
import os
from pathlib import Path, PurePosixPath
from typing import Annotated, Final, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from pmvir.camera import Camera
from pmvir.errors import ConfigError, ManifestError
from pmvir.io import json_limits
from pmvir.io.frames import FRAME_SUFFIXES, RawFormat
from pmvir.polarization.layout import MosaicLayout, layout_from_sensor

FORMAT: Final = "pmvir-capture/1"
MANIFEST_NAME = "capture.json"
#: Largest accepted deviation of a manifest rotation from orthonormal with det +1
#: (max abs entry of R^T R - I, and |det R - 1|).
ROTATION_TOLERANCE = 1e-4


# ----------------------------------------------------------------------------- manifest model


class _Closed(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False)


def _check_path(value: str, folder: str, suffixes: tuple[str, ...]) -> str:
    """Accept only ``folder/<name><suffix>``: relative, inside the capture, '/'-separated."""
    bad = None
    if "\\" in value:
        bad = "uses a backslash; use '/' separators"
    elif value.startswith("/") or ":" in value:
        bad = "is absolute (or has a drive letter/':'); paths are relative to the capture"
    elif "\x00" in value:
        bad = "contains a NUL character"
    elif any(p in ("", ".", "..") for p in value.split("/")):
        bad = "has an empty, '.' or '..' segment; paths must stay inside the capture"
    else:
        parts = PurePosixPath(value).parts
        if len(parts) != 2 or parts[0] != folder:
            bad = f"must be {folder}/<name><ext> (directly inside {folder}/)"
        elif PurePosixPath(value).suffix.lower() not in suffixes or not PurePosixPath(value).stem:
            bad = f"must end in one of {', '.join(suffixes)}"
    if bad:
        raise ValueError(f"path {value!r} {bad}")
    return value


class Intrinsics(_Closed):
    """Pinhole intrinsics in pixels of the full-resolution mosaic grid (COLMAP pixel convention)."""

    model: Literal["PINHOLE"] = Field(default="PINHOLE", description="Camera model; only PINHOLE")
    width: int = Field(gt=0, description="Image width in pixels")
    height: int = Field(gt=0, description="Image height in pixels")
    fx: float = Field(gt=0, description="Focal length along x, pixels")
    fy: float = Field(gt=0, description="Focal length along y, pixels")
    cx: float = Field(description="Principal point x, pixels (image centre = width / 2)")
    cy: float = Field(description="Principal point y, pixels (image centre = height / 2)")
    estimated: bool | None = Field(
        default=None,
        description="True: an estimate (e.g. from EXIF) that SfM refines; absent or false: calibrated, held fixed",
    )

    def K(self) -> np.ndarray:
        """(3, 3) float64 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @classmethod
    def from_camera(cls, camera: Camera) -> Intrinsics:
        K = camera.K
        return cls(width=camera.width, height=camera.height, fx=float(K[0, 0]), fy=float(K[1, 1]),
                   cx=float(K[0, 2]), cy=float(K[1, 2]))


_Row3 = Annotated[list[float], Field(min_length=3, max_length=3)]


class CamFromWorld(_Closed):
    """Rigid world-to-camera transform, ``x_cam = R @ x_world + t`` (OpenCV axes)."""

    R: Annotated[list[_Row3], Field(min_length=3, max_length=3)] = Field(description="3x3 rotation, row-major")
    t: _Row3 = Field(description="translation, world units")

    @field_validator("R")
    @classmethod
    def _rotation(cls, R: list[list[float]]) -> list[list[float]]:
        m = np.asarray(R, dtype=np.float64)
        ortho = float(np.abs(m.T @ m - np.eye(3)).max())
        det = float(np.linalg.det(m))
        if ortho > ROTATION_TOLERANCE or abs(det - 1.0) > ROTATION_TOLERANCE:
            raise ValueError(
                f"R is not a rotation (orthonormal, det +1): max|R^T R - I| = {ortho:.3g}, det = {det:.6g}"
            )
        return R

    def arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """(R (3, 3), t (3,)) float64; R is the nearest exact rotation to the stored one."""
        u, _, vt = np.linalg.svd(np.asarray(self.R, dtype=np.float64))
        return u @ vt, np.asarray(self.t, dtype=np.float64)

    @classmethod
    def from_arrays(cls, R: np.ndarray, t: np.ndarray) -> CamFromWorld:
        return cls(R=np.asarray(R, dtype=np.float64).reshape(3, 3).tolist(),
                   t=np.asarray(t, dtype=np.float64).reshape(3).tolist())


class RawSpec(_Closed):
    """Layout of headerless ``.raw``/``.bin`` frames."""

    width: int = Field(gt=0, description="Frame width in pixels")
    height: int = Field(gt=0, description="Frame height in pixels")
    dtype: Literal["uint8", "uint16le", "uint16be", "mono12p"] = Field(description="Sample encoding")

    def to_format(self) -> RawFormat:
        return RawFormat(width=self.width, height=self.height, dtype=self.dtype)


class SensorSpec(_Closed):
    """The sensor: mosaic layout and sample levels."""

    layout: Literal["IMX250MYR", "IMX250MZR"] = Field(description="Sensor mosaic layout")
    bit_depth: int = Field(ge=1, le=16, description="Significant bits per sample")
    black_level: float = Field(default=0.0, ge=0, description="Subtracted first, raw sample units")
    white_level: float | None = Field(
        default=None, description="Samples >= this are saturated; default 2^bit_depth - 1"
    )
    aop_reference: Literal["ccw", "cw"] = Field(default="ccw", description="Sense of the polarizer angles")
    polarizer_block: tuple[tuple[int, int], tuple[int, int]] | None = Field(
        default=None, description="Override: 2x2 polarizer angles, degrees, row-major"
    )
    bayer: Literal["RGGB", "BGGR", "GRBG", "GBRG"] | None = Field(
        default=None, description="Override: Bayer pattern of the four 2x2 blocks (colour sensors)"
    )

    @model_validator(mode="after")
    def _levels_and_layout(self) -> SensorSpec:
        top = (1 << self.bit_depth) - 1
        if self.white_level is None:
            self.white_level = float(top)
        if not self.black_level < self.white_level <= top:
            raise ValueError(
                f"need black_level < white_level <= 2^bit_depth - 1 = {top}, "
                f"got black_level {self.black_level}, white_level {self.white_level}"
            )
        self.layout_value()  # raises on inconsistent overrides
        return self

    @property
    def white(self) -> float:
        """``white_level``, or its default 2^bit_depth - 1 where the manifest left it out."""
        return float((1 << self.bit_depth) - 1) if self.white_level is None else float(self.white_level)

    def layout_value(self) -> MosaicLayout:
        """The MosaicLayout (angles converted to the ccw sense)."""
        try:
            return layout_from_sensor(
                self.layout, polarizer_block=self.polarizer_block, bayer=self.bayer,
                aop_reference=self.aop_reference,
            )
        except ConfigError as exc:
            raise ValueError(str(exc)) from None


class FrameEntry(_Closed):
    """One view."""

    file: str = Field(description="frames/<name>.<ext>")
    mask: str | None = Field(default=None, description="masks/<name>.png, non-zero = object")
    cam_from_world: CamFromWorld | None = Field(default=None, description="Known pose")
    intrinsics: Intrinsics | None = Field(default=None, description="Per-frame intrinsics (win over shared)")
    exposure: float = Field(default=1.0, gt=0, description="Relative exposure; samples are divided by it")

    @field_validator("file")
    @classmethod
    def _file_path(cls, v: str) -> str:
        return _check_path(v, "frames", tuple(sorted(FRAME_SUFFIXES)))

    @field_validator("mask")
    @classmethod
    def _mask_path(cls, v: str | None) -> str | None:
        return None if v is None else _check_path(v, "masks", (".png",))

    @property
    def name(self) -> str:
        return PurePosixPath(self.file).stem

    @property
    def is_headerless(self) -> bool:
        return FRAME_SUFFIXES[PurePosixPath(self.file).suffix.lower()] == "raw"


class CaptureManifest(_Closed):
    """``capture.json``."""

    format: Literal["pmvir-capture/1"] = Field(default=FORMAT, description="Format and version")
    sensor: SensorSpec
    intrinsics: Intrinsics | None = Field(default=None, description="Shared intrinsics")
    raw: RawSpec | None = Field(default=None, description="Layout of headerless frames")
    frames: list[FrameEntry] = Field(min_length=1)

    @model_validator(mode="after")
    def _frames_consistent(self) -> CaptureManifest:
        seen: dict[str, str] = {}
        for f in self.frames:
            if f.name in seen:
                raise ValueError(f"frame name {f.name!r} is used twice ({seen[f.name]!r} and {f.file!r})")
            seen[f.name] = f.file
        headerless = [f.file for f in self.frames if f.is_headerless]
        if headerless and self.raw is None:
            raise ValueError(f"headerless frames ({headerless[0]!r}, ...) need \"raw\": {{width, height, dtype}}")
        return self


def _format_errors(exc: ValidationError) -> str:
    parts = []
    for err in exc.errors():
        loc = "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in err["loc"]).lstrip(".")
        msg = err["msg"].removeprefix("Value error, ")
        parts.append(f"{loc or '(top level)'}: {msg}")
    return "; ".join(parts)


def parse_manifest(data: bytes | str, *, label: str = MANIFEST_NAME) -> CaptureManifest:
    """Parse and validate ``capture.json`` content; ManifestError naming ``label`` and each bad field."""
    try:
        doc = json_limits.loads(data, source=label)
    except json_limits.JsonError as exc:
        raise ManifestError(label, exc.problem) from None
    if isinstance(doc, dict) and "format" not in doc:
        raise ManifestError(label, f"format: missing; expected {FORMAT!r}")
    try:
        return CaptureManifest.model_validate(doc)
    except ValidationError as exc:
        raise ManifestError(label, _format_errors(exc)) from exc


def write_capture_manifest(root: str | Path, manifest: CaptureManifest) -> Path:
    """Write ``root/capture.json`` atomically (None fields left out); returns its path."""
    path = Path(root) / MANIFEST_NAME
    tmp = path.with_name(f".{MANIFEST_NAME}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(manifest.model_dump(mode="json", exclude_none=True), indent=1))
    os.replace(tmp, path)
    return path
