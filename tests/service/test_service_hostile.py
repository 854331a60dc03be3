"""Hostile input gets a 4xx JSON error naming the file or field and the problem, never a 5xx.

One test per case found by a corpus of hostile requests: huge integers and deep
nesting in every JSON the API reads, a PNG whose header declares a huge image, zip member
names and compression methods Python's zipfile cannot handle, a chunked body with a bad
chunk size, a zip of many small highly compressible members, unbounded options and a path
no route matches. Then Hypothesis throws generated bodies at the JSON and multipart
endpoints and at capture.json: no answer may be a 5xx.
"""

from __future__ import annotations

import io
import json
import socket
import struct
import zipfile
import zlib
from pathlib import Path

import httpx
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.testing import ServiceStack

from svc_helpers import KEY, new_job, start_refused

HUGE_INT = "1" * 5000
DEEP = "[" * 50_000 + "]" * 50_000


def _error(r: httpx.Response, status: int) -> dict:
    assert r.status_code == status, r.text
    assert r.headers["content-type"].startswith("application/json")
    return r.json()


def _zip_bytes(members: dict[str, bytes], *, compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=compression) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _patch_method(data: bytes, method: int) -> bytes:
    """Set every member's compression method (local headers and central directory) to ``method``."""
    out = bytearray(data)
    for sig, offset in ((b"PK\x03\x04", 8), (b"PK\x01\x02", 10)):
        pos = out.find(sig)
        while pos >= 0:
            out[pos + offset : pos + offset + 2] = struct.pack("<H", method)
            pos = out.find(sig, pos + 4)
    return bytes(out)


def _post_zip(api: httpx.Client, data: bytes, options: str | None = None) -> httpx.Response:
    fields = {"options": options} if options is not None else None
    return api.post("/v1/jobs", files={"capture": ("c.zip", data, "application/zip")}, data=fields)


def _capture_zip(small_capture: Path) -> dict[str, bytes]:
    return {
        p.relative_to(small_capture).as_posix(): p.read_bytes()
        for p in small_capture.rglob("*")
        if p.is_file()
    }


