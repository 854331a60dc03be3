"""Raw sensor frames: reading and writing the files of a capture's ``frames/``.

Spec: shared/spec/capture-format.md, section 1, "Frame files". A frame holds
the mosaic samples exactly as read out, one integer per pixel; nothing here
interprets the mosaic (that is :mod:`pmvir.polarization`).

Formats, chosen by the file's suffix (case-insensitive):

============  ==================================================================
``.png``      single-channel 8- or 16-bit PNG (greyscale colour type only)
``.tif``      single-channel 8- or 16-bit unsigned TIFF (first page)
``.tiff``
``.dng``      the CFA samples, ``raw_image`` as read by rawpy; the DNG's own
              colour interpretation is ignored. Written as an uncompressed
              16-bit CFA DNG. LibRaw does not read images under 22x22 pixels.
``.raw``      headerless samples, row-major, no row padding, described by a
``.bin``      :class:`RawFormat` (width, height, dtype): ``uint8``,
              ``uint16le``, ``uint16be`` or ``mono12p``
============  ==================================================================

``mono12p`` is GenICam PFNC Mono12p: a little-endian bit stream of 12-bit
samples, two samples in three bytes: byte0 = p0 bits 0-7; byte1 low nibble =
p0 bits 8-11, high nibble = p1 bits 0-3; byte2 = p1 bits 4-11. The stream runs
on across rows; an odd number of samples ends with a half-used byte (its high
nibble zero), so a frame of n samples is ceil(1.5 n) bytes.

Public API:

* :func:`frame_format` (suffix -> ``"png" | "tiff" | "dng" | "raw"``),
  :data:`FRAME_SUFFIXES`, :data:`RAW_DTYPES`, :class:`RawFormat`
* :func:`read_frame` -> (H, W) uint8 or uint16 samples
* :func:`read_frame_size` -> (height, width) from the header only
* :func:`container_bits` -> bits per sample of the file's container (8, 12, 16)
* :func:`png_significant_bits`, :func:`tiff_max_sample_value`, :func:`dng_levels`: what a
  container says of its samples' range (PNG ``sBIT``, TIFF ``MaxSampleValue``, DNG black/white level)
* :func:`write_frame` (atomic: temporary name, then rename)
* :func:`pack_mono12p`, :func:`unpack_mono12p`

Every problem with a file raises :class:`pmvir.errors.FrameError` naming the
file (``label`` if given, e.g. the path relative to the capture, else the
path); bad arguments from the caller raise ``ValueError``.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import cv2
import numpy as np
import rawpy
import tifffile

from pmvir.errors import ConfigError, DTypeError, FrameError, InputError, ShapeError

#: Frame file suffixes (lower case) and the format each one holds.
FRAME_SUFFIXES: dict[str, str] = {
    ".png": "png",
    ".tif": "tiff",
    ".tiff": "tiff",
    ".dng": "dng",
    ".raw": "raw",
    ".bin": "raw",
}
#: Sample encodings of headerless ``.raw``/``.bin`` frames.
RAW_DTYPES: tuple[str, ...] = ("uint8", "uint16le", "uint16be", "mono12p")

RawDtype = Literal["uint8", "uint16le", "uint16be", "mono12p"]

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
#: Most pixels a frame may have (about 4x a 24 MP polarization sensor); checked from the header,
#: before anything is decoded, so a small file declaring a huge image is refused cheaply.
MAX_FRAME_PIXELS = 100_000_000
_DNG_MIN_SIZE = 22  # LibRaw rejects raw images smaller than this in either direction


@dataclass(frozen=True)
class RawFormat:
    """How a headerless frame is laid out (the manifest's ``"raw"`` object).

    Attributes:
        width, height: frame size in pixels.
        dtype: one of :data:`RAW_DTYPES`.
    """

    width: int
    height: int
    dtype: str

    def __post_init__(self) -> None:
        if self.dtype not in RAW_DTYPES:
            raise ConfigError(f"raw dtype must be one of {RAW_DTYPES}, got {self.dtype!r}")
        if self.width <= 0 or self.height <= 0:
            raise ConfigError(f"raw size must be positive, got {self.width}x{self.height}")

    @property
    def nbytes(self) -> int:
        """Exact file length in bytes."""
        n = self.width * self.height
        if self.dtype == "uint8":
            return n
        if self.dtype == "mono12p":
            return (3 * n + 1) // 2
        return 2 * n


def frame_format(path: str | Path) -> str:
    """``"png" | "tiff" | "dng" | "raw"`` from the suffix; InputError for any other suffix."""
    suffix = Path(path).suffix.lower()
    if suffix not in FRAME_SUFFIXES:
        raise InputError(f"{path}: unknown frame suffix {suffix!r}; expected one of {sorted(FRAME_SUFFIXES)}")
    return FRAME_SUFFIXES[suffix]


def container_bits(path: str | Path, samples: np.ndarray, *, raw: RawFormat | None = None) -> int:
    """Bits per sample the file's container holds.

    Headerless files: 8 (uint8), 12 (mono12p) or 16 from ``raw.dtype``; other
    formats: 8 or 16 from the dtype of the samples :func:`read_frame` returned.
    """
    if frame_format(path) == "raw" and raw is not None:
        return {"uint8": 8, "mono12p": 12}.get(raw.dtype, 16)
    return 8 * samples.dtype.itemsize


# ----------------------------------------------------------------------------- mono12p


def pack_mono12p(samples: np.ndarray) -> bytes:
    """Pack integer samples (any shape, values 0..4095) as GenICam Mono12p bytes, row-major."""
    flat = np.asarray(samples).reshape(-1)
    if flat.size and (flat.min() < 0 or flat.max() > 4095):
        raise InputError("mono12p holds values 0..4095 only")
    v = flat.astype(np.uint16)
    if v.size % 2:
        v = np.concatenate([v, np.zeros(1, np.uint16)])
    p0, p1 = v[0::2], v[1::2]
    out = np.empty((p0.size, 3), dtype=np.uint8)
    out[:, 0] = p0 & 0xFF
    out[:, 1] = (p0 >> 8) | ((p1 & 0x0F) << 4)
    out[:, 2] = p1 >> 4
    data = out.tobytes()
    return data[: (3 * flat.size + 1) // 2]


def unpack_mono12p(data: bytes | np.ndarray, count: int) -> np.ndarray:
    """Unpack ``count`` samples from GenICam Mono12p bytes; returns (count,) uint16."""
    need = (3 * count + 1) // 2
    b = np.frombuffer(data, dtype=np.uint8) if isinstance(data, (bytes, bytearray, memoryview)) else data
    if b.size < need:
        raise InputError(f"mono12p: {count} samples need {need} bytes, got {b.size}")
    b = b[:need]
    if b.size % 3:
        b = np.concatenate([b, np.zeros(3 - b.size % 3, np.uint8)])
    t = b.reshape(-1, 3).astype(np.uint16)
    out = np.empty(2 * t.shape[0], dtype=np.uint16)
    out[0::2] = t[:, 0] | ((t[:, 1] & 0x0F) << 8)
    out[1::2] = (t[:, 1] >> 4) | (t[:, 2] << 4)
    return out[:count]


# ----------------------------------------------------------------------------- reading


def _png_header(data: bytes, label: str) -> tuple[int, int, int, int]:
    """Walk every chunk of a PNG (lengths and CRCs), return (width, height, bit depth, colour type).

    Catches truncated and corrupted files before the decoder sees them.
    """
    if not data.startswith(_PNG_SIGNATURE):
        raise FrameError(label, "not a PNG file (bad signature)")
    pos, ihdr, seen_iend = len(_PNG_SIGNATURE), None, False
    while pos < len(data):
        if pos + 8 > len(data):
            raise FrameError(label, "truncated PNG (chunk header cut off)")
        length, ctype = struct.unpack(">I4s", data[pos : pos + 8])
        end = pos + 8 + length + 4
        if end > len(data):
            raise FrameError(label, f"truncated PNG ({ctype.decode('latin-1')!r} chunk cut off at byte {len(data)})")
        body = data[pos + 4 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[end - 4 : end])
        if zlib.crc32(body) & 0xFFFFFFFF != crc:
            raise FrameError(label, f"corrupt PNG (CRC mismatch in {ctype.decode('latin-1')!r} chunk)")
        if ctype == b"IHDR":
            if length != 13:
                raise FrameError(label, "corrupt PNG (bad IHDR)")
            ihdr = struct.unpack(">IIBB", body[4:14])
        pos = end
        if ctype == b"IEND":
            seen_iend = True
            break
    if ihdr is None:
        raise FrameError(label, "corrupt PNG (no IHDR chunk)")
    if not seen_iend:
        raise FrameError(label, "truncated PNG (no IEND chunk)")
    return ihdr


def _check_pixels(label: str, width: int, height: int) -> None:
    if width < 1 or height < 1:
        raise FrameError(label, f"the header declares an empty {width}x{height} image")
    if width * height > MAX_FRAME_PIXELS:
        raise FrameError(
            label,
            f"the header declares {width}x{height} = {width * height} pixels, more than the limit of "
            f"{MAX_FRAME_PIXELS}",
        )


#: What a colour frame is missing: the mosaic the polarization and colour are decoded from.
_RAW_HINT = (
    "pmvir reads the sensor's raw mosaic (one sample per pixel, as the camera saves Mono8, Mono12 or "
    "Mono16 frames), not a demosaiced colour image"
)


def _check_png_kind(label: str, bit_depth: int, colour_type: int) -> None:
    if colour_type != 0:
        kinds = {2: "an RGB", 3: "a palette", 4: "a grey+alpha", 6: "an RGBA"}
        raise FrameError(
            label,
            f"expected a single-channel greyscale PNG, got {kinds.get(colour_type, 'a colour')} image; {_RAW_HINT}",
        )
    if bit_depth not in (8, 16):
        raise FrameError(label, f"expected an 8- or 16-bit PNG, got {bit_depth}-bit")


def _read_png(path: Path, label: str) -> np.ndarray:
    data = path.read_bytes()
    w, h, bit_depth, colour_type = _png_header(data, label)
    _check_png_kind(label, bit_depth, colour_type)
    _check_pixels(label, w, h)
    try:
        img = cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as exc:
        raise FrameError(label, f"PNG could not be decoded: {exc.err or exc}") from None
    if img is None:
        raise FrameError(label, "PNG could not be decoded")
    return img


def _tiff_page(tif: tifffile.TiffFile, label: str) -> tifffile.TiffPage:
    if not tif.pages:
        raise FrameError(label, "TIFF has no image")
    page = tif.pages.first
    if page.samplesperpixel != 1 or len(page.shape) != 2:
        raise FrameError(label, f"expected a single-channel TIFF, got shape {page.shape}; {_RAW_HINT}")
    if page.dtype not in (np.dtype(np.uint8), np.dtype(np.uint16)):
        raise FrameError(label, f"expected an 8- or 16-bit unsigned TIFF, got {page.dtype}")
    _check_pixels(label, int(page.shape[1]), int(page.shape[0]))
    return page


def _read_tiff(path: Path, label: str) -> np.ndarray:
    try:
        with tifffile.TiffFile(path) as tif:
            page = _tiff_page(tif, label)
            size = path.stat().st_size
            if any(
                o + n > size for o, n in zip(page.dataoffsets, page.databytecounts, strict=True)
            ):
                raise FrameError(label, "truncated TIFF (image data runs past the end of the file)")
            img = page.asarray()
    except FrameError:
        raise
    except Exception as exc:  # tifffile raises many types for broken files
        raise FrameError(label, f"not a readable TIFF: {exc}") from exc
    return np.ascontiguousarray(img)


def _open_dng(path: Path, label: str) -> rawpy.RawPy:
    raw = rawpy.RawPy()
    try:
        raw.open_file(str(path))
    except Exception as exc:
        raw.close()
        raise FrameError(label, f"not a DNG that rawpy/LibRaw can read: {exc}") from exc
    return raw


def _read_dng(path: Path, label: str) -> np.ndarray:
    raw = _open_dng(path, label)
    try:
        try:
            raw.unpack()
        except Exception as exc:
            raise FrameError(label, f"DNG raw data could not be read: {exc}") from exc
        if raw.raw_type != rawpy.RawType.Flat:
            raise FrameError(
                label, "expected a single-plane CFA mosaic DNG, got a multi-channel (linear/demosaiced) DNG"
            )
        img = np.array(raw.raw_image, dtype=np.uint16, copy=True)
    finally:
        raw.close()
    if img.ndim != 2:
        raise FrameError(label, f"expected a single-plane CFA mosaic DNG, got raw data of shape {img.shape}")
    return img


def _check_raw_length(path: Path, label: str, raw: RawFormat | None) -> RawFormat:
    if raw is None:
        raise FrameError(label, "headerless frame but the manifest has no \"raw\": {width, height, dtype}")
    size = path.stat().st_size
    if size != raw.nbytes:
        how = "shorter" if size < raw.nbytes else "longer"
        raise FrameError(
            label,
            f"raw file is {how} than declared: {size} bytes, expected {raw.nbytes} "
            f"({raw.width}x{raw.height} {raw.dtype})",
        )
    return raw


def _read_raw(path: Path, label: str, raw: RawFormat | None) -> np.ndarray:
    raw = _check_raw_length(path, label, raw)
    data = path.read_bytes()
    shape = (raw.height, raw.width)
    if raw.dtype == "uint8":
        return np.frombuffer(data, dtype=np.uint8).reshape(shape).copy()
    if raw.dtype == "uint16le":
        return np.frombuffer(data, dtype="<u2").astype(np.uint16).reshape(shape)
    if raw.dtype == "uint16be":
        return np.frombuffer(data, dtype=">u2").astype(np.uint16).reshape(shape)
    return unpack_mono12p(data, raw.width * raw.height).reshape(shape)


def _label(path: Path, label: str | None) -> str:
    return str(path) if label is None else label


def _format_or_frame_error(path: Path, label: str) -> str:
    try:
        return frame_format(path)
    except ValueError:
        raise FrameError(
            label, f"unknown frame file type {path.suffix!r}; expected one of {sorted(FRAME_SUFFIXES)}"
        ) from None


def read_frame(path: str | Path, *, raw: RawFormat | None = None, label: str | None = None) -> np.ndarray:
    """Read the raw samples of one frame file.

    Args:
        path: the frame file; its suffix picks the format.
        raw: layout of headerless ``.raw``/``.bin`` files (ignored for other formats).
        label: the name used in error messages (default: ``path``).

    Returns:
        (H, W) uint8 (8-bit PNG/TIFF, raw uint8) or uint16 (everything else) samples as stored.

    Raises:
        FrameError: missing file, undecodable or truncated file, not a single-channel
            8/16-bit image, a DNG that is not a single-plane mosaic, a headerless file
            whose length does not match ``raw``.
    """
    path = Path(path)
    label = _label(path, label)
    fmt = _format_or_frame_error(path, label)
    if not path.is_file():
        raise FrameError(label, "frame file not found")
    if fmt == "png":
        return _read_png(path, label)
    if fmt == "tiff":
        return _read_tiff(path, label)
    if fmt == "dng":
        return _read_dng(path, label)
    return _read_raw(path, label, raw)


def read_frame_size(
    path: str | Path, *, raw: RawFormat | None = None, label: str | None = None
) -> tuple[int, int]:
    """(height, width) of a frame from its header (PNG chunks, TIFF tags, DNG header, raw length).

    Checks the file's structure as far as the header goes (PNG: every chunk's CRC;
    raw: the exact length) but does not decode pixels. Raises FrameError like
    :func:`read_frame`.
    """
    path = Path(path)
    label = _label(path, label)
    fmt = _format_or_frame_error(path, label)
    if not path.is_file():
        raise FrameError(label, "frame file not found")
    if fmt == "png":
        w, h, bit_depth, colour_type = _png_header(path.read_bytes(), label)
        _check_png_kind(label, bit_depth, colour_type)
        _check_pixels(label, w, h)
        return h, w
    if fmt == "tiff":
        try:
            with tifffile.TiffFile(path) as tif:
                page = _tiff_page(tif, label)
                return int(page.shape[0]), int(page.shape[1])
        except FrameError:
            raise
        except Exception as exc:
            raise FrameError(label, f"not a readable TIFF: {exc}") from exc
    if fmt == "dng":
        rp = _open_dng(path, label)
        try:
            return int(rp.sizes.raw_height), int(rp.sizes.raw_width)
        finally:
            rp.close()
    r = _check_raw_length(path, label, raw)
    return r.height, r.width


def png_significant_bits(path: str | Path) -> int | None:
    """Significant bits of a greyscale PNG from its ``sBIT`` chunk (e.g. 12 for 12-bit data in a
    16-bit PNG), or None when it has none. Reads the chunks before the image data only."""
    with open(path, "rb") as f:
        if f.read(len(_PNG_SIGNATURE)) != _PNG_SIGNATURE:
            return None
        while len(head := f.read(8)) == 8:
            length, ctype = struct.unpack(">I4s", head)
            if ctype == b"sBIT":
                body = f.read(length)
                return body[0] if body and 1 <= body[0] <= 16 else None
            if ctype in (b"IDAT", b"IEND"):
                return None
            f.seek(length + 4, os.SEEK_CUR)
    return None


def tiff_max_sample_value(path: str | Path) -> int | None:
    """The ``MaxSampleValue`` tag of a TIFF's first page, or None when absent or unreadable."""
    try:
        with tifffile.TiffFile(path) as tif:
            tag = tif.pages.first.tags.get("MaxSampleValue") if tif.pages else None
            value = None if tag is None else tag.value
    except Exception:  # noqa: BLE001 - a hint only; read_frame reports unreadable files
        return None
    if isinstance(value, tuple | list):
        value = value[0] if value else None
    return int(value) if isinstance(value, int) and value > 0 else None


