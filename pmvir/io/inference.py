"""``capture.json`` inferred from a folder of frames (shared/spec/capture-format.md, section 1).

A folder that holds frame files and no ``capture.json`` is a capture: the frames lie
directly in it, or in its ``frames/`` folder when it has one (then only there).
:func:`infer_manifest` reads every frame and returns the manifest with one line per
thing it inferred (:attr:`InferredManifest.notes`), what ``pmvir init`` prints.

What is inferred, and from what:

* **frames**: every ``.png``, ``.tif``/``.tiff``, ``.dng``, ``.raw``/``.bin`` file
  (hidden files skipped), in natural order of their names (``img2`` before ``img10``);
  masks from ``masks/<name>.png`` where they exist (masks are optional).
* **size**: from the files; all frames must have one size, a multiple of the layout's
  period (4 for IMX250MYR, 2 for IMX250MZR). Headerless frames need
  :attr:`InferOptions.frame_size`; their encoding (``uint8``, ``uint16le``/``be``,
  ``mono12p``) follows from the file length (``uint16be`` where little-endian reading
  gives samples above 12 bits and big-endian does not).
* **bit depth**: 8 for 8-bit containers and ``uint8`` files, 12 for ``mono12p``; a DNG's
  white level, a PNG's ``sBIT`` or a TIFF's ``MaxSampleValue`` where present; otherwise
  the smallest of 12, 14 and 16 bits that holds the largest sample of all frames (12-bit
  data in 16-bit files keeps its values 0..4095, spec section 1).
* **black level**: :attr:`InferOptions.black_level`, else the DNG's, else 0 (with a note when no frame
  goes near 0: a pedestal the user may give); the white level the DNG's, else 2^bit_depth - 1.
* **layout**: :attr:`InferOptions.layout` (IMX250MYR by default).
* **intrinsics**: from EXIF where every frame has a focal length (:mod:`pmvir.io.exif`;
  the IMX250's 3.45 um pixel pitch turns a bare ``FocalLength`` into pixels), marked
  ``"estimated": true`` so that SfM refines them; otherwise none, and SfM estimates
  them. No poses: SfM estimates them.

Problems raise :class:`~pmvir.errors.FrameError` naming the file (frames of
different sizes, an unreadable frame, a size the mosaic cannot tile, a headerless
frame without a size) or :class:`~pmvir.errors.ManifestError` naming ``capture.json``
(no manifest and no frames to infer it from).
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import ValidationError

from pmvir.errors import ConfigError, FrameError, ManifestError
from pmvir.io.exif import exif_focal_px
from pmvir.io.frames import (
    FRAME_SUFFIXES,
    RawFormat,
    dng_levels,
    frame_format,
    png_significant_bits,
    read_frame,
    tiff_max_sample_value,
)
from pmvir.io.manifest import MANIFEST_NAME, CaptureManifest, FrameEntry, Intrinsics, RawSpec, SensorSpec
from pmvir.polarization.layout import layout_from_sensor

LayoutName = Literal["IMX250MYR", "IMX250MZR"]
#: Layouts a manifest may name, the default first.
LAYOUTS: tuple[LayoutName, ...] = ("IMX250MYR", "IMX250MZR")
#: Pixel pitch (mm) of the sensors of :data:`LAYOUTS` (Sony IMX250: 3.45 um).
PIXEL_PITCH_MM: dict[str, float] = {"IMX250MYR": 0.00345, "IMX250MZR": 0.00345}
#: Bit depths a 16-bit container's data is taken to have, smallest first (by its largest sample).
_DEPTHS_IN_16 = (12, 14, 16)


@dataclass(frozen=True)
class InferOptions:
    """What a folder of frames cannot say about itself.

    Attributes:
        layout: the sensor's mosaic layout.
        black_level: subtracted first, raw sample units; None: the DNG's, else 0.
        frame_size: (width, height) of headerless ``.raw``/``.bin`` frames, pixels.
    """

    layout: LayoutName = "IMX250MYR"
    black_level: float | None = None
    frame_size: tuple[int, int] | None = None

    def __post_init__(self) -> None:
        if self.layout not in LAYOUTS:
            raise ConfigError(f"layout must be one of {', '.join(LAYOUTS)}, got {self.layout!r}")
        if self.black_level is not None and not self.black_level >= 0:
            raise ConfigError(f"black level must be >= 0, got {self.black_level}")
        if self.frame_size is not None and min(self.frame_size) <= 0:
            raise ConfigError(f"frame size must be positive, got {self.frame_size[0]}x{self.frame_size[1]}")


@dataclass(frozen=True)
class InferredManifest:
    """A manifest inferred from a folder of frames.

    Attributes:
        manifest: the manifest; frame paths are ``frames/<name>`` as the spec has them,
            whether the files lie in ``frames/`` or directly in the folder.
        frames_dir: the folder that holds the frames.
        notes: one line per inferred value, saying from what.
    """

    manifest: CaptureManifest
    frames_dir: Path
    notes: tuple[str, ...] = field(default_factory=tuple)


def parse_frame_size(text: str) -> tuple[int, int]:
    """``"WxH"`` -> (width, height); ConfigError otherwise."""
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or min(int(m[1]), int(m[2])) <= 0:
        raise ConfigError(f"frame size {text!r}: expected WIDTHxHEIGHT in pixels, e.g. 2448x2048")
    return int(m[1]), int(m[2])


def frames_folder(root: Path) -> Path:
    """Where a capture's frames lie: ``root/frames`` when it is a folder, else ``root`` itself."""
    sub = root / "frames"
    return sub if sub.is_dir() else root


