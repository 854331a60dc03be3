"""Zipped captures Python's zipfile cannot read safely are refused by name (pmvir.io.capture_zip)."""

from __future__ import annotations

import io
import struct
import zipfile
from pathlib import Path

import pytest

from pmvir.errors import CaptureError
from pmvir.io.capture_zip import extract_capture_zip


def _zip(path: Path, members: dict[str, bytes]) -> Path:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    path.write_bytes(buf.getvalue())
    return path


def _patch(path: Path, offsets: dict[bytes, int], value: int, *, mask: bool = False) -> None:
    """Set (or OR into, with ``mask``) a 2-byte field of every local header and central directory entry."""
    data = bytearray(path.read_bytes())
    for sig, at in offsets.items():
        pos = data.find(sig)
        while pos >= 0:
            (old,) = struct.unpack_from("<H", data, pos + at)
            struct.pack_into("<H", data, pos + at, old | value if mask else value)
            pos = data.find(sig, pos + 4)
    path.write_bytes(bytes(data))


@pytest.mark.parametrize(("method", "name"), [(9, "Deflate64"), (14, "LZMA"), (12, "bzip2"), (99, "unknown")])
def test_member_with_an_unsupported_compression_method_is_refused_by_name(
    tmp_path: Path, method: int, name: str
) -> None:
    z = _zip(tmp_path / "c.zip", {"capture.json": b"{}"})
    _patch(z, {b"PK\x03\x04": 8, b"PK\x01\x02": 10}, method)
    with pytest.raises(CaptureError, match=rf"'capture\.json' uses compression method {method} \({name}\)"):
        extract_capture_zip(z, tmp_path / "out")


def test_member_name_flagged_utf8_but_invalid_is_refused_with_its_bytes(tmp_path: Path) -> None:
    z = _zip(tmp_path / "c.zip", {"capture.json": b"{}", "frames/abc.png": b"x"})
    z.write_bytes(z.read_bytes().replace(b"frames/abc.png", b"frames/\xff\xfec.png"))
    _patch(z, {b"PK\x03\x04": 6, b"PK\x01\x02": 8}, 0x800, mask=True)
    with pytest.raises(CaptureError, match=r"flagged UTF-8 but is not valid UTF-8") as err:
        extract_capture_zip(z, tmp_path / "out")
    assert r"\xff\xfe" in str(err.value)


def test_many_small_compressible_members_are_refused_as_a_whole(tmp_path: Path) -> None:
    members = {"capture.json": b"{}", **{f"frames/{i:03d}.png": bytes(500_000) for i in range(20)}}
    z = _zip(tmp_path / "c.zip", members)  # 10 MB from ~10 KB; no member is over 1 MiB
    with pytest.raises(CaptureError, match=r"the zip as a whole expands \d+x"):
        extract_capture_zip(z, tmp_path / "out")
    extract_capture_zip(z, tmp_path / "ok", max_ratio=1e6)  # the same zip with a laxer limit
    assert len(list((tmp_path / "ok" / "frames").iterdir())) == 20
