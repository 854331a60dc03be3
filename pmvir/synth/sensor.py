"""The sensor step shared by every renderer: linear Stokes image to raw 12-bit mosaic.

1. Polarizer intensities ``I_theta = (s0 + s1 cos 2 theta + s2 sin 2 theta) / 2``
   for theta = 0, 45, 90, 135 degrees (spec section 2, ccw sense), so the decoded
   ``I_int = (I0 + I45 + I90 + I135) / 4 = s0 / 2``.
2. :func:`pmvir.polarization.layout.mosaic` keeps each pixel's own angle and colour.
3. Gain: ``x = gain * I_theta`` is the signal as a fraction of full scale
   (``(sample - black) / (white - black)``, the decoded units).
4. Shot noise: ``Poisson(x * full_well) / full_well`` (``full_well`` electrons at
   full scale; 0 turns shot noise off).
5. Read noise: Gaussian, standard deviation ``read_noise`` in full-scale units.
6. Quantization: ``round(black + x * (white - black))`` clipped to [0, white]; a
   sample at ``white`` is saturated.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmvir.errors import ConfigError, ShapeError
from pmvir.polarization.layout import ANGLES_DEG, IMX250MYR, MosaicLayout, mosaic


@dataclass(frozen=True)
class SensorModel:
    """The simulated camera's read-out.

    Attributes:
        layout: mosaic layout (IMX250MYR: colour polarization).
        bit_depth: bits per sample.
        black_level: sample value of zero light.
        white_level: saturation value (2**bit_depth - 1 for a 12-bit read-out: 4095).
        full_well: electrons at full scale (shot noise); 0 disables shot noise.
        read_noise: read-noise standard deviation as a fraction of full scale; 0 disables it.
    """

    layout: MosaicLayout = IMX250MYR
    bit_depth: int = 12
    black_level: int = 64
    white_level: int = 4095
    full_well: float = 10500.0
    read_noise: float = 0.001

    def __post_init__(self) -> None:
        if not 0 <= self.black_level < self.white_level <= (1 << self.bit_depth) - 1:
            raise ConfigError(
                f"need 0 <= black_level < white_level <= {(1 << self.bit_depth) - 1}, "
                f"got {self.black_level}, {self.white_level}"
            )
        if self.full_well < 0 or self.read_noise < 0:
            raise ConfigError(
                f"full_well and read_noise must be >= 0, got {self.full_well}, {self.read_noise}"
            )


def stokes_to_intensities(stokes: np.ndarray) -> np.ndarray:
    """Intensities behind ideal polarizers at 0, 45, 90, 135 degrees.

    Args:
        stokes: (H, W, C, 3) linear Stokes (s0, s1, s2) per colour, float.

    Returns:
        (H, W, 4, C) float32 intensities in :data:`ANGLES_DEG` order, clamped at >= 0.
    """
    if stokes.ndim != 4 or stokes.shape[-1] != 3:
        raise ShapeError(f"expected (H, W, C, 3) Stokes, got {stokes.shape}")
    # cos 2theta, sin 2theta are (1, 0), (0, 1), (-1, 0), (0, -1) for 0, 45, 90, 135 degrees: exact.
    assert ANGLES_DEG == (0, 45, 90, 135)
    s = np.asarray(stokes, dtype=np.float32)
    s0, s1, s2 = s[..., 0], s[..., 1], s[..., 2]
    out = np.stack([s0 + s1, s0 + s2, s0 - s1, s0 - s2], axis=2) * np.float32(0.5)
    return np.maximum(out, np.float32(0.0))


def noiseless_signal(stokes: np.ndarray, gain: float, layout: MosaicLayout = IMX250MYR) -> np.ndarray:
    """The mosaic signal in full-scale units before noise and quantization, (H, W) float32."""
    return mosaic(stokes_to_intensities(stokes), layout) * np.float32(gain)


def capture_mosaic(
    stokes: np.ndarray, *, gain: float, sensor: SensorModel, rng: np.random.Generator
) -> np.ndarray:
    """Simulate the raw read-out of a linear Stokes image.

    Args:
        stokes: (H, W, C, 3) float Stokes image, renderer radiance units
            (C = 3 for a colour layout, 1 for monochrome).
        gain: full-scale units per radiance unit (exposure and amplifier gain together).
        sensor: the read-out model.
        rng: random generator for the noise.

    Returns:
        (H, W) uint16 samples in [0, sensor.white_level].
    """
    if gain <= 0:
        raise ConfigError(f"gain must be > 0, got {gain}")
    x = noiseless_signal(stokes, gain, sensor.layout).astype(np.float64)
    if sensor.full_well > 0:
        electrons = np.minimum(x, 4.0) * sensor.full_well  # far above white it saturates anyway
        x = rng.poisson(electrons).astype(np.float64) / sensor.full_well
    if sensor.read_noise > 0:
        x = x + rng.normal(0.0, sensor.read_noise, size=x.shape)
    span = sensor.white_level - sensor.black_level
    samples = np.rint(sensor.black_level + x * span)
    return np.clip(samples, 0, sensor.white_level).astype(np.uint16)
