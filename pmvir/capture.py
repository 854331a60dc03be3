"""Reading and validating captures (shared/spec/capture-format.md, section 1).

A capture is a folder, or a ``.zip`` of it, holding ``capture.json``,
``frames/<name>.<ext>`` and optional ``masks/<name>.png``. A folder (or zip) of
frames without ``capture.json`` is a capture too: its manifest is inferred
(:mod:`pmvir.io.inference`). The frames may lie directly in the folder instead of
in ``frames/`` (a folder without ``frames/``): the manifest still names them
``frames/<name>.<ext>``, and error messages name the files as they lie.

Public API
==========

``with open_capture(path, infer=InferOptions(...)) as cap:``
    ``path`` is a capture folder, its ``capture.json``, or a ``.zip`` (every
    member checked, then extracted to a temporary folder that ``close()`` / the
    ``with`` exit removes; see :mod:`pmvir.io.capture_zip` for the limits, which
    are keyword options here too). ``infer`` is used only where there is no
    ``capture.json``. Raises CaptureError / ManifestError.

:func:`validate_capture` ``(path, *, decode_frames=True) -> list[CaptureError]``
    opens and validates, returning every problem (each naming its file) instead
    of raising: what an HTTP 422 answer lists.

:class:`Capture`
    ``root`` (Path), ``manifest`` (:class:`CaptureManifest`), ``inferred``
    (the notes of what was inferred, or None for a given manifest), ``sensor``,
    ``layout`` (MosaicLayout, angles ccw), ``frames`` (tuple of
    :class:`CaptureFrame`), ``len(cap)``, ``index(name)``, ``has_all_poses``,
    ``frame_size(i)`` -> (H, W), ``read_samples(i)`` -> (H, W) uint8/uint16,
    ``read_raw(i)`` -> :class:`RawFrame`, ``read_mask(i)`` -> (H, W) bool or None,
    ``validate(*, decode_frames=True)`` -> list[CaptureError].

:class:`RawFrame`
    ``samples`` (H, W) uint8/uint16 as stored; ``mosaic`` (H, W) float32
    ``(sample - black_level) / (white_level - black_level) / exposure``, not
    clipped; ``saturated`` (H, W) bool, ``sample >= white_level``; ``exposure``.

The manifest model (:class:`CaptureManifest`, :class:`SensorSpec`,
:class:`Intrinsics`, :class:`CamFromWorld`, :class:`RawSpec`,
:class:`FrameEntry`, :func:`parse_manifest`, :func:`write_capture_manifest`)
lives in :mod:`pmvir.io.manifest` and is re-exported here;
:func:`zip_capture` comes from :mod:`pmvir.io.capture_zip`.

Checks on each frame (``read_raw`` raises the first as FrameError;
``validate`` collects all): decodable single-channel 8/16-bit data; container
at least ``bit_depth`` bits (an 8-bit file declared 12-bit is an error); no
sample above 2^bit_depth - 1; width and height multiples of the layout period
(4 colour, 2 monochrome); size equal to the frame's intrinsics (own, else
shared); frames without intrinsics all of one size; mask the frame's size.
"""

from __future__ import annotations

import shutil
import tempfile
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pmvir.camera import Camera
from pmvir.errors import CaptureError, FrameError
from pmvir.io.capture_zip import (
    DEFAULT_MAX_MEMBERS,
    DEFAULT_MAX_RATIO,
    DEFAULT_MAX_TOTAL_BYTES,
    extract_capture_zip,
    zip_capture,
)
from pmvir.io.frames import RawFormat, container_bits, read_frame, read_frame_size
from pmvir.io.inference import InferOptions, frames_folder, infer_manifest
from pmvir.io.manifest import (
    FORMAT,
    MANIFEST_NAME,
    ROTATION_TOLERANCE,
    CamFromWorld,
    CaptureManifest,
    FrameEntry,
    Intrinsics,
    RawSpec,
    SensorSpec,
    parse_manifest,
    write_capture_manifest,
)
from pmvir.polarization.layout import MosaicLayout

__all__ = [
    "FORMAT", "MANIFEST_NAME", "ROTATION_TOLERANCE", "CamFromWorld", "Capture", "CaptureFrame",
    "CaptureManifest", "FrameEntry", "InferOptions", "Intrinsics", "RawFrame", "RawSpec", "SensorSpec",
    "open_capture",
    "parse_manifest", "validate_capture", "write_capture_manifest", "zip_capture",
]