def _png(width: int, height: int) -> bytes:
    """A 16-bit greyscale PNG whose IHDR declares width x height, with a tiny (wrong) IDAT."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))

    ihdr = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )


# ----------------------------------------------------------------------------- JSON


def test_json_body_with_a_5000_digit_integer_is_422(api: httpx.Client) -> None:
    body = '{"options": {"refine": {"solver": {"max_iterations": ' + HUGE_INT + "}}}}"
    err = _error(api.post("/v1/jobs", content=body, headers={"content-type": "application/json"}), 422)
    assert err["errors"][0]["loc"] == ["body"] and "5000 characters" in err["errors"][0]["msg"]


def test_json_body_nested_50000_deep_is_422(api: httpx.Client) -> None:
    err = _error(api.post("/v1/jobs", content=DEEP, headers={"content-type": "application/json"}), 422)
    assert "nested deeper" in err["errors"][0]["msg"]


def test_zip_options_field_with_a_5000_digit_integer_is_422(api: httpx.Client, small_capture: Path) -> None:
    data = _zip_bytes(_capture_zip(small_capture))
    err = _error(_post_zip(api, data, '{"refine": {"solver": {"max_iterations": ' + HUGE_INT + "}}}"), 422)
    assert err["errors"][0]["loc"] == ["body", "options"] and "5000 characters" in err["errors"][0]["msg"]


@pytest.mark.parametrize(
    ("content", "problem"),
    [
        ('{"format": "pmvir-capture/1", "x": ' + HUGE_INT + "}", "5000 characters"),
        ('{"format": "pmvir-capture/1", "x": ' + "[" * 30_000 + "]" * 30_000 + "}", "nested deeper"),
    ],
    ids=["huge-int", "deep"],
)
def test_capture_json_with_a_huge_number_or_deep_nesting_is_422(
    api: httpx.Client, content: str, problem: str
) -> None:
    job = new_job(api)
    err = _error(api.put(f"/v1/jobs/{job}/files/capture.json", content=content.encode()), 422)
    assert err["errors"][0]["file"] == "capture.json" and problem in err["errors"][0]["msg"]


def test_options_out_of_their_documented_range_are_422(api: httpx.Client) -> None:
    r = api.post("/v1/jobs", json={"options": {"refine": {"solver": {"max_iterations": 10**40}}}})
    assert _error(r, 422)["errors"][0]["loc"] == ["body", "options", "refine", "solver", "max_iterations"]
    r = api.post("/v1/jobs", json={"options": {"refine": {"stages": {"tau_pol": [1e300, 1.0, 1.0]}}}})
    err = _error(r, 422)
    assert err["errors"][0]["loc"] == ["body", "options", "refine", "stages", "tau_pol"]
    assert "1e9" in err["errors"][0]["msg"]


# ----------------------------------------------------------------------------- frames


def test_png_declaring_a_huge_image_is_refused_from_its_header_with_the_other_errors(
    api: httpx.Client, small_capture: Path
) -> None:
    job = new_job(api, small_capture)
    api.put(f"/v1/jobs/{job}/files/frames/001.png", content=_png(1_000_000, 1_000_000))
    api.put(f"/v1/jobs/{job}/files/frames/002.png", content=b"\x89PNG\r\n\x1a\n" + b"x" * 40)
    err = start_refused(api, job)
    by_file = {e["file"]: e["msg"] for e in err["errors"]}
    assert "1000000x1000000" in by_file["frames/001.png"] and "limit" in by_file["frames/001.png"]
    assert "frames/002.png" in by_file  # the other file's problem is reported too
    assert api.get(f"/v1/jobs/{job}").json()["status"] == "created"


# ----------------------------------------------------------------------------- zips


def test_zip_member_name_flagged_utf8_with_invalid_bytes_is_422(
    api: httpx.Client, small_capture: Path
) -> None:
    data = bytearray(_zip_bytes({**_capture_zip(small_capture), "frames/zz9.png": b"x"}))
    data = bytearray(data.replace(b"frames/zz9.png", b"frames/\xff\xfe\xfd.png"))
    for sig, at in ((b"PK\x03\x04", 6), (b"PK\x01\x02", 8)):  # flag every name as UTF-8 (bit 11)
        pos = data.find(sig)
        while pos >= 0:
            (flags,) = struct.unpack("<H", data[pos + at : pos + at + 2])
            data[pos + at : pos + at + 2] = struct.pack("<H", flags | 0x800)
            pos = data.find(sig, pos + 4)
    err = _error(_post_zip(api, bytes(data)), 422)
    assert "flagged UTF-8" in err["message"] and "\\xff\\xfe\\xfd" in err["message"]


@pytest.mark.parametrize(("method", "name"), [(9, "Deflate64"), (14, "LZMA"), (12, "bzip2")])
def test_zip_member_with_an_unsupported_compression_is_refused_by_name(
    api: httpx.Client, small_capture: Path, method: int, name: str
) -> None:
    data = _patch_method(_zip_bytes(_capture_zip(small_capture)), method)
    err = _error(_post_zip(api, data), 422)
    assert {e["file"] for e in err["errors"]} >= {"capture.json", "frames/000.png"}
    assert all(name in e["msg"] and "only stored and deflate" in e["msg"] for e in err["errors"])


def test_zip_of_many_small_compressible_members_is_refused_as_a_whole(
    api: httpx.Client, small_capture: Path
) -> None:
    members = _capture_zip(small_capture)
    members.update({f"frames/z{i:03d}.png": bytes(150_000) for i in range(40)})  # 6 MB from ~20 KB
    err = _error(_post_zip(api, _zip_bytes(members)), 413)
    assert "the zip as a whole expands" in err["message"]


# ----------------------------------------------------------------------------- transport, routes


def test_chunked_body_with_an_invalid_chunk_size_logs_no_traceback(stack: ServiceStack) -> None:
    host, port = stack.url.removeprefix("http://").split(":")
    request = (
        "POST /v1/jobs HTTP/1.1\r\nHost: x\r\n"
        f"Authorization: Bearer {KEY}\r\nContent-Type: application/json\r\n"
        "Transfer-Encoding: chunked\r\n\r\nzz\r\n{}\r\n0\r\n\r\n"
    )
    with socket.create_connection((host, int(port)), timeout=10) as s:
        s.sendall(request.encode())
        answer = s.recv(65536).decode("latin-1")
    assert answer.startswith("HTTP/1.1 4"), answer
    assert httpx.get(stack.url + "/healthz").status_code == 200
    assert "Traceback" not in (stack.log_dir / "api.log").read_text()


def test_a_path_no_route_matches_is_a_json_404_saying_why(api: httpx.Client) -> None:
    job = new_job(api)
    err = _error(api.put(f"/v1/jobs/{job}/files/frames/a%0Ab.png", content=b"x"), 404)
    assert "control character" in err["message"] and "a\\nb.png" in err["message"]
    err = _error(api.get("/nowhere"), 404)
    assert "/v1" in err["message"]


# ----------------------------------------------------------------------------- fuzz

_json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=12), children, max_size=4)
    ),
    max_leaves=20,
)
_bodies = st.one_of(
    st.binary(max_size=300),
    _json_values.map(lambda v: json.dumps(v).encode()),
    st.fixed_dictionaries(
        {
            "options": st.dictionaries(
                st.sampled_from(["decode", "geometry", "refine", "stop_after", "x"]), _json_values
            )
        }
    ).map(lambda v: json.dumps(v).encode()),
    st.integers(1, 3000).map(lambda n: ("[" * n + "]" * n).encode()),
    st.integers(1, 6000).map(lambda n: b'{"label": ' + b"9" * n + b"}"),
)
_FUZZ = settings(
    max_examples=40, derandomize=True, deadline=None, database=None, suppress_health_check=list(HealthCheck)
)


def test_generated_bodies_never_get_a_5xx(api: httpx.Client) -> None:
    job = new_job(api)

    @given(body=_bodies)
    @_FUZZ
    def run(body: bytes) -> None:
        r = api.post("/v1/jobs", content=body, headers={"content-type": "application/json"})
        assert r.status_code < 500, r.text
        if r.status_code in (200, 201):
            api.delete(f"/v1/jobs/{r.json()['id']}")
        r = api.put(f"/v1/jobs/{job}/files/capture.json", content=body)
        assert r.status_code < 500, r.text
        r = _post_zip(api, _zip_bytes({"capture.json": body}), options=body.decode("latin-1"))
        assert r.status_code < 500, r.text
        if r.status_code in (200, 201):
            api.delete(f"/v1/jobs/{r.json()['id']}")

    run()
