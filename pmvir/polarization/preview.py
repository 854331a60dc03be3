"""8-bit preview images of decoded polarization frames (for people, not for the pipeline).

* Intensity (I_int, I_min): auto-exposed, then clipped and sRGB-encoded. The
  exposure scale maps the 99.5th percentile of the valid pixels' brightest
  channel to white (:func:`exposure_scale`); I_int and I_min of a frame share
  I_int's scale so that they can be compared.
* DoP: grey, linear, 0 -> black, 1 -> white; invalid pixels black.
* AoP: colour wheel. Hue is the AoP over [0, pi) mapped onto the full hue
  circle (0 red, pi/3 green, 2 pi/3 blue, back to red at pi); saturation is
  ``min(DoP / dop_full_saturation, 1)`` (default 0.5: DoP 0 white, DoP >= 0.5
  fully saturated); value 1; invalid pixels black.

All functions take float32 arrays as produced by
:func:`pmvir.polarization.stokes.polarization_images` and return uint8
images, RGB channel order.
"""

from __future__ import annotations

import os
from pathlib import Path

import cv2
import numpy as np

from pmvir.errors import ConfigError, ShapeError

#: Percentile of the valid pixels' brightest channel mapped to white.
EXPOSURE_PERCENTILE = 99.5
#: DoP at and above which the AoP wheel is fully saturated.
DOP_FULL_SATURATION = 0.5


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """The sRGB transfer function (IEC 61966-2-1) of linear values clipped to [0, 1].

    Args:
        linear: any shape, float.

    Returns:
        Same shape, float32 in [0, 1].
    """
    x = np.clip(linear, 0.0, 1.0).astype(np.float32)
    low = x * np.float32(12.92)
    high = np.float32(1.055) * np.power(x, np.float32(1 / 2.4)) - np.float32(0.055)
    return np.where(x <= 0.0031308, low, high).astype(np.float32)


def exposure_scale(image: np.ndarray, valid: np.ndarray | None = None, *,
                   percentile: float = EXPOSURE_PERCENTILE) -> float:
    """Factor that maps the given percentile of the brightest channel to 1.

    Args:
        image: (H, W, C) float linear intensities.
        valid: optional (H, W) bool; only these pixels count (all pixels when
            none is valid).
        percentile: in (0, 100].

    Returns:
        A positive scale (1.0 when the image is black).
    """
    if image.ndim != 3:
        raise ShapeError(f"expected an (H, W, C) image, got shape {image.shape}")
    peak = image.max(axis=2)
    if valid is not None and valid.any():
        peak = peak[valid]
    peak = peak[np.isfinite(peak)]
    if peak.size == 0:
        return 1.0
    level = float(np.percentile(peak, percentile))
    return 1.0 / level if level > 1e-12 else 1.0


def intensity_preview(image: np.ndarray, *, scale: float = 1.0) -> np.ndarray:
    """sRGB 8-bit preview of a linear image.

    Args:
        image: (H, W, 3) float linear intensities (normalized units).
        scale: exposure factor applied before clipping to [0, 1].

    Returns:
        (H, W, 3) uint8, RGB.
    """
    if image.ndim != 3 or image.shape[2] != 3:
        raise ShapeError(f"expected an (H, W, 3) image, got shape {image.shape}")
    encoded = srgb_encode(image * np.float32(scale))
    return np.rint(encoded * 255.0).astype(np.uint8)


def dop_preview(dop: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """Grey 8-bit DoP: 0 black, 1 white, linear; invalid pixels black.

    Args:
        dop: (H, W) float in [0, 1].
        valid: optional (H, W) bool.

    Returns:
        (H, W) uint8.
    """
    grey = np.rint(np.clip(dop, 0.0, 1.0) * 255.0).astype(np.uint8)
    if valid is not None:
        grey[~valid] = 0
    return grey


def aop_preview(aop: np.ndarray, dop: np.ndarray, valid: np.ndarray | None = None, *,
                dop_full_saturation: float = DOP_FULL_SATURATION) -> np.ndarray:
    """AoP colour wheel with DoP as saturation.

    Args:
        aop: (H, W) float radians in [0, pi).
        dop: (H, W) float in [0, 1].
        valid: optional (H, W) bool; invalid pixels are black.
        dop_full_saturation: DoP mapped to full saturation (> 0).

    Returns:
        (H, W, 3) uint8, RGB.
    """
    if aop.shape != dop.shape or aop.ndim != 2:
        raise ShapeError(f"expected matching (H, W) aop and dop, got {aop.shape} and {dop.shape}")
    if not dop_full_saturation > 0:
        raise ConfigError(f"dop_full_saturation must be > 0, got {dop_full_saturation}")
    hue = np.mod(aop, np.pi).astype(np.float32) * np.float32(360.0 / np.pi)
    sat = np.clip(dop / np.float32(dop_full_saturation), 0.0, 1.0).astype(np.float32)
    hsv = cv2.merge([hue, sat, np.ones_like(sat)])
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)  # float32 HSV: H in [0, 360)
    out = np.rint(np.clip(rgb, 0.0, 1.0) * 255.0).astype(np.uint8)
    if valid is not None:
        out[~valid] = 0
    return out


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write an 8-bit grey (H, W) or RGB (H, W, 3) image as PNG, atomically.

    Returns:
        The path written.
    """
    path = Path(path)
    if image.dtype != np.uint8 or image.ndim not in (2, 3):
        raise ShapeError(f"expected a uint8 (H, W) or (H, W, 3) image, got {image.dtype} {image.shape}")
    data = image if image.ndim == 2 else cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    ok, buf = cv2.imencode(".png", data)
    if not ok:  # pragma: no cover - OpenCV failure
        raise OSError(f"could not encode {path} as PNG")
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_bytes(buf.tobytes())
    os.replace(tmp, path)
    return path