@dataclass(frozen=True)
class CaptureFrame:
    """One view of a capture, resolved from its manifest entry.

    Attributes:
        index: position in the manifest's frame list.
        name: the file's stem (unique in the capture), e.g. "000".
        file: the path as written in the manifest, e.g. "frames/000.png".
        path: the file on disk.
        mask, mask_path: the mask as in the manifest and on disk, or None.
        intrinsics: the frame's own intrinsics, else the shared ones, else None.
        cam_from_world: (R (3, 3), t (3,)) float64, or None.
        exposure: relative exposure (> 0).
    """

    index: int
    name: str
    file: str
    path: Path
    mask: str | None
    mask_path: Path | None
    intrinsics: Intrinsics | None
    cam_from_world: tuple[np.ndarray, np.ndarray] | None
    exposure: float

    @property
    def camera(self) -> Camera | None:
        """The Camera when both intrinsics and pose are known, else None."""
        if self.intrinsics is None or self.cam_from_world is None:
            return None
        k = self.intrinsics
        R, t = self.cam_from_world
        return Camera.from_intrinsics(k.fx, k.fy, k.cx, k.cy, k.width, k.height, R, t)


@dataclass(frozen=True)
class RawFrame:
    """A frame's samples, normalized.

    Attributes:
        samples: (H, W) uint8 or uint16, as stored in the file.
        mosaic: (H, W) float32, (sample - black_level) / (white_level - black_level) / exposure.
        saturated: (H, W) bool, sample >= white_level (not a measurement).
        exposure: the exposure the mosaic was divided by.
    """

    samples: np.ndarray
    mosaic: np.ndarray
    saturated: np.ndarray
    exposure: float