def _natural_key(name: str) -> list[object]:
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def find_frame_files(root: Path) -> list[Path]:
    """The frame files of a bare folder (module docstring), in natural order; ManifestError when none."""
    folder = frames_folder(root)
    files: list[Path] = []
    others: list[Path] = []
    for p in folder.iterdir():
        if p.name.startswith(".") or not p.is_file():
            continue
        (files if p.suffix.lower() in FRAME_SUFFIXES else others).append(p)
    if not files:
        where = "frames/" if folder != root else "the folder"
        seen = f"; it holds {len(others)} other file(s), e.g. {sorted(o.name for o in others)[0]!r}" if others else ""
        raise ManifestError(
            MANIFEST_NAME,
            f"not found in {root}, and no frame files ({', '.join(sorted(FRAME_SUFFIXES))}) in {where} "
            f"to infer it from{seen}",
        )
    files.sort(key=lambda p: _natural_key(p.name))
    seen_names: dict[str, str] = {}
    for p in files:
        if p.stem in seen_names:
            raise FrameError(
                p.relative_to(root).as_posix(), f"has the same name as {seen_names[p.stem]!r}; frame names must be unique"
            )
        seen_names[p.stem] = p.name
    return files


def _raw_format(path: Path, size: tuple[int, int] | None, label: str) -> RawFormat:
    """The encoding of a headerless frame of ``size`` (w, h), from its length (module docstring)."""
    if size is None:
        raise FrameError(label, "a headerless frame: give its size (--frame-size WxH)")
    w, h = size
    n, length = w * h, path.stat().st_size
    if length == n:
        return RawFormat(w, h, "uint8")
    if length == (3 * n + 1) // 2:
        return RawFormat(w, h, "mono12p")
    if length == 2 * n:
        data = np.fromfile(path, dtype="<u2")
        big = np.fromfile(path, dtype=">u2")
        be = int(data.max()) > 4095 and int(big.max()) <= 4095
        return RawFormat(w, h, "uint16be" if be else "uint16le")
    raise FrameError(
        label,
        f"{length} bytes fits no encoding of {w}x{h}: uint8 {n}, mono12p {(3 * n + 1) // 2}, uint16 {2 * n} bytes",
    )


@dataclass
class _Scan:
    """What reading every frame found."""

    size: tuple[int, int] | None = None
    size_file: str = ""
    container: dict[int, str] = field(default_factory=dict)  # bits -> a file with them
    peak: int = 0
    floor: int | None = None  # the lowest of the frames' 0.01th-percentile samples (a black-level hint)
    declared: dict[str, int] = field(default_factory=dict)  # file -> bit depth its container declares
    dng: list[tuple[str, float, int]] = field(default_factory=list)  # (file, black, white)
    raw: RawFormat | None = None


