"""Per-view images of a result, for people: decoded previews and residuals of the refined model.

Both are written at a modest resolution: a frame is reduced by the smallest
integer factor ``s`` that brings its width to at most ``max_size`` pixels
(block means of s x s pixels; the camera is scaled to match, so pixel centres
stay exact).

* ``previews/<stem>_int.png``, ``_dop.png``, ``_aop.png``: I_int, DoP and AoP as
  :mod:`pmvir.polarization.preview` draws them.
* ``residuals/<stem>_intensity.png``: observed minus rendered intensity (the
  colour mean of the intensity the refinement fitted, I_min or I_int, minus
  ``K * S(N) * rgb_scale`` of the refined mesh rendered per pixel with
  :func:`pmvir.refine.forward.render_decoded`) on a diverging scale: blue
  negative (the model too bright), white zero, red positive, saturated at the
  ``scale`` stated in ``residuals/summary.json`` (one scale for every view);
  black where the model or the observation is missing.
* ``residuals/<stem>_epol.png``: E_pol per pixel, ``rho * cost(eta)`` between
  the rendered normal's azimuth and the observed AoP (the refinement's term,
  :func:`pmvir.refine.energy.polarimetric_cost`), from 0 (black) to
  ``epol_scale`` (white, the 99th percentile over every view) on the inferno
  colour map; pixels whose DoP is below ``pol.dop_min`` count 0.
* ``residuals/summary.json``: per view the RMS and mean residual and the mean
  E_pol over the pixels compared.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from pmvir.camera import Camera
from pmvir.config import RefineOptions
from pmvir.polarization.preview import aop_preview, dop_preview, exposure_scale, intensity_preview, write_png
from pmvir.polarization.stokes import PolarizationImages

#: Views rendered with one ray-casting scene (bounds the memory of the rendered frames).
_RENDER_BATCH = 8


def reduction_factor(width: int, max_size: int) -> int:
    """Smallest integer s with ceil(width / s) <= max_size.

    >>> reduction_factor(2448, 512), reduction_factor(408, 512)
    (5, 1)
    """
    return max(1, math.ceil(width / max_size))


def reduce_mean(image: np.ndarray, s: int) -> np.ndarray:
    """Means of s x s blocks, (H // s, W // s, ...) float32 (the rows and columns left over are dropped)."""
    h, w = image.shape[0] // s * s, image.shape[1] // s * s
    x = image[:h, :w].astype(np.float32)
    return x.reshape(h // s, s, w // s, s, *x.shape[2:]).mean(axis=(1, 3))


def reduced_camera(cam: Camera, s: int) -> Camera:
    """The camera whose pixels are the s x s blocks of ``cam``'s (pixel centres map exactly)."""
    k = cam.K.copy()
    k[:2] /= s
    return Camera(K=k, R=cam.R, t=cam.t, width=cam.width // s, height=cam.height // s)


def reduce_polarization(images: PolarizationImages, s: int) -> dict[str, np.ndarray]:
    """Block means of a decoded frame: intensities averaged, AoP/DoP from the averaged normalized Stokes
    components, a block valid only when all its pixels are."""
    if s == 1:
        return {
            "i_int": images.i_int,
            "i_min": images.i_min,
            "aop": images.aop,
            "dop": images.dop,
            "valid": images.valid,
        }
    s1 = reduce_mean(images.dop * np.cos(2.0 * images.aop), s)
    s2 = reduce_mean(images.dop * np.sin(2.0 * images.aop), s)
    return {
        "i_int": reduce_mean(images.i_int, s),
        "i_min": reduce_mean(images.i_min, s),
        "aop": np.mod(0.5 * np.arctan2(s2, s1), np.pi).astype(np.float32),
        "dop": np.clip(np.hypot(s1, s2), 0.0, 1.0).astype(np.float32),
        "valid": reduce_mean(images.valid.astype(np.float32), s) >= 1.0,
    }


def write_view_previews(folder: Path, stem: str, images: PolarizationImages, *, max_size: int) -> list[Path]:
    """``<stem>_int.png``, ``<stem>_dop.png`` and ``<stem>_aop.png`` at most ``max_size`` pixels wide."""
    r = reduce_polarization(images, reduction_factor(images.i_int.shape[1], max_size))
    scale = exposure_scale(r["i_int"], r["valid"])
    return [
        write_png(folder / f"{stem}_int.png", intensity_preview(r["i_int"], scale=scale)),
        write_png(folder / f"{stem}_dop.png", dop_preview(r["dop"], r["valid"])),
        write_png(folder / f"{stem}_aop.png", aop_preview(r["aop"], r["dop"], r["valid"])),
    ]


def diverging(values: np.ndarray, scale: float, mask: np.ndarray) -> np.ndarray:
    """Blue (-scale) - white (0) - red (+scale) colours of (H, W) values; black outside ``mask``.

    Returns:
        (H, W, 3) uint8 RGB.
    """
    t = np.clip(values / max(scale, 1e-12), -1.0, 1.0)
    pos, neg = np.clip(t, 0.0, 1.0), np.clip(-t, 0.0, 1.0)
    rgb = np.stack([1.0 - neg, 1.0 - np.maximum(pos, neg), 1.0 - pos], axis=-1)
    out = np.rint(rgb * 255.0).astype(np.uint8)
    out[~mask] = 0
    return out


def sequential(values: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Inferno colours of (H, W) values in [0, 1]; black outside ``mask``. Returns (H, W, 3) uint8 RGB."""
    grey = np.rint(np.clip(values, 0.0, 1.0) * 255.0).astype(np.uint8)
    out = cv2.cvtColor(cv2.applyColorMap(grey, cv2.COLORMAP_INFERNO), cv2.COLOR_BGR2RGB)
    out[~mask] = 0
    return out


def pixel_epol(model_aop: np.ndarray, aop: np.ndarray, dop: np.ndarray, options: RefineOptions) -> np.ndarray:
    """E_pol per pixel: ``rho * cost(eta)`` (rho = 1 without ``pol.dop_weight``); 0 where DoP < ``pol.dop_min``.

    Args:
        model_aop: (H, W) the rendered normal's azimuth modulo pi (E_pol's eta only depends on it modulo
            pi/2), radians.
        aop, dop: (H, W) observed AoP (radians in [0, pi)) and DoP.
        options: the refinement's options (``pol.k``, ``pol.dop_weight``, ``pol.dop_min``).

    Returns:
        (H, W) float32 in [0, 1].
    """
    import torch

    from pmvir.refine.energy import azimuth_distance, polarimetric_cost

    eta = azimuth_distance(
        torch.from_numpy(model_aop.astype(np.float64)), torch.from_numpy(aop.astype(np.float64))
    )
    cost = polarimetric_cost(eta, k=options.pol.k).numpy()
    weight = dop if options.pol.dop_weight else np.ones_like(dop)
    return np.where(dop >= options.pol.dop_min, weight * cost, 0.0).astype(np.float32)


def write_residuals(
    folder: Path,
    views: Sequence[tuple[str, PolarizationImages]],
    cameras: Sequence[Camera],
    mesh_vertices: np.ndarray,
    mesh_faces: np.ndarray,
    albedo: np.ndarray,
    sh: np.ndarray,
    rgb_scale: np.ndarray,
    *,
    options: RefineOptions,
    max_size: int,
) -> dict[str, Any]:
    """Write the residual images of every view and ``summary.json``; returns the summary.

    Args:
        folder: the (temporary) ``residuals/`` folder.
        views: per registered view its stem and decoded images.
        cameras: the views' cameras (same order).
        mesh_vertices, mesh_faces, albedo: the refined mesh (N, 3), (F, 3), (N, 3) linear.
        sh, rgb_scale: (V, T) shading coefficients (T = 9, 16 or 25, as refine.lighting.sh_order) and (V, 3) scales of the views.
        options: the refinement's options (which intensity it fitted, E_pol's parameters).
        max_size: widest image written, pixels.
    """
    import json

    from pmvir.refine.forward import render_decoded

    key = "i_min" if options.pho.intensity == "min" else "i_int"
    factors = [reduction_factor(cam.width, max_size) for cam in cameras]
    small = [reduced_camera(cam, s) for cam, s in zip(cameras, factors, strict=True)]
    per_view = []
    for start in range(0, len(small), _RENDER_BATCH):  # one ray-casting scene per batch of views
        batch = range(start, min(start + _RENDER_BATCH, len(small)))
        models = render_decoded(
            mesh_vertices,
            mesh_faces,
            albedo,
            [small[c] for c in batch],
            sh[batch.start : batch.stop],
            rgb_scale[batch.start : batch.stop],
            dop_scale=0.0,
        )
        for c, model in zip(batch, models, strict=True):
            stem, images = views[c]
            obs = reduce_polarization(images, factors[c])
            h, w = model["mask"].shape
            compared = model["mask"] & obs["valid"][:h, :w]
            residual = (obs[key][:h, :w] - model["i_min"]).mean(axis=2)
            epol = pixel_epol(model["aop"], obs["aop"][:h, :w], obs["dop"][:h, :w], options)
            per_view.append((stem, residual, epol, compared))
    magnitudes = np.concatenate([np.abs(r[m]) for _, r, _, m in per_view]) if per_view else np.zeros(0)
    scale = float(np.percentile(magnitudes, 99.0)) if magnitudes.size else 1.0
    scale = scale if scale > 1e-9 else 1.0
    epols = np.concatenate([e[m] for _, _, e, m in per_view]) if per_view else np.zeros(0)
    epol_scale = float(np.percentile(epols, 99.0)) if epols.size else 1.0
    epol_scale = epol_scale if epol_scale > 1e-9 else 1.0
    rows = []
    for stem, residual, epol, compared in per_view:
        write_png(folder / f"{stem}_intensity.png", diverging(residual, scale, compared))
        write_png(folder / f"{stem}_epol.png", sequential(epol / epol_scale, compared))
        n = int(compared.sum())
        rows.append(
            {
                "view": stem,
                "pixels": n,
                "rms": float(np.sqrt(np.mean(residual[compared] ** 2))) if n else None,
                "mean": float(residual[compared].mean()) if n else None,
                "mean_epol": float(epol[compared].mean()) if n else None,
            }
        )
    summary = {
        "format": "pmvir-residuals/1",
        "intensity": key,
        "scale": scale,
        "epol_scale": epol_scale,
        "note": "intensity residual = observed - rendered colour mean, shown from -scale (blue) to +scale "
        "(red); E_pol per pixel from 0 (black) to epol_scale (white, inferno colour map)",
        "views": rows,
    }
    (folder / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary
