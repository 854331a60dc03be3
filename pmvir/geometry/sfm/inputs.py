"""What SfM is given: the views checked, their 8-bit SIFT images and masks written for COLMAP, their intrinsics."""

from __future__ import annotations

import shutil
from collections.abc import Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import cv2
import numpy as np

from pmvir.camera import Camera
from pmvir.config import SfmOptions
from pmvir.errors import InputError, ShapeError
from pmvir.polarization.preview import srgb_encode
from pmvir.threads import usable_threads

#: Percentile of the foreground grey level mapped to white in the SIFT images.
EXPOSURE_PERCENTILE = 99.5

#: cv2.imwrite flags of the scratch PNGs COLMAP reads once: uncompressed (half the time to write).
SCRATCH_PNG = [cv2.IMWRITE_PNG_COMPRESSION, 0]


def sift_image(
    image: np.ndarray, mask: np.ndarray | None = None, *, equalize: bool = True, denoise: float = 0.0
) -> np.ndarray:
    """The 8-bit grey image SIFT sees.

    Args:
        image: (H, W, C) or (H, W) float linear intensities (any positive scale).
        mask: optional (H, W) bool foreground; the exposure is set on it.
        equalize: apply CLAHE (clip limit 2, 8 x 8 tiles); without it the 0.5th percentile (over
            the mask) is black instead, so an unknown pedestal (a black level left in the
            intensities) does not lift the shadows.
        denoise: strength h (grey levels) of OpenCV's non-local-means denoising (7 x 7 patches
            searched over 21 x 21 pixels) before the equalization; 0: none.

    Returns:
        (H, W) uint8: the channel mean scaled so its 99.5th percentile (over the mask)
        is 1 (and, not equalized, shifted so its 0.5th is 0), sRGB-encoded, optionally denoised
        and equalized.
    """
    grey = image.mean(axis=2) if image.ndim == 3 else image
    if grey.ndim != 2:
        raise ShapeError(f"expected an (H, W) or (H, W, C) image, got shape {image.shape}")
    grey = np.nan_to_num(grey.astype(np.float32), nan=0.0, posinf=0.0, neginf=0.0)
    values = grey[mask] if mask is not None and mask.any() else grey.ravel()
    level = float(np.percentile(values, EXPOSURE_PERCENTILE)) if values.size else 0.0
    black = 0.0 if equalize or not values.size else float(np.percentile(values, 100.0 - EXPOSURE_PERCENTILE))
    if level - black > 1e-12:
        grey = np.maximum(grey - np.float32(black), 0.0)
        level -= black
    scale = 1.0 / level if level > 1e-12 else 1.0
    out: np.ndarray = np.rint(srgb_encode(grey * np.float32(scale)) * 255.0).astype(np.uint8)
    if denoise > 0:
        out = cv2.fastNlMeansDenoising(out, None, float(denoise), 7, 21)
    if equalize:
        out = cv2.createCLAHE(clipLimit=2.0, tileGridSize=(8, 8)).apply(out)
    return out


def check_inputs(
    images: Sequence[np.ndarray],
    names: Sequence[str],
    cameras: Sequence[Camera | None] | None,
    intrinsics: Sequence[np.ndarray | None] | None,
    masks: Sequence[np.ndarray | None] | None,
) -> None:
    """Raise InputError or ShapeError unless names are distinct and every per-view list, image,
    mask, camera and K agrees with the images (at least 16 x 16, K without skew)."""
    n = len(images)
    if len(names) != n or len(set(names)) != n:
        raise InputError(f"expected {n} distinct names, got {len(names)} ({len(set(names))} distinct)")
    for label, seq in (("cameras", cameras), ("intrinsics", intrinsics), ("masks", masks)):
        if seq is not None and len(seq) != n:
            raise ShapeError(f"{label} has {len(seq)} entries for {n} images")
    for i, im in enumerate(images):
        if im.ndim not in (2, 3) or min(im.shape[:2]) < 16:
            raise ShapeError(f"view {names[i]}: expected an (H, W, C) image of at least 16 x 16, got {im.shape}")
        h, w = im.shape[:2]
        mask = masks[i] if masks is not None else None
        if mask is not None and mask.shape != (h, w):
            raise ShapeError(f"view {names[i]}: mask {mask.shape} does not match the image {(h, w)}")
        cam = cameras[i] if cameras is not None else None
        if cam is not None and (cam.width, cam.height) != (w, h):
            raise ShapeError(f"view {names[i]}: camera is {cam.width} x {cam.height}, the image {w} x {h}")
        k = intrinsics[i] if intrinsics is not None else None
        for K in (k, None if cam is None else cam.K):
            if K is not None and (np.shape(K) != (3, 3) or abs(float(np.asarray(K)[0, 1])) > 1e-12):
                raise InputError(f"view {names[i]}: intrinsics must be a 3 x 3 K without skew")


def write_inputs(
    workdir: Path,
    images: Sequence[np.ndarray],
    masks: Sequence[np.ndarray | None] | None,
    options: SfmOptions,
    *,
    reuse: Path | None = None,
) -> tuple[Path, Path | None, list[str]]:
    """SIFT images (and COLMAP masks: 0 = no features) under ``workdir``; returns dirs and file names.
    ``reuse``: a folder of SIFT images an earlier run wrote from the same images, masks and image
    options (``sift_equalize``, ``sift_denoise``); its files are copied instead of computed again."""
    image_dir, mask_dir = workdir / "images", workdir / "masks"
    for d in (image_dir, mask_dir, workdir / "sparse"):
        shutil.rmtree(d, ignore_errors=True)
    image_dir.mkdir(parents=True)
    files = [f"{i:05d}.png" for i in range(len(images))]
    has_masks = masks is not None and any(m is not None for m in masks)
    if has_masks:
        mask_dir.mkdir()
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * options.mask_erosion_px + 1,) * 2)

    def write(i: int) -> None:
        name, mask = files[i], None if masks is None else masks[i]
        if reuse is not None and (reuse / name).is_file():
            shutil.copyfile(reuse / name, image_dir / name)
        else:
            sift = sift_image(images[i], mask, equalize=options.sift_equalize, denoise=options.sift_denoise)
            cv2.imwrite(str(image_dir / name), sift, SCRATCH_PNG)
        if has_masks:
            m = np.full(images[i].shape[:2], 255, np.uint8) if mask is None else mask.astype(np.uint8) * 255
            cv2.imwrite(str(mask_dir / f"{name}.png"), cv2.erode(m, kernel), SCRATCH_PNG)

    # views on several threads (OpenCV and most of NumPy release the GIL): the exposure, encoding and
    # PNG writing of 36 views of 612x512 take half the time; non-local means is parallel by itself
    with ThreadPoolExecutor(max_workers=min(usable_threads(), max(len(files), 1))) as pool:
        list(pool.map(write, range(len(files))))
    return image_dir, (mask_dir if has_masks else None), files


def view_intrinsics(
    i: int, cameras: Sequence[Camera | None] | None, intrinsics: Sequence[np.ndarray | None] | None
) -> np.ndarray | None:
    """View ``i``'s K: from ``intrinsics`` when given, else its camera's, else None (to estimate)."""
    if intrinsics is not None and intrinsics[i] is not None:
        return np.asarray(intrinsics[i], dtype=np.float64)
    cam = cameras[i] if cameras is not None else None
    return None if cam is None else cam.K