def _scan(files: Sequence[Path], root: Path, options: InferOptions, period: int) -> _Scan:
    scan = _Scan()
    for p in files:
        name = p.relative_to(root).as_posix()  # errors name the file as it lies in the folder
        fmt = frame_format(p)
        raw = None
        if fmt == "raw":
            raw = _raw_format(p, options.frame_size, name)
            if scan.raw is not None and scan.raw != raw:
                raise FrameError(name, f"encoded as {raw.dtype}, but an earlier frame as {scan.raw.dtype}")
            scan.raw = raw
        samples = read_frame(p, raw=raw, label=name)
        h, w = samples.shape
        if scan.size is None:
            scan.size, scan.size_file = (h, w), name
        elif scan.size != (h, w):
            sh, sw = scan.size
            raise FrameError(name, f"size {w}x{h} differs from {scan.size_file}'s {sw}x{sh}; all frames must have one size")
        if w % period or h % period:
            raise FrameError(
                name, f"size {w}x{h}: width and height must be multiples of {period} for {options.layout}"
            )
        bits = {"uint8": 8, "mono12p": 12}.get(raw.dtype, 16) if raw is not None else 8 * samples.dtype.itemsize
        scan.container.setdefault(bits, name)
        scan.peak = max(scan.peak, int(samples.max()))
        low = int(np.partition(samples.ravel(), samples.size // 10_000)[samples.size // 10_000])
        scan.floor = low if scan.floor is None else min(scan.floor, low)
        if fmt == "dng":
            black, white = dng_levels(p, label=name)
            scan.dng.append((name, black, white))
            scan.declared[name] = max(1, white.bit_length())
        elif fmt == "png" and (sbit := png_significant_bits(p)) is not None:
            scan.declared[name] = sbit
        elif fmt == "tiff" and (top := tiff_max_sample_value(p)) is not None:
            scan.declared[name] = top.bit_length()
    return scan


def _bit_depth(scan: _Scan, n_files: int, notes: list[str]) -> int:
    if len(scan.container) > 1:
        (b1, f1), (b2, f2) = sorted(scan.container.items())[:2]
        raise FrameError(f2, f"holds {b2}-bit samples but {f1} holds {b1}-bit ones; all frames must have one type")
    (bits,) = scan.container
    if bits in (8, 12):
        notes.append(f"bit depth {bits}: {bits}-bit files")
        return bits
    declared = set(scan.declared.values())
    if len(declared) == 1 and len(scan.declared) == n_files:
        depth = declared.pop()
        if depth >= scan.peak.bit_length():
            notes.append(f"bit depth {depth}: as the files declare it (DNG white level, PNG sBIT or TIFF MaxSampleValue)")
            return depth
    depth = next(d for d in _DEPTHS_IN_16 if scan.peak <= (1 << d) - 1)
    notes.append(f"bit depth {depth}: 16-bit files whose largest sample is {scan.peak}")
    return depth


#: Darkest samples at or above this fraction of the full scale make the black-level note point at a pedestal.
_PEDESTAL_HINT = 0.005


def _levels(scan: _Scan, options: InferOptions, bit_depth: int, notes: list[str]) -> tuple[float, float | None]:
    white: float | None = None
    black = 0.0
    if scan.dng:
        name, dng_black, dng_white = scan.dng[0]
        if 0 < dng_white <= (1 << bit_depth) - 1:
            white = float(dng_white)
            notes.append(f"white level {dng_white}: from {name}")
        black = dng_black
    if options.black_level is not None:
        black = float(options.black_level)
        notes.append(f"black level {black:g}: as given")
    elif scan.dng:
        notes.append(f"black level {black:g}: from {scan.dng[0][0]}")
    else:
        note = "black level 0: none given (--black-level), the files hold none"
        if scan.floor and scan.floor >= _PEDESTAL_HINT * (1 << bit_depth):
            note += (f"; yet no frame goes below {scan.floor} (0.01 % of its samples): if the camera adds a "
                     "pedestal, give it with --black-level")
        notes.append(note)
    top = white if white is not None else float((1 << bit_depth) - 1)
    if not black < top:
        raise ConfigError(f"black level {black:g} must be below the white level {top:g} (bit depth {bit_depth})")
    return black, white


def _intrinsics(
    files: Sequence[Path], size: tuple[int, int], layout: str, notes: list[str]
) -> Intrinsics | None:
    h, w = size
    focals = [exif_focal_px(p, w, h, pixel_pitch_mm=PIXEL_PITCH_MM.get(layout)) for p in files]
    found = [f for f in focals if f is not None]
    if not found or len(found) < len(files):
        if found:
            notes.append(f"intrinsics: estimated by SfM (only {len(found)} of {len(files)} frames have an EXIF focal length)")
        else:
            notes.append("intrinsics: estimated by SfM (no EXIF focal length in the frames)")
        return None
    fx = float(np.median([f.fx for f in found]))
    fy = float(np.median([f.fy for f in found]))
    notes.append(f"intrinsics: fx {fx:.1f}, fy {fy:.1f} px from {found[0].source}, principal point at the centre; SfM refines them")
    return Intrinsics(width=w, height=h, fx=fx, fy=fy, cx=w / 2.0, cy=h / 2.0, estimated=True)


def _frame_entry(p: Path, root: Path) -> FrameEntry:
    mask = root / "masks" / f"{p.stem}.png"
    try:
        return FrameEntry(file=f"frames/{p.name}", mask=f"masks/{mask.name}" if mask.is_file() else None)
    except ValidationError as exc:
        msg = "; ".join(e["msg"].removeprefix("Value error, ") for e in exc.errors())
        raise FrameError(p.relative_to(root).as_posix(), f"the file name cannot be used in a manifest: {msg}") from None


def infer_manifest(root: str | Path, options: InferOptions | None = None) -> InferredManifest:
    """Infer ``capture.json`` for a folder of frames (module docstring: what, from what).

    Args:
        root: the folder; its frames lie in it or in its ``frames/``.
        options: layout, black level and the size of headerless frames.

    Returns:
        The manifest, the frames' folder and the notes of what was inferred.

    Raises:
        ManifestError: no frames in the folder (and no capture.json).
        FrameError: a frame unreadable, of another size or sample type than the first,
            of a size the layout cannot tile; a headerless frame without a size.
        ConfigError: the black level is not below the white level.
    """
    root = Path(root)
    options = options or InferOptions()
    files = find_frame_files(root)
    layout = layout_from_sensor(options.layout)
    entries = [_frame_entry(p, root) for p in files]
    scan = _scan(files, root, options, layout.period)
    assert scan.size is not None  # at least one frame was read
    h, w = scan.size
    notes = [
        f"{len(files)} frames of {w}x{h} in {'frames/' if frames_folder(root) != root else 'the folder'}"
        + (f" ({scan.raw.dtype})" if scan.raw is not None else ""),
        f"layout {options.layout}" + (" (the default; --layout to choose)" if options.layout == LAYOUTS[0] else ""),
    ]
    masked = sum(e.mask is not None for e in entries)
    if masked:
        notes.append(f"masks: {masked} of {len(entries)} frames have masks/<name>.png")
    bit_depth = _bit_depth(scan, len(files), notes)
    black, white = _levels(scan, options, bit_depth, notes)
    intrinsics = _intrinsics(files, scan.size, options.layout, notes)
    notes.append("poses: estimated by SfM")
    manifest = CaptureManifest(
        sensor=SensorSpec(layout=options.layout, bit_depth=bit_depth, black_level=black, white_level=white),
        intrinsics=intrinsics,
        raw=None if scan.raw is None else RawSpec(width=w, height=h, dtype=scan.raw.dtype),
        frames=entries,
    )
    return InferredManifest(manifest=manifest, frames_dir=frames_folder(root), notes=tuple(notes))