def dng_levels(path: str | Path, *, label: str | None = None) -> tuple[float, int]:
    """(black level, white level) of a DNG as LibRaw reads them: the mean of the per-channel black
    levels, and the white level. FrameError when rawpy cannot open the file."""
    path = Path(path)
    raw = _open_dng(path, _label(path, label))
    try:
        black = [float(b) for b in raw.black_level_per_channel]
        return (sum(black) / len(black) if black else 0.0), int(raw.white_level)
    finally:
        raw.close()


# ----------------------------------------------------------------------------- writing


def _dng_tags(bit_depth: int) -> list[tuple]:
    white = (1 << bit_depth) - 1
    identity = (1, 1, 0, 1, 0, 1, 0, 1, 1, 1, 0, 1, 0, 1, 0, 1, 1, 1)  # SRATIONAL 3x3 identity
    return [
        (50706, 1, 4, (1, 4, 0, 0), True),  # DNGVersion
        (50707, 1, 4, (1, 1, 0, 0), True),  # DNGBackwardVersion
        (50708, 2, 0, "pmvir raw mosaic", True),  # UniqueCameraModel
        (33421, 3, 2, (2, 2), True),  # CFARepeatPatternDim
        (33422, 1, 4, (0, 1, 1, 2), True),  # CFAPattern RGGB (ignored by pmvir: the manifest rules)
        (50710, 1, 3, (0, 1, 2), True),  # CFAPlaneColor
        (50711, 3, 1, 1, True),  # CFALayout rectangular
        (50714, 4, 1, 0, True),  # BlackLevel
        (50717, 4, 1, white, True),  # WhiteLevel
        (50721, 10, 9, identity, True),  # ColorMatrix1
        (50778, 3, 1, 21, True),  # CalibrationIlluminant1 D65
    ]


