"""Decoding: raw mosaic -> I_int, I_min, AoP, DoP, valid (pipeline stage 1).

:func:`decode_frame` turns one normalized mosaic into
:class:`~pmvir.polarization.stokes.PolarizationImages` (demosaicing, then the
spec section 2 quantities); :func:`decode_capture` does it for the frames of a
capture and writes, per frame, ``DIR/<stem>.npz`` (the spec's decoded frame)
and PNG previews beside it:

==========================  ====================================================
``<stem>.npz``              ``i_int``, ``i_min`` (H, W, 3) float32 linear, units
                            ``(sample - black) / (white - black) / exposure``;
                            ``aop`` (H, W) float32 radians [0, pi), ccw; ``dop``
                            (H, W) float32 [0, 1]; ``valid`` (H, W) bool
``<stem>_int.png``          I_int, auto-exposed, sRGB (see :mod:`pmvir.polarization.preview`)
``<stem>_min.png``          I_min with I_int's exposure
``<stem>_dop.png``          DoP, grey
``<stem>_aop.png``          AoP colour wheel, DoP as saturation
==========================  ====================================================

A pixel is invalid (``valid`` False) when its colour-mean intensity is at or
below ``DecodeOptions.noise_floor``, when any mosaic sample within the
demosaicing footprint is saturated, or when the frame's mask marks it as
background. Monochrome sensors give grey I_int / I_min repeated in R, G, B.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from pmvir.capture import Capture, open_capture
from pmvir.config import DecodeOptions
from pmvir.errors import CaptureError, ConfigError, ShapeError
from pmvir.polarization.demosaic import demosaic, saturation_footprint
from pmvir.polarization.layout import MosaicLayout
from pmvir.polarization.noise import closure_noise, unbiased_dop
from pmvir.polarization.preview import (
    aop_preview,
    dop_preview,
    exposure_scale,
    intensity_preview,
    write_png,
)
from pmvir.polarization.stokes import PolarizationImages, PolarizationWriter, unpolarized_intensity
from pmvir.progress import Progress

#: Arrays of a decoded-frame file: name -> (dtype, number of dimensions).
NPZ_KEYS: dict[str, tuple[type, int]] = {
    "i_int": (np.float32, 3),
    "i_min": (np.float32, 3),
    "aop": (np.float32, 2),
    "dop": (np.float32, 2),
    "valid": (np.bool_, 2),
}

#: Suffixes of the preview PNGs written beside each ``<stem>.npz``.
PREVIEW_SUFFIXES = ("_int.png", "_min.png", "_dop.png", "_aop.png")



def decode_frame(
    mosaic: np.ndarray,
    layout: MosaicLayout,
    *,
    saturated: np.ndarray | None = None,
    mask: np.ndarray | None = None,
    options: DecodeOptions | None = None,
) -> PolarizationImages:
    """Polarization images of one raw frame.

    Args:
        mosaic: (H, W) float32 normalized samples (exposure-divided, black level removed).
        layout: the sensor layout (angles ccw).
        saturated: optional (H, W) bool, samples at or above the white level.
        mask: optional (H, W) bool foreground mask; False pixels are invalid.
        options: demosaicing method, noise floor and DoP estimator (defaults: ``DecodeOptions()``).

    Returns:
        i_int, i_min (H, W, 3) float32; aop, dop (H, W) float32; valid (H, W) bool.
    """
    options = options or DecodeOptions()
    if mosaic.ndim != 2:
        raise ShapeError(f"expected an (H, W) mosaic, got shape {mosaic.shape}")
    for name, m in (("saturated", saturated), ("mask", mask)):
        if m is not None and m.shape != mosaic.shape:
            raise ShapeError(f"{name} has shape {m.shape}, the mosaic {mosaic.shape}")
    invalid = None
    if saturated is not None and saturated.any():
        invalid = saturation_footprint(saturated, layout, method=options.demosaic)
    if mask is not None:
        invalid = ~mask.astype(bool) if invalid is None else invalid | ~mask.astype(bool)
    # the Stokes quantities are computed strip by strip as the demosaicing finishes each strip
    intensities = np.empty((4, layout.channels, *mosaic.shape), dtype=np.float32).transpose(2, 3, 0, 1)
    writer = PolarizationWriter(intensities, noise_floor=options.noise_floor, invalid=invalid)
    demosaic(mosaic, layout, method=options.demosaic, out=intensities, on_strip=writer.write)
    images = writer.result()
    if options.dop_estimator == "unbiased":
        noise = closure_noise(mosaic, layout, valid=images.valid)
        dop = unbiased_dop(images.dop, noise, method=options.demosaic, channels=layout.channels)
        images = PolarizationImages(
            i_int=images.i_int,
            i_min=unpolarized_intensity(images.i_int, dop),
            aop=images.aop,
            dop=dop,
            valid=images.valid,
        )
    if images.i_int.shape[2] == 1:
        images = PolarizationImages(
            i_int=np.repeat(images.i_int, 3, axis=2),
            i_min=np.repeat(images.i_min, 3, axis=2),
            aop=images.aop,
            dop=images.dop,
            valid=images.valid,
        )
    return images


def write_decoded(path: str | Path, images: PolarizationImages, *, compress: bool = False) -> Path:
    """Write a decoded frame as ``.npz`` (atomically: temporary name, then rename).

    Args:
        path: the ``.npz`` file.
        images: what :func:`decode_frame` returned.
        compress: zlib-compress the arrays (smaller, several times slower).
    """
    path = Path(path)
    arrays = {k: getattr(images, k) for k in NPZ_KEYS}
    for k, (dtype, ndim) in NPZ_KEYS.items():
        arrays[k] = np.ascontiguousarray(arrays[k], dtype=dtype)
        if arrays[k].ndim != ndim:
            raise ShapeError(f"{k} must have {ndim} dimensions, got shape {arrays[k].shape}")
    tmp = path.with_name(f".{path.name}.tmp")
    with open(tmp, "wb") as f:
        (np.savez_compressed if compress else np.savez)(f, **arrays)
    os.replace(tmp, path)
    return path


def read_decoded(path: str | Path) -> PolarizationImages:
    """Read a decoded-frame ``.npz`` and check its keys, dtypes and shapes.

    Raises:
        CaptureError: the file is missing, unreadable, or not a decoded frame.
    """
    path = Path(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise CaptureError(path, f"cannot read decoded frame: {exc}") from exc
    if set(arrays) != set(NPZ_KEYS):
        raise CaptureError(path, f"expected arrays {sorted(NPZ_KEYS)}, found {sorted(arrays)}")
    for k, (dtype, ndim) in NPZ_KEYS.items():
        a = arrays[k]
        if a.dtype != dtype or a.ndim != ndim:
            raise CaptureError(path, f"{k}: expected {ndim}-D {np.dtype(dtype)}, got {a.ndim}-D {a.dtype}")
    h, w = arrays["aop"].shape
    for k in NPZ_KEYS:
        want = (h, w, 3) if arrays[k].ndim == 3 else (h, w)
        if arrays[k].shape != want:
            raise CaptureError(path, f"{k}: expected shape {want}, got {arrays[k].shape}")
    return PolarizationImages(**arrays)


def write_previews(out_dir: str | Path, stem: str, images: PolarizationImages) -> list[Path]:
    """Write the four preview PNGs of a decoded frame; returns their paths."""
    out_dir = Path(out_dir)
    scale = exposure_scale(images.i_int, images.valid)
    return [
        write_png(out_dir / f"{stem}_int.png", intensity_preview(images.i_int, scale=scale)),
        write_png(out_dir / f"{stem}_min.png", intensity_preview(images.i_min, scale=scale)),
        write_png(out_dir / f"{stem}_dop.png", dop_preview(images.dop, images.valid)),
        write_png(out_dir / f"{stem}_aop.png", aop_preview(images.aop, images.dop, images.valid)),
    ]


def select_frames(capture: Capture, frames: Sequence[str | int] | None) -> list[int]:
    """Indices of the frames named by stem (e.g. "003") or by 0-based index.

    A string that is a frame's stem names that frame; otherwise a string of
    digits (or an int) is an index. None selects every frame.

    Raises:
        ConfigError: a name that is no frame's stem, or an index out of range.
    """
    n = len(capture.frames)
    if frames is None:
        return list(range(n))
    chosen: list[int] = []
    for item in frames:
        if isinstance(item, str):
            try:
                chosen.append(capture.index(item))
                continue
            except KeyError:
                if not item.strip().lstrip("-").isdigit():
                    raise ConfigError(
                        f"no frame named {item!r}; frames are "
                        f"{', '.join(f.name for f in capture.frames[:8])}{' ...' if n > 8 else ''}"
                    ) from None
                item = int(item)
        if not 0 <= item < n:
            raise ConfigError(f"frame index {item} out of range: the capture has {n} frames (0..{n - 1})")
        chosen.append(int(item))
    return list(dict.fromkeys(chosen))


def decode_capture(
    capture: str | Path | Capture,
    out_dir: str | Path,
    *,
    options: DecodeOptions | None = None,
    frames: Sequence[str | int] | None = None,
    previews: bool = True,
    compress: bool = False,
    progress: Progress | None = None,
) -> list[Path]:
    """Decode frames of a capture to ``out_dir/<stem>.npz`` plus previews.

    Args:
        capture: capture folder / zip / capture.json path, or an open Capture.
        out_dir: created if missing; existing files of the same names are replaced.
        options: demosaicing method and noise floor.
        frames: stems or 0-based indices to decode (default: all), see :func:`select_frames`.
        previews: also write the PNG previews.
        compress: compress the ``.npz`` files.
        progress: reports after each frame (its fraction of the frames) and is polled
            for cancellation.

    Returns:
        The ``.npz`` paths written, in decoding order.

    Raises:
        CaptureError: the capture or one of its frames/masks is unreadable or invalid.
        ConfigError: a requested frame does not exist.
    """
    if isinstance(capture, Capture):
        return _decode_open(capture, Path(out_dir), options, frames, previews, compress, progress)
    with open_capture(capture) as cap:
        return _decode_open(cap, Path(out_dir), options, frames, previews, compress, progress)


def _decode_open(
    cap: Capture,
    out_dir: Path,
    options: DecodeOptions | None,
    frames: Sequence[str | int] | None,
    previews: bool,
    compress: bool,
    progress: Progress | None,
) -> list[Path]:
    indices = select_frames(cap, frames)
    out_dir.mkdir(parents=True, exist_ok=True)
    total = len(indices)
    progress = progress or Progress.none()
    written: list[Path] = []
    for done, i in enumerate(indices, start=1):
        raw = cap.read_raw(i)
        images = decode_frame(
            raw.mosaic, cap.layout, saturated=raw.saturated, mask=cap.read_mask(i), options=options
        )
        stem = cap.frames[i].name
        written.append(write_decoded(out_dir / f"{stem}.npz", images, compress=compress))
        if previews:
            write_previews(out_dir, stem, images)
        progress.update(done / total, f"decoded {cap.frames[i].file}")
    return written