class Capture:
    """An opened capture. Use as a context manager, or call :meth:`close`.

    Args:
        root: the capture folder.
        manifest: its manifest, as given or inferred.
        tmpdir: a temporary folder that :meth:`close` removes (a zip's extraction).
        inferred: the notes of what was inferred (:class:`pmvir.io.inference.InferredManifest`),
            or None when the manifest was given.
    """

    def __init__(
        self,
        root: str | Path,
        manifest: CaptureManifest,
        *,
        tmpdir: str | Path | None = None,
        inferred: tuple[str, ...] | None = None,
    ):
        self.root = Path(root)
        self.manifest = manifest
        self.inferred = inferred
        self._flat = frames_folder(self.root) == self.root
        self.sensor: SensorSpec = manifest.sensor
        self.layout: MosaicLayout = manifest.sensor.layout_value()
        self._raw: RawFormat | None = manifest.raw.to_format() if manifest.raw else None
        self._cleanup = (
            weakref.finalize(self, shutil.rmtree, str(tmpdir), ignore_errors=True) if tmpdir else None
        )
        frames = []
        for i, f in enumerate(manifest.frames):
            frames.append(
                CaptureFrame(
                    index=i,
                    name=f.name,
                    file=f.file,
                    path=self.root / self.on_disk(f.file),
                    mask=f.mask,
                    mask_path=None if f.mask is None else self.root / f.mask,
                    intrinsics=f.intrinsics or manifest.intrinsics,
                    cam_from_world=None if f.cam_from_world is None else f.cam_from_world.arrays(),
                    exposure=f.exposure,
                )
            )
        self.frames: tuple[CaptureFrame, ...] = tuple(frames)

    # -- lifetime

    def close(self) -> None:
        """Remove the temporary extraction of a zipped capture (no-op for folders)."""
        if self._cleanup is not None:
            self._cleanup()

    def __enter__(self) -> Capture:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- frames

    def __len__(self) -> int:
        return len(self.frames)

    def index(self, name: str) -> int:
        """Index of the frame called ``name`` (its file stem); KeyError if none."""
        for f in self.frames:
            if f.name == name:
                return f.index
        raise KeyError(f"no frame named {name!r}")

    @property
    def has_all_poses(self) -> bool:
        """Known-pose mode: every frame has intrinsics (own or shared) and a cam_from_world."""
        return all(f.camera is not None for f in self.frames)

    def on_disk(self, rel: str) -> str:
        """A manifest path as the file lies in the capture folder: ``frames/<name>`` is ``<name>``
        where the frames lie in the folder itself (no ``frames/`` folder)."""
        return rel.removeprefix("frames/") if self._flat else rel

    def _path(self, rel: str) -> Path:
        """The file of a manifest path; FrameError if a link takes it outside the capture."""
        path = self.root / self.on_disk(rel)
        if path.exists() and not path.resolve().is_relative_to(self.root.resolve()):
            raise FrameError(self.on_disk(rel), "resolves outside the capture (symbolic link)")
        return path

    def _expected_size(self, i: int) -> tuple[int, int] | None:
        k = self.frames[i].intrinsics
        return None if k is None else (k.height, k.width)

    def frame_size(self, i: int) -> tuple[int, int]:
        """(height, width) of frame i from its header."""
        f = self.frames[i]
        return read_frame_size(self._path(f.file), raw=self._raw, label=self.on_disk(f.file))

    def _size_problems(self, i: int, size: tuple[int, int]) -> list[str]:
        h, w = size
        problems = []
        p = self.layout.period
        if w % p or h % p:
            problems.append(
                f"size {w}x{h}: width and height must be multiples of {p} for {self.sensor.layout}"
            )
        exp = self._expected_size(i)
        if exp is not None and exp != (h, w):
            problems.append(f"size {w}x{h} does not match the intrinsics' {exp[1]}x{exp[0]}")
        return problems

    def _sample_problems(self, i: int, samples: np.ndarray) -> list[str]:
        bd = self.sensor.bit_depth
        bits = container_bits(self.frames[i].path, samples, raw=self._raw)
        if bits < bd:
            return [f"{bits}-bit data but sensor.bit_depth is {bd}"]
        top = (1 << bd) - 1
        peak = int(samples.max())
        if peak > top:
            hint = "; MSB-aligned data? then declare bit_depth 16" if bits == 16 and peak & 0xF == 0 else ""
            return [f"sample value {peak} exceeds 2^bit_depth - 1 = {top} (bit_depth {bd}){hint}"]
        return []

    def read_samples(self, i: int) -> np.ndarray:
        """(H, W) uint8/uint16 samples of frame i, checked (FrameError naming the file)."""
        f = self.frames[i]
        samples = read_frame(self._path(f.file), raw=self._raw, label=self.on_disk(f.file))
        problems = self._size_problems(i, samples.shape) + self._sample_problems(i, samples)
        if problems:
            raise FrameError(self.on_disk(f.file), "; ".join(problems))
        return samples

    def read_raw(self, i: int) -> RawFrame:
        """Frame i normalized: see :class:`RawFrame`. FrameError if the frame fails a check."""
        samples = self.read_samples(i)
        black = float(self.sensor.black_level)
        white = self.sensor.white
        exposure = self.frames[i].exposure
        scale = np.float32(1.0 / ((white - black) * exposure))
        mosaic = (samples.astype(np.float32) - np.float32(black)) * scale
        return RawFrame(samples=samples, mosaic=mosaic, saturated=samples >= white, exposure=exposure)

    def _read_mask_checked(self, i: int, size: tuple[int, int]) -> np.ndarray | None:
        f = self.frames[i]
        if f.mask is None:
            return None
        m = read_frame(self._path(f.mask), label=f.mask)
        if m.shape != size:
            raise FrameError(
                f.mask, f"mask is {m.shape[1]}x{m.shape[0]} but frame {self.on_disk(f.file)} is {size[1]}x{size[0]}"
            )
        return m != 0

    def read_mask(self, i: int) -> np.ndarray | None:
        """(H, W) bool foreground mask of frame i (non-zero = object), or None when it has none."""
        if self.frames[i].mask is None:
            return None
        return self._read_mask_checked(i, self.frame_size(i))

    # -- validation

    def validate(self, *, decode_frames: bool = True) -> list[CaptureError]:
        """Check every frame and mask; returns all problems (empty when the capture is valid).

        Args:
            decode_frames: decode every frame and mask (sample range and bit-depth
                checks); False checks files and sizes from headers only.

        Returns:
            One CaptureError (FrameError) per bad file, naming it.
        """
        problems: list[CaptureError] = []
        common: tuple[str, tuple[int, int]] | None = None
        for f in self.frames:
            try:
                if decode_frames:
                    samples = read_frame(self._path(f.file), raw=self._raw, label=self.on_disk(f.file))
                    size = samples.shape
                    found = self._sample_problems(f.index, samples)
                else:
                    size = self.frame_size(f.index)
                    found = []
            except CaptureError as exc:
                problems.append(exc)
                if f.mask is not None:  # the mask's size cannot be compared, but it must be readable
                    try:
                        read_frame_size(self._path(f.mask), label=f.mask)
                    except CaptureError as mexc:
                        problems.append(mexc)
                continue
            found = self._size_problems(f.index, size) + found
            if f.intrinsics is None:
                if common is None:
                    common = (self.on_disk(f.file), size)
                elif common[1] != size:
                    found.append(
                        f"size {size[1]}x{size[0]} differs from {common[0]}'s {common[1][1]}x{common[1][0]}; "
                        "frames without intrinsics must all have one size"
                    )
            if found:
                problems.append(FrameError(self.on_disk(f.file), "; ".join(found)))
            if f.mask is not None:
                try:
                    if decode_frames:
                        self._read_mask_checked(f.index, size)
                    else:
                        msize = read_frame_size(self._path(f.mask), label=f.mask)
                        if msize != size:
                            raise FrameError(f.mask, f"mask is {msize[1]}x{msize[0]} but frame {self.on_disk(f.file)} "
                                             f"is {size[1]}x{size[0]}")
                except CaptureError as exc:
                    problems.append(exc)
        return problems