def _encode(samples: np.ndarray, fmt: str, bit_depth: int, raw_dtype: str | None) -> bytes:
    h, w = samples.shape
    if fmt in ("png", "tiff"):
        arr: np.ndarray = samples.astype(np.uint8 if bit_depth <= 8 else np.uint16)
        if fmt == "png":
            ok, buf = cv2.imencode(".png", arr)
            if not ok:
                raise ValueError("PNG encoding failed")
            return buf.tobytes()
        bio = io.BytesIO()
        tifffile.imwrite(bio, arr, photometric="minisblack")
        return bio.getvalue()
    if fmt == "dng":
        if h < _DNG_MIN_SIZE or w < _DNG_MIN_SIZE:
            raise ShapeError(f"DNG frames must be at least {_DNG_MIN_SIZE}x{_DNG_MIN_SIZE} (LibRaw), got {w}x{h}")
        bio = io.BytesIO()
        tifffile.imwrite(
            bio,
            samples.astype(np.uint16),
            photometric=32803,  # CFA
            subfiletype=0,
            extratags=_dng_tags(bit_depth),
        )
        return bio.getvalue()
    if raw_dtype not in RAW_DTYPES:
        raise ConfigError(f"headerless frames need raw_dtype in {RAW_DTYPES}, got {raw_dtype!r}")
    limit = {"uint8": 8, "mono12p": 12}.get(raw_dtype, 16)
    if bit_depth > limit:
        raise ConfigError(f"raw dtype {raw_dtype} holds at most {limit} bits, bit_depth is {bit_depth}")
    if raw_dtype == "uint8":
        return samples.astype(np.uint8).tobytes()
    if raw_dtype == "uint16le":
        return samples.astype("<u2").tobytes()
    if raw_dtype == "uint16be":
        return samples.astype(">u2").tobytes()
    return pack_mono12p(samples)


