"""The working resolution: full-size frames binned for the geometry and refinement stages.

A 2448x2048 IMX250MYR frame holds more pixels than the refined mesh can use: the
subdivision sizes triangles in image pixels, so the mesh, the refinement's samples and
its memory would grow with the pixel count. Every frame is therefore decoded at full
resolution, one at a time, and binned right away by an integer factor ``f`` (the
smallest one that brings the longer side to ``decode.max_working_size_px`` or less).
Only the binned images are held, and the geometry and refinement stages see a capture
whose intrinsics and masks are binned the same way (:class:`BinnedCapture`).

Binning follows the capture spec's conventions (section 1: COLMAP pixel centres at
+0.5): the frame is cropped to a multiple of ``f`` at its right and bottom edges and a
working pixel covers an ``f x f`` block, so ``u' = u / f`` and ``fx' = fx / f``,
``cx' = cx / f`` (likewise y). The polarization of a block is that of its summed light:
the normalized Stokes vectors (DoP cos 2 AoP, DoP sin 2 AoP) averaged with the
colour-mean intensity as weight, then AoP and DoP taken from the average (AoP is axial:
raw angles are never averaged). Intensities are averaged; a working pixel is valid only
when every pixel of its block is; a mask keeps the block when at least half of it is
foreground.
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from pmvir.capture import Capture, CaptureFrame
from pmvir.errors import ConfigError, ShapeError
from pmvir.io.manifest import Intrinsics
from pmvir.polarization.stokes import PolarizationImages


def binning_factor(width: int, height: int, max_size_px: int) -> int:
    """The smallest integer factor that brings ``max(width, height)`` to ``max_size_px`` or less.

    Args:
        width, height: the frame size in pixels (> 0).
        max_size_px: the longest side the working images may have; 0 means full resolution.

    Returns:
        The factor, >= 1 (1 when the frame already fits or ``max_size_px`` is 0).
    """
    if width <= 0 or height <= 0:
        raise ConfigError(f"expected a positive frame size, got {width}x{height}")
    if max_size_px < 0:
        raise ConfigError(f"max_size_px must be >= 0, got {max_size_px}")
    if max_size_px == 0:
        return 1
    return max(1, math.ceil(max(width, height) / max_size_px))


def _block_mean(a: np.ndarray, f: int) -> np.ndarray:
    """Mean over ``f x f`` blocks of the first two axes (cropped to multiples of f), float32."""
    h, w = a.shape[0] // f, a.shape[1] // f
    blocks = a[: h * f, : w * f].reshape(h, f, w, f, *a.shape[2:])
    return blocks.mean(axis=(1, 3), dtype=np.float64).astype(np.float32)


def bin_images(images: PolarizationImages, f: int) -> PolarizationImages:
    """One frame's decoded images at the working resolution (module docstring).

    Args:
        images: full-resolution images, (H, W[, C]).
        f: the binning factor (>= 1); 1 returns ``images`` itself.

    Returns:
        Images of shape (H // f, W // f[, C]), float32 (``valid`` bool).
    """
    if f < 1:
        raise ConfigError(f"binning factor must be >= 1, got {f}")
    if f == 1:
        return images
    h, w = images.aop.shape
    if h < f or w < f:
        raise ShapeError(f"a {w}x{h} frame cannot be binned by {f}")
    weight = images.i_int.mean(axis=2) if images.i_int.ndim == 3 else images.i_int
    weight = np.maximum(weight, 0.0).astype(np.float32)
    two_phi = 2.0 * images.aop.astype(np.float32)
    q = _block_mean(weight * images.dop * np.cos(two_phi), f)
    u = _block_mean(weight * images.dop * np.sin(two_phi), f)
    total = _block_mean(weight, f)
    dark = total <= 0.0
    safe = np.where(dark, 1.0, total).astype(np.float32)
    q, u = q / safe, u / safe
    if dark.any():  # blocks without light: the unweighted average of the normalized Stokes vectors
        q = np.where(dark, _block_mean(images.dop * np.cos(two_phi), f), q)
        u = np.where(dark, _block_mean(images.dop * np.sin(two_phi), f), u)
    dop = np.clip(np.hypot(q, u), 0.0, 1.0).astype(np.float32)
    aop = np.mod(0.5 * np.arctan2(u, q), np.pi).astype(np.float32)
    aop[aop >= np.float32(np.pi)] = 0.0
    valid_blocks = images.valid[: (h // f) * f, : (w // f) * f].reshape(h // f, f, w // f, f)
    return PolarizationImages(
        i_int=_block_mean(images.i_int, f),
        i_min=_block_mean(images.i_min, f),
        aop=aop,
        dop=dop,
        valid=np.asarray(valid_blocks.all(axis=(1, 3)), dtype=bool),
    )


def bin_mask(mask: np.ndarray | None, f: int) -> np.ndarray | None:
    """A foreground mask at the working resolution: a block is foreground when at least half of it is."""
    if mask is None or f == 1:
        return mask
    return _block_mean(mask.astype(np.float32), f) >= 0.5


def bin_noise(noise: np.ndarray, f: int) -> np.ndarray:
    """A per-pixel noise map at the working resolution: the mean over each block's measured pixels.

    Demosaiced neighbours share raw samples, so a block's noise is not divided by ``f``: the
    mean is the conservative figure. NaN (unmeasured) where no pixel of the block is measured.
    """
    if f == 1:
        return noise
    measured = np.isfinite(noise)
    total = _block_mean(np.where(measured, noise, 0.0).astype(np.float32), f)
    count = _block_mean(measured.astype(np.float32), f)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 0, total / np.maximum(count, 1e-12), np.nan).astype(np.float32)


def bin_intrinsics(k: Intrinsics, f: int) -> Intrinsics:
    """Pinhole intrinsics of the frame binned by ``f`` (cropped to a multiple of f)."""
    if f == 1:
        return k
    return k.model_copy(
        update={
            "width": k.width // f,
            "height": k.height // f,
            "fx": k.fx / f,
            "fy": k.fy / f,
            "cx": k.cx / f,
            "cy": k.cy / f,
        }
    )


class BinnedCapture(Capture):
    """An open capture as the geometry and refinement stages see it at the working resolution.

    The frames' intrinsics and the masks are binned by ``factor``; raw frames
    (:meth:`read_raw`) stay at full resolution, checked against the full-size intrinsics.
    It shares the wrapped capture's files and leaves closing to it.

    Attributes:
        full: the wrapped capture.
        factor: the binning factor (>= 1).
    """

    def __init__(self, cap: Capture, factor: int):
        if factor < 1:
            raise ConfigError(f"binning factor must be >= 1, got {factor}")
        self.__dict__.update(cap.__dict__)
        self._cleanup = None  # the wrapped capture owns a zip's extraction
        self.full = cap
        self.factor = factor
        self.frames: tuple[CaptureFrame, ...] = tuple(
            f if f.intrinsics is None else replace(f, intrinsics=bin_intrinsics(f.intrinsics, factor))
            for f in cap.frames
        )

    def _expected_size(self, i: int) -> tuple[int, int] | None:
        return self.full._expected_size(i)

    def read_mask(self, i: int) -> np.ndarray | None:
        """(H // factor, W // factor) bool foreground mask of frame i, or None."""
        return bin_mask(self.full.read_mask(i), self.factor)


def working_capture(cap: Capture, factor: int) -> Capture:
    """``cap`` itself when ``factor`` is 1, else its :class:`BinnedCapture`."""
    return cap if factor == 1 else BinnedCapture(cap, factor)


def unbin_mask(mask: np.ndarray, f: int, shape: tuple[int, ...]) -> np.ndarray:
    """A working-resolution bool mask at full resolution ``shape`` (H, W): each pixel takes its
    block's value; the cropped right and bottom edges are False."""
    if f == 1:
        return mask
    full = np.zeros(shape[:2], dtype=bool)
    up = np.repeat(np.repeat(mask, f, axis=0), f, axis=1)
    full[: up.shape[0], : up.shape[1]] = up
    return full


def frame_extent(cap: Capture) -> tuple[int, int]:
    """(width, height): the largest frame width and height of a capture, from the headers."""
    sizes = [cap.frame_size(i) for i in range(len(cap.frames))]
    return max(w for _, w in sizes), max(h for h, _ in sizes)


def resolution_report(extent: tuple[int, int], factor: int) -> dict[str, object]:
    """What report.json says of the resolutions: the frames', the binning factor and the working size."""
    w, h = extent
    working = f"{w // factor}x{h // factor}"
    return {"frames": f"{w}x{h}", "binning": factor, "decode": f"{w}x{h}", "geometry": working, "refine": working}
