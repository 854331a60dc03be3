"""Frame files (pmvir.io.frames): every format round-trips; each bad file raises FrameError naming it."""

from __future__ import annotations

import numpy as np
import pytest
import tifffile

from pmvir.errors import FrameError
from pmvir.io.frames import (
    RawFormat,
    container_bits,
    pack_mono12p,
    read_frame,
    read_frame_size,
    unpack_mono12p,
    write_frame,
)


def _samples(h: int, w: int, bit_depth: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    a = rng.integers(0, 1 << bit_depth, size=(h, w)).astype(np.uint16)
    a.flat[0] = 0
    a.flat[-1] = (1 << bit_depth) - 1  # both ends of the range
    return a


# ----------------------------------------------------------------------------- round trips


@pytest.mark.parametrize("suffix", [".png", ".tif", ".tiff"])
@pytest.mark.parametrize("bit_depth", [8, 12, 16])
def test_png_tiff_round_trip(tmp_path, suffix, bit_depth):
    a = _samples(12, 20, bit_depth)
    p = tmp_path / f"f{suffix}"
    write_frame(p, a, bit_depth=bit_depth)
    b = read_frame(p)
    assert b.dtype == (np.uint8 if bit_depth <= 8 else np.uint16)
    np.testing.assert_array_equal(b, a)
    assert read_frame_size(p) == (12, 20)
    assert container_bits(p, b) == (8 if bit_depth <= 8 else 16)


@pytest.mark.parametrize("bit_depth", [8, 12, 16])
def test_dng_round_trip_through_rawpy(tmp_path, bit_depth):
    a = _samples(24, 28, bit_depth, seed=1)
    p = tmp_path / "f.dng"
    write_frame(p, a, bit_depth=bit_depth)
    b = read_frame(p)  # rawpy raw_image
    assert b.dtype == np.uint16
    np.testing.assert_array_equal(b, a)
    assert read_frame_size(p) == (24, 28)


def test_dng_written_is_a_cfa_dng(tmp_path):
    p = tmp_path / "f.dng"
    write_frame(p, _samples(24, 24, 12), bit_depth=12)
    with tifffile.TiffFile(p) as tif:
        page = tif.pages.first
        assert page.photometric == 32803  # CFA
        assert page.compression == 1
        assert bytes(page.tags["DNGVersion"].value) == bytes([1, 4, 0, 0])
        assert page.tags["WhiteLevel"].value == 4095


def test_dng_smaller_than_libraw_minimum_is_refused(tmp_path):
    with pytest.raises(ValueError, match="22x22"):
        write_frame(tmp_path / "f.dng", _samples(8, 8, 12), bit_depth=12)


@pytest.mark.parametrize(
    "dtype,bit_depth", [("uint8", 8), ("uint16le", 12), ("uint16le", 16), ("uint16be", 12), ("uint16be", 16),
                        ("mono12p", 12), ("mono12p", 10)]
)
@pytest.mark.parametrize("suffix", [".raw", ".bin"])
def test_headerless_round_trip(tmp_path, dtype, bit_depth, suffix):
    a = _samples(6, 10, bit_depth, seed=2)
    p = tmp_path / f"f{suffix}"
    write_frame(p, a, bit_depth=bit_depth, raw_dtype=dtype)
    fmt = RawFormat(width=10, height=6, dtype=dtype)
    assert p.stat().st_size == fmt.nbytes
    np.testing.assert_array_equal(read_frame(p, raw=fmt), a)
    assert read_frame_size(p, raw=fmt) == (6, 10)
    assert container_bits(p, a, raw=fmt) == {"uint8": 8, "mono12p": 12}.get(dtype, 16)


def test_uint16be_byte_order(tmp_path):
    p = tmp_path / "f.raw"
    write_frame(p, np.array([[0x0102, 0x0A0B]], dtype=np.uint16), bit_depth=16, raw_dtype="uint16be")
    assert p.read_bytes() == b"\x01\x02\x0a\x0b"
    write_frame(p, np.array([[0x0102, 0x0A0B]], dtype=np.uint16), bit_depth=16, raw_dtype="uint16le")
    assert p.read_bytes() == b"\x02\x01\x0b\x0a"


def test_mono12p_bit_order_is_genicam_pfnc():
    # p0 = 0xABC, p1 = 0x123: byte0 = p0 bits 0-7, byte1 = p0 bits 8-11 | p1 bits 0-3 << 4, byte2 = p1 bits 4-11
    assert pack_mono12p(np.array([0xABC, 0x123])) == bytes([0xBC, 0x3A, 0x12])
    np.testing.assert_array_equal(unpack_mono12p(bytes([0xBC, 0x3A, 0x12]), 2), [0xABC, 0x123])


@pytest.mark.parametrize("n", [1, 2, 3, 4, 5, 7, 8])
def test_mono12p_odd_and_even_counts(n):
    v = (np.arange(n, dtype=np.uint16) * 1237 + 4095) % 4096
    data = pack_mono12p(v)
    assert len(data) == (3 * n + 1) // 2
    np.testing.assert_array_equal(unpack_mono12p(data, n), v)
    if n % 2:
        assert data[-1] >> 4 == 0  # half-used last byte


def test_mono12p_odd_frame_round_trip(tmp_path):
    a = _samples(3, 5, 12, seed=3)  # 15 samples: the stream runs across rows, ends mid-byte
    p = tmp_path / "odd.raw"
    write_frame(p, a, bit_depth=12, raw_dtype="mono12p")
    assert p.stat().st_size == 23
    np.testing.assert_array_equal(read_frame(p, raw=RawFormat(5, 3, "mono12p")), a)


def test_write_rejects_values_above_bit_depth(tmp_path):
    with pytest.raises(ValueError, match=r"0\.\.4095"):
        write_frame(tmp_path / "f.png", np.full((4, 4), 4096, np.uint16), bit_depth=12)


def test_write_rejects_container_too_small(tmp_path):
    with pytest.raises(ValueError, match="mono12p holds at most 12 bits"):
        write_frame(tmp_path / "f.raw", np.zeros((4, 4), np.uint16), bit_depth=16, raw_dtype="mono12p")


def test_write_is_atomic_no_leftovers(tmp_path):
    write_frame(tmp_path / "f.png", _samples(4, 4, 8), bit_depth=8)
    assert [p.name for p in tmp_path.iterdir()] == ["f.png"]


# ----------------------------------------------------------------------------- bad files


def test_truncated_png(tmp_path):
    p = tmp_path / "trunc.png"
    write_frame(p, _samples(16, 16, 12), bit_depth=12)
    p.write_bytes(p.read_bytes()[:-30])
    with pytest.raises(FrameError, match=r"trunc\.png.*truncated PNG"):
        read_frame(p)
    with pytest.raises(FrameError, match="truncated PNG"):
        read_frame_size(p)


def test_corrupt_png_crc(tmp_path):
    p = tmp_path / "bad.png"
    write_frame(p, _samples(16, 16, 12), bit_depth=12)
    data = bytearray(p.read_bytes())
    data[40] ^= 0xFF  # inside the first IDAT
    p.write_bytes(bytes(data))
    with pytest.raises(FrameError, match=r"bad\.png.*CRC"):
        read_frame(p)


def test_not_an_image(tmp_path):
    p = tmp_path / "text.png"
    p.write_text("hello, not an image")
    with pytest.raises(FrameError, match=r"text\.png.*not a PNG"):
        read_frame(p)


def test_not_a_tiff(tmp_path):
    p = tmp_path / "text.tif"
    p.write_text("hello, not an image")
    with pytest.raises(FrameError, match=r"text\.tif.*not a readable TIFF"):
        read_frame(p)


def test_rgb_png_is_multi_channel(tmp_path):
    import cv2

    p = tmp_path / "rgb.png"
    cv2.imwrite(str(p), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(FrameError, match=r"rgb\.png.*single-channel.*an RGB image.*raw mosaic"):
        read_frame(p)


def test_rgb_tiff_is_multi_channel(tmp_path):
    p = tmp_path / "rgb.tif"
    tifffile.imwrite(p, np.zeros((8, 8, 3), np.uint16), photometric="rgb")
    with pytest.raises(FrameError, match=r"rgb\.tif.*single-channel.*raw mosaic"):
        read_frame(p)


def test_float_tiff_refused(tmp_path):
    p = tmp_path / "float.tif"
    tifffile.imwrite(p, np.zeros((8, 8), np.float32))
    with pytest.raises(FrameError, match=r"float\.tif.*8- or 16-bit unsigned"):
        read_frame(p)


def test_truncated_tiff(tmp_path):
    p = tmp_path / "trunc.tif"
    write_frame(p, _samples(32, 32, 16), bit_depth=16)
    p.write_bytes(p.read_bytes()[:600])
    with pytest.raises(FrameError, match=r"trunc\.tif"):
        read_frame(p)


def test_rgb_dng_is_not_a_mosaic(tmp_path):
    p = tmp_path / "rgb.dng"
    tifffile.imwrite(
        p, np.zeros((24, 24, 3), np.uint16), photometric=34892, subfiletype=0,  # LinearRaw RGB
        extratags=[(50706, 1, 4, (1, 4, 0, 0), True), (50708, 2, 0, "x", True)],
    )
    with pytest.raises(FrameError, match=r"rgb\.dng.*single-plane CFA mosaic"):
        read_frame(p)


def test_rgb_tiff_named_dng(tmp_path):
    p = tmp_path / "fake.dng"
    tifffile.imwrite(p, np.zeros((24, 24, 3), np.uint16), photometric="rgb")
    with pytest.raises(FrameError, match=r"fake\.dng.*not a DNG"):
        read_frame(p)


def test_raw_shorter_than_declared(tmp_path):
    p = tmp_path / "short.raw"
    p.write_bytes(b"\0" * (2 * 8 * 8 - 2))
    with pytest.raises(FrameError, match=r"short\.raw.*shorter than declared.*126 bytes, expected 128"):
        read_frame(p, raw=RawFormat(8, 8, "uint16le"))


def test_raw_longer_than_declared(tmp_path):
    p = tmp_path / "long.bin"
    p.write_bytes(b"\0" * (8 * 8 + 1))
    with pytest.raises(FrameError, match=r"long\.bin.*longer than declared"):
        read_frame_size(p, raw=RawFormat(8, 8, "uint8"))


def test_raw_without_layout(tmp_path):
    p = tmp_path / "f.raw"
    p.write_bytes(b"\0" * 64)
    with pytest.raises(FrameError, match=r"f\.raw.*no \"raw\""):
        read_frame(p)


def test_unknown_raw_dtype():
    with pytest.raises(ValueError, match="raw dtype must be one of"):
        RawFormat(8, 8, "uint32")


def test_unknown_suffix(tmp_path):
    p = tmp_path / "f.jpg"
    p.write_bytes(b"\xff\xd8")
    with pytest.raises(FrameError, match=r"f\.jpg.*unknown frame file type"):
        read_frame(p)


def test_missing_file_uses_label(tmp_path):
    with pytest.raises(FrameError, match=r"^frames/000\.png: frame file not found"):
        read_frame(tmp_path / "nope.png", label="frames/000.png")


def test_mono12p_round_trip_property():
    from hypothesis import given, settings
    from hypothesis import strategies as st

    @settings(max_examples=60, deadline=None)
    @given(st.lists(st.integers(0, 4095), min_size=1, max_size=41))
    def check(values):
        v = np.array(values, dtype=np.uint16)
        np.testing.assert_array_equal(unpack_mono12p(pack_mono12p(v), v.size), v)

    check()