def write_frame(
    path: str | Path, samples: np.ndarray, *, bit_depth: int, raw_dtype: str | None = None
) -> None:
    """Write one raw frame; the suffix of ``path`` picks the format.

    PNG and TIFF use an 8-bit container when ``bit_depth <= 8``, else 16-bit
    (values kept as they are, e.g. 0..4095 for 12-bit data). DNG is an
    uncompressed 16-bit CFA DNG (WhiteLevel tag 2^bit_depth - 1). Headerless
    files need ``raw_dtype``. The file is written atomically (temporary name in
    the same folder, then rename).

    Args:
        path: destination (.png, .tif, .tiff, .dng, .raw, .bin).
        samples: (H, W) integer samples, 0 <= value <= 2^bit_depth - 1.
        bit_depth: significant bits of the data, 1..16.
        raw_dtype: one of :data:`RAW_DTYPES`, for .raw/.bin only.

    Raises:
        InputError: unknown suffix, values out of range for ``bit_depth``.
        ShapeError / DTypeError: not a 2-D integer array; a DNG under 22x22 pixels.
        ConfigError: ``bit_depth`` or ``raw_dtype`` out of range, a container too small for ``bit_depth``.
    """
    path = Path(path)
    fmt = frame_format(path)
    samples = np.asarray(samples)
    if samples.ndim != 2 or samples.size == 0:
        raise ShapeError(f"expected (H, W) samples, got shape {samples.shape}")
    if not np.issubdtype(samples.dtype, np.integer):
        raise DTypeError(f"expected integer samples, got {samples.dtype}")
    if not 1 <= bit_depth <= 16:
        raise ConfigError(f"bit_depth must be 1..16, got {bit_depth}")
    if samples.min() < 0 or samples.max() > (1 << bit_depth) - 1:
        raise InputError(
            f"samples must lie in 0..{(1 << bit_depth) - 1} for bit_depth {bit_depth}, "
            f"got {samples.min()}..{samples.max()}"
        )
    data = _encode(samples, fmt, bit_depth, raw_dtype)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, path)
    finally:
        if tmp.exists():
            tmp.unlink()
