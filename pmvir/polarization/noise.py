"""How noisy each pixel's polarization is, measured from the raw mosaic itself.

Ideal polarizers at 0, 45, 90 and 135 degrees close: ``I0 + I90 = I45 + I135 = s0``
for any Stokes vector. In each 2x2 polarizer block of the mosaic (one colour, four
angles) the closure residual ``r = (I0 + I90) - (I45 + I135)`` is therefore not
signal but noise: shot and read noise, a path tracer's Monte Carlo noise, and the
scene changing inside the block (albedo edges, fine relief), which is what the
demosaicing turns into false polarization. With independent noise of standard
deviation ``sigma`` on each polarizer sample, ``r`` has standard deviation ``2 sigma``,
as have ``s1 = I0 - I90`` and ``s2 = I45 - I135`` up to a factor sqrt(2); relative to
``s0`` it is the noise of the normalized Stokes vector (DoP cos 2 phi, DoP sin 2 phi)
up to a constant. The AoP's noise is that divided by the DoP, so ``DoP / noise`` is
the AoP's signal-to-noise ratio.

:func:`closure_noise` is the local root mean square of ``r / s0`` over blocks whose
four samples are all valid, at full resolution. The refinement weights E_pol's pairs by
it (``refine.pol.aop_noise``).

Noise biases the DoP upward: ``E[s1^2 + s2^2]`` is the signal's power plus the noise's.
:func:`unbiased_dop` subtracts the noise's share, ``gain * closure_noise^2``, from
``DoP^2`` before the square root (clamped at 0), with ``gain`` the demosaicing method's
ratio ``E[DoP^2] / E[closure_noise^2]`` on an unpolarized flat field
(:data:`DOP_NOISE_GAIN`: the interpolation's averaging shrinks the noise of s1 and s2 by
a factor of its own, the guided filter's most).
"""

from __future__ import annotations

import cv2
import numpy as np

from pmvir.errors import ConfigError, DTypeError, ShapeError
from pmvir.polarization.layout import MosaicLayout

#: ``E[DoP^2] / E[closure_noise^2]`` of an unpolarized, uniformly lit field under shot and read
#: noise, per (demosaicing method, colour channels of the layout); independent of the level and
#: the noise's size within 10 % (tests/polarization/test_noise.py measures it).
DOP_NOISE_GAIN: dict[tuple[str, int], float] = {
    ("bilinear", 3): 0.154,
    ("edge-aware", 3): 0.165,
    ("guided", 3): 0.017,
    ("eari", 3): 0.133,
    ("eari-guided", 3): 0.017,
    ("bilinear", 1): 0.567,
    ("edge-aware", 1): 0.567,
    ("guided", 1): 0.0175,
    ("eari", 1): 0.341,
    ("eari-guided", 1): 0.0175,
}

#: Sign of each angle (ANGLES_DEG order: 0, 45, 90, 135) in the closure residual.
_CLOSURE_SIGN = np.array([1.0, -1.0, 1.0, -1.0], dtype=np.float32)


