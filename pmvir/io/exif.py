"""Focal length in pixels from a frame file's EXIF tags (PNG ``eXIf``, TIFF and DNG IFDs).

:func:`exif_focal_px` reads, from the first of these a file holds:

1. ``FocalLength`` (mm) with ``FocalPlaneXResolution`` / ``FocalPlaneYResolution`` and
   ``FocalPlaneResolutionUnit`` (pixels per inch, cm or mm of the sensor): fx, fy in pixels;
2. ``FocalLengthIn35mmFilm``: f_px = f35 * hypot(W, H) / hypot(36, 24) (the 35 mm
   equivalent is defined by the diagonal);
3. ``FocalLength`` alone, with the pixel pitch of a sensor the caller knows (the
   IMX250's 3.45 um): f_px = f_mm / pitch_mm.

PNG EXIF is read with Pillow, TIFF and DNG tags with tifffile (DNG keeps the
tags in IFD 0 as TIFF/EP allows, or in the EXIF sub-IFD). A file without such
tags, or with tags that do not parse, gives None: EXIF is a hint, never an error.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import tifffile
from PIL import Image

from pmvir.io.frames import frame_format

#: EXIF tag numbers.
_FOCAL_LENGTH = 37386
_FOCAL_35MM = 41989
_FP_XRES = 41486
_FP_YRES = 41487
_FP_UNIT = 41488
_EXIF_IFD = 34665
#: FocalPlaneResolutionUnit -> millimetres per unit (EXIF: 2 inch, 3 cm; 4 mm and 5 um are seen too).
_MM_PER_UNIT = {2: 25.4, 3: 10.0, 4: 1.0, 5: 0.001}


@dataclass(frozen=True)
class ExifFocal:
    """A focal length in pixels of the full frame and how it was found.

    Attributes:
        fx, fy: focal lengths, pixels.
        source: the tags used, for a person reading what was inferred.
    """

    fx: float
    fy: float
    source: str


def _number(value: Any) -> float | None:
    """An EXIF rational (tuple, IFDRational, or number) as a positive finite float, else None."""
    try:
        if isinstance(value, tuple | list):
            if len(value) == 2:
                out = float(value[0]) / float(value[1]) if float(value[1]) else math.nan
            else:
                out = float(value[0])
        else:
            out = float(value)
    except (TypeError, ValueError, ZeroDivisionError, IndexError):
        return None
    return out if math.isfinite(out) and out > 0 else None


def _tiff_tags(path: Path) -> dict[int, Any]:
    tags: dict[int, Any] = {}
    with tifffile.TiffFile(path) as tif:
        if not tif.pages:
            return tags
        for tag in tif.pages.first.tags.values():
            if tag.code == _EXIF_IFD and isinstance(tag.value, dict):
                for name, value in tag.value.items():
                    code = tifffile.TIFF.TAGS.get(str(name), None)
                    if isinstance(code, int):
                        tags.setdefault(code, value)
            else:
                tags.setdefault(tag.code, tag.value)
    return tags


def _png_tags(path: Path) -> dict[int, Any]:
    with Image.open(path) as im:
        exif = im.getexif()
        tags: dict[int, Any] = dict(exif.items())
        tags.update(exif.get_ifd(_EXIF_IFD))
    return tags


def read_exif_tags(path: str | Path) -> dict[int, Any]:
    """EXIF tags of a PNG, TIFF or DNG by tag number (IFD 0 and the EXIF sub-IFD); {} when none or unreadable."""
    path = Path(path)
    try:
        fmt = frame_format(path)
        if fmt == "png":
            return _png_tags(path)
        if fmt in ("tiff", "dng"):
            return _tiff_tags(path)
    except Exception:  # noqa: BLE001 - EXIF is a hint: a file whose tags do not parse has none
        return {}
    return {}


def exif_focal_px(
    path: str | Path, width: int, height: int, *, pixel_pitch_mm: float | None = None
) -> ExifFocal | None:
    """The focal length in pixels from a frame's EXIF tags (module docstring: the order), or None.

    Args:
        path: a .png, .tif/.tiff or .dng frame.
        width, height: the frame's size in pixels.
        pixel_pitch_mm: the sensor's pixel pitch, used when only ``FocalLength`` is given.
    """
    tags = read_exif_tags(path)
    f_mm = _number(tags.get(_FOCAL_LENGTH))
    xres, yres = _number(tags.get(_FP_XRES)), _number(tags.get(_FP_YRES))
    unit_code = tags.get(_FP_UNIT, 2)
    unit = _MM_PER_UNIT.get(unit_code) if isinstance(unit_code, int) else None
    if f_mm is not None and xres is not None and unit is not None:
        fx = f_mm * xres / unit
        fy = f_mm * (yres if yres is not None else xres) / unit
        return ExifFocal(fx, fy, f"EXIF FocalLength {f_mm:g} mm and FocalPlaneX/YResolution")
    f35 = _number(tags.get(_FOCAL_35MM))
    if f35 is not None:
        f = f35 * math.hypot(width, height) / math.hypot(36.0, 24.0)
        return ExifFocal(f, f, f"EXIF FocalLengthIn35mmFilm {f35:g} mm")
    if f_mm is not None and pixel_pitch_mm is not None:
        f = f_mm / pixel_pitch_mm
        return ExifFocal(f, f, f"EXIF FocalLength {f_mm:g} mm and the sensor's {pixel_pitch_mm * 1000:g} um pixels")
    return None
