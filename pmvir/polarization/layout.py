"""Mosaic layouts of polarization sensors, and mosaicing (the forward model).

The layout is a value, not a comment: a frozen dataclass naming the polarizer
angle of each pixel of the 2x2 polarizer block and, for colour sensors, the
Bayer pattern formed by the four 2x2 blocks of the 4x4 super-pixel
(shared/spec/capture-format.md, section 1).

Angles inside a ``MosaicLayout`` are always in the spec's counter-clockwise
sense (from image +x toward image -y). A capture that declares
``aop_reference: "cw"`` is converted once, in :func:`layout_from_sensor`, by
mapping every labelled angle a to (-a) mod 180, so every later stage works in
one sense.

Array conventions used across pmvir:

* intensities: shape (H, W, 4, C), float32; axis 2 is the polarizer angle in the
  order of :data:`ANGLES_DEG` (0, 45, 90, 135), axis 3 the colour (R, G, B) for
  colour sensors or a single channel for monochrome ones.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pmvir.errors import ConfigError, ShapeError

#: Polarizer angles of the four intensity channels, degrees, in channel order.
ANGLES_DEG: tuple[int, int, int, int] = (0, 45, 90, 135)

_BAYER_PATTERNS = ("RGGB", "BGGR", "GRBG", "GBRG")
_COLOUR_INDEX = {"R": 0, "G": 1, "B": 2}


@dataclass(frozen=True)
class MosaicLayout:
    """Where each polarizer angle and colour filter sits on the sensor.

    Attributes:
        polarizer_block: polarizer angle in degrees (ccw sense) of each pixel of
            the 2x2 block, row-major ((top-left, top-right), (bottom-left, bottom-right)).
        bayer: Bayer pattern of the four 2x2 blocks in the 4x4 super-pixel
            ("RGGB", ...), or None for a monochrome sensor.
    """

    polarizer_block: tuple[tuple[int, int], tuple[int, int]] = ((90, 45), (135, 0))
    bayer: str | None = "RGGB"

    def __post_init__(self) -> None:
        angles = sorted(a for row in self.polarizer_block for a in row)
        if angles != sorted(ANGLES_DEG):
            raise ConfigError(
                f"polarizer_block must hold each of 0, 45, 90, 135 once, got {self.polarizer_block}"
            )
        if self.bayer is not None and self.bayer not in _BAYER_PATTERNS:
            raise ConfigError(f"bayer must be one of {_BAYER_PATTERNS} or None, got {self.bayer!r}")

    @property
    def is_colour(self) -> bool:
        return self.bayer is not None

    @property
    def channels(self) -> int:
        """Number of colour channels: 3 for colour sensors, 1 for monochrome."""
        return 3 if self.is_colour else 1

    @property
    def period(self) -> int:
        """Size of the repeating super-pixel: 4 for colour, 2 for monochrome."""
        return 4 if self.is_colour else 2

    def angle_index_block(self) -> np.ndarray:
        """Index into :data:`ANGLES_DEG` of each pixel of the 2x2 polarizer block, (2, 2) int."""
        return np.array(
            [[ANGLES_DEG.index(a) for a in row] for row in self.polarizer_block], dtype=np.int64
        )

    def colour_index_block(self) -> np.ndarray:
        """Colour index (0 R, 1 G, 2 B) of each 2x2 block of the super-pixel, (2, 2) int."""
        if self.bayer is None:
            return np.zeros((2, 2), dtype=np.int64)
        b = self.bayer
        return np.array(
            [[_COLOUR_INDEX[b[0]], _COLOUR_INDEX[b[1]]], [_COLOUR_INDEX[b[2]], _COLOUR_INDEX[b[3]]]],
            dtype=np.int64,
        )

    def angle_map(self, height: int, width: int) -> np.ndarray:
        """Angle index of every pixel of an (height, width) mosaic, int64."""
        return np.tile(self.angle_index_block(), (height // 2, width // 2))

    def colour_map(self, height: int, width: int) -> np.ndarray:
        """Colour index of every pixel of an (height, width) mosaic, int64."""
        blocks = self.colour_index_block().repeat(2, axis=0).repeat(2, axis=1)
        reps = (height // 4, width // 4) if self.is_colour else (height // 2, width // 2)
        if not self.is_colour:
            return np.zeros((height, width), dtype=np.int64)
        return np.tile(blocks, reps)

    def check_size(self, height: int, width: int) -> None:
        """Raise ConfigError unless (height, width) is a whole number of super-pixels."""
        p = self.period
        if height <= 0 or width <= 0 or height % p or width % p:
            raise ConfigError(
                f"mosaic size {width}x{height} is not a multiple of {p} in both directions"
            )


#: Sony IMX250MYR (colour polarization, e.g. Lucid PHX050S-Q).
IMX250MYR = MosaicLayout(polarizer_block=((90, 45), (135, 0)), bayer="RGGB")
#: Sony IMX250MZR (monochrome polarization).
IMX250MZR = MosaicLayout(polarizer_block=((90, 45), (135, 0)), bayer=None)

_KNOWN = {"IMX250MYR": IMX250MYR, "IMX250MZR": IMX250MZR}


def layout_from_sensor(
    name: str,
    *,
    polarizer_block: tuple[tuple[int, int], tuple[int, int]] | list[list[int]] | None = None,
    bayer: str | None = None,
    aop_reference: str = "ccw",
) -> MosaicLayout:
    """The layout of a named sensor, with the manifest's optional overrides applied.

    Args:
        name: "IMX250MYR" or "IMX250MZR".
        polarizer_block: 2x2 polarizer angles in degrees as labelled by the capture.
        bayer: Bayer pattern override (colour sensors only).
        aop_reference: "ccw" (spec default) or "cw"; "cw" labels are converted to ccw.

    Returns:
        The layout, angles in the ccw sense.
    """
    if name not in _KNOWN:
        raise ConfigError(f"unknown sensor layout {name!r}; expected one of {sorted(_KNOWN)}")
    base = _KNOWN[name]
    block = base.polarizer_block
    if polarizer_block is not None:
        rows = [[int(a) for a in row] for row in polarizer_block]
        if len(rows) != 2 or any(len(row) != 2 for row in rows):
            raise ConfigError(f"polarizer_block must be 2x2, got {polarizer_block}")
        block = ((rows[0][0], rows[0][1]), (rows[1][0], rows[1][1]))
    if aop_reference not in ("ccw", "cw"):
        raise ConfigError(f"aop_reference must be 'ccw' or 'cw', got {aop_reference!r}")
    if aop_reference == "cw":
        (a, b), (c, d) = block
        block = (((-a) % 180, (-b) % 180), ((-c) % 180, (-d) % 180))
    if bayer is not None and not base.is_colour:
        raise ConfigError(f"bayer override given for the monochrome layout {name}")
    return MosaicLayout(polarizer_block=block, bayer=bayer if bayer is not None else base.bayer)


def mosaic(intensities: np.ndarray, layout: MosaicLayout) -> np.ndarray:
    """Sample full-resolution polarizer/colour intensities the way the sensor does.

    Args:
        intensities: (H, W, 4, C) float, angle axis in ANGLES_DEG order, C = layout.channels.
        layout: the sensor layout.

    Returns:
        (H, W) mosaic with the same dtype as ``intensities``: each pixel keeps the
        value of its own polarizer angle and colour filter.
    """
    if intensities.ndim != 4 or intensities.shape[2] != 4 or intensities.shape[3] != layout.channels:
        raise ShapeError(
            f"expected (H, W, 4, {layout.channels}) intensities, got {intensities.shape}"
        )
    h, w = intensities.shape[:2]
    layout.check_size(h, w)
    a = layout.angle_map(h, w)
    c = layout.colour_map(h, w)
    rows, cols = np.indices((h, w))
    return intensities[rows, cols, a, c]