def closure_noise(
    mosaic: np.ndarray,
    layout: MosaicLayout,
    *,
    valid: np.ndarray | None = None,
    sigma_px: float = 3.0,
) -> np.ndarray:
    """The local RMS of the polarizer closure residual relative to s0, per pixel.

    Args:
        mosaic: (H, W) float32 normalized raw samples (as :func:`pmvir.decode.decode_frame`
            takes them).
        layout: the sensor layout (which angle sits where in the 2x2 block).
        valid: optional (H, W) bool; a block counts only where its four samples are valid
            (inside the mask, not saturated, above the noise floor).
        sigma_px: standard deviation of the Gaussian average, in pixels.

    Returns:
        (H, W) float32, ``sqrt(mean of (r / s0)^2)`` over nearby valid blocks (a normalized
        Gaussian average); NaN where no valid block is near (the caller decides what an
        unmeasured pixel means).

    Example:
        A uniform field closes exactly; noise on one sample shows up around it only:

        >>> from pmvir.polarization.layout import IMX250MYR, mosaic
        >>> field = np.broadcast_to(np.array([1.0, 0.5, 0.0, 0.5], np.float32)[:, None], (16, 16, 4, 3))
        >>> m = mosaic(np.ascontiguousarray(field), IMX250MYR)
        >>> float(closure_noise(m, IMX250MYR).max())
        0.0
        >>> m[8, 8] += 0.1
        >>> noise = closure_noise(m, IMX250MYR, sigma_px=2.0)
        >>> bool(noise[8, 8] > 0.01 > noise[0, 0])
        True
    """
    if mosaic.ndim != 2:
        raise ShapeError(f"expected an (H, W) mosaic, got shape {mosaic.shape}")
    if mosaic.dtype != np.float32:
        raise DTypeError(f"expected a float32 mosaic, got {mosaic.dtype}")
    if not sigma_px > 0:
        raise ConfigError(f"sigma_px must be positive, got {sigma_px}")
    h, w = mosaic.shape
    layout.check_size(h, w)
    if valid is not None and valid.shape != mosaic.shape:
        raise ShapeError(f"valid has shape {valid.shape}, the mosaic {mosaic.shape}")
    sign = _CLOSURE_SIGN[layout.angle_index_block()]
    corners = [(dy, dx) for dy in range(2) for dx in range(2)]
    residual = np.zeros((h // 2, w // 2), np.float32)
    s0 = np.zeros((h // 2, w // 2), np.float32)
    for dy, dx in corners:
        residual += sign[dy, dx] * mosaic[dy::2, dx::2]
        s0 += 0.5 * mosaic[dy::2, dx::2]
    ok: np.ndarray = s0 > 0.0
    if valid is not None:
        for dy, dx in corners:
            ok &= valid[dy::2, dx::2]
    ratio = np.where(ok, residual / np.where(ok, s0, 1.0), 0.0).astype(np.float32)
    weight = ok.astype(np.float32)
    sigma_blocks = 0.5 * sigma_px

    def blur(a: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(a, (0, 0), sigma_blocks, borderType=cv2.BORDER_REPLICATE)

    den = blur(weight)
    mean_sq = blur(ratio * ratio) / np.maximum(den, 1e-12)
    # block centres sit at pixel (2j + 0.5, 2i + 0.5) in array coordinates: cv2's resize by 2
    # (pixel-centre aligned) puts them there
    full = cv2.resize(np.sqrt(mean_sq), (w, h), interpolation=cv2.INTER_LINEAR)
    near = cv2.resize(den, (w, h), interpolation=cv2.INTER_LINEAR) > 1e-3
    return np.where(near, full, np.nan).astype(np.float32)


def unbiased_dop(dop: np.ndarray, noise: np.ndarray, *, method: str, channels: int = 3) -> np.ndarray:
    """The DoP with the noise's expected share of ``s1^2 + s2^2`` taken out.

    Args:
        dop: (H, W) float32 DoP as decoded (``sqrt(s1^2 + s2^2) / s0`` of demosaiced values).
        noise: (H, W) float32 :func:`closure_noise` of the same frame; NaN (unmeasured) leaves
            the DoP as it is.
        method: the demosaicing method that made ``dop``.
        channels: colour channels of the sensor layout (3: colour, 1: monochrome).

    Returns:
        (H, W) float32 ``sqrt(max(dop^2 - gain * noise^2, 0))``, in [0, 1].

    Example:
        >>> dop = np.array([[0.05, 0.2]], np.float32)
        >>> unbiased_dop(dop, np.array([[1.0, 1.0]], np.float32), method="bilinear").astype(float).round(3).tolist()
        [[0.0, 0.0]]
        >>> unbiased_dop(dop, np.array([[0.1, np.nan]], np.float32), method="bilinear").astype(float).round(3).tolist()
        [[0.031, 0.2]]
    """
    if (method, channels) not in DOP_NOISE_GAIN:
        known = sorted({m for m, _ in DOP_NOISE_GAIN})
        raise ConfigError(f"unknown demosaicing method {method!r} for {channels} channel(s); expected one of {known}")
    if dop.shape != noise.shape:
        raise ShapeError(f"dop has shape {dop.shape}, the noise {noise.shape}")
    power = np.square(dop, dtype=np.float32) - np.float32(DOP_NOISE_GAIN[method, channels]) * np.nan_to_num(
        noise.astype(np.float32), nan=0.0
    ) ** 2
    return np.sqrt(np.maximum(power, np.float32(0.0))).astype(np.float32)