def open_capture(
    path: str | Path,
    *,
    workdir: str | Path | None = None,
    max_members: int = DEFAULT_MAX_MEMBERS,
    max_total_bytes: int = DEFAULT_MAX_TOTAL_BYTES,
    max_ratio: float = DEFAULT_MAX_RATIO,
    infer: InferOptions | None = None,
) -> Capture:
    """Open a capture folder, its ``capture.json``, or a zipped capture.

    Args:
        path: folder, ``.../capture.json``, or ``.zip``.
        infer: what a folder of frames without ``capture.json`` cannot say (layout, black
            level, size of headerless frames); unused where there is a ``capture.json``.
        workdir: where a zip is extracted (a new temporary folder inside it;
            default: the system temporary folder).
        max_members, max_total_bytes, max_ratio: zip limits (see :mod:`pmvir.io.capture_zip`).

    Returns:
        The Capture; frames are read lazily. The manifest is fully validated.

    Raises:
        CaptureError: the path is neither a folder nor a zip, or the zip is unsafe/corrupt;
            no capture.json and no frames.
        FrameError: no capture.json, and a frame cannot give the manifest (see
            :func:`pmvir.io.inference.infer_manifest`).
        ManifestError: capture.json is not JSON, or invalid (each bad field named).
    """
    path = Path(path)
    if path.is_dir():
        return _open_folder(path, infer)
    if path.is_file() and path.name == MANIFEST_NAME:
        return _open_folder(path.parent, infer)
    if not path.exists():
        raise CaptureError(str(path), "no such capture folder or zip")
    tmp = Path(tempfile.mkdtemp(prefix="pmvir-capture-", dir=workdir))
    try:
        root = extract_capture_zip(
            path, tmp, max_members=max_members, max_total_bytes=max_total_bytes, max_ratio=max_ratio
        )
        return _open_folder(root, infer, tmpdir=tmp)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def _open_folder(root: Path, infer: InferOptions | None, *, tmpdir: Path | None = None) -> Capture:
    """The capture of a folder: its capture.json, else the manifest inferred from its frames."""
    mpath = root / MANIFEST_NAME
    if mpath.is_file():
        return Capture(root, parse_manifest(mpath.read_bytes()), tmpdir=tmpdir)
    inferred = infer_manifest(root, infer)
    return Capture(root, inferred.manifest, tmpdir=tmpdir, inferred=inferred.notes)


def validate_capture(path: str | Path, *, decode_frames: bool = True, **open_options: Any) -> list[CaptureError]:
    """Open and validate a capture; every problem is returned, none raised.

    Args:
        path: as for :func:`open_capture`.
        decode_frames: as for :meth:`Capture.validate`.
        open_options: keyword options of :func:`open_capture`.

    Returns:
        The problems: a single ManifestError/CaptureError when the capture cannot be
        opened, else one FrameError per bad frame or mask. Empty when valid.
    """
    try:
        cap = open_capture(path, **open_options)
    except CaptureError as exc:
        return [exc]
    with cap:
        return cap.validate(decode_frames=decode_frames)
