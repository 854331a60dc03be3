"""Keys, ownership, path validation and limits, against the live service (and one in-process app)."""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import httpx
import pytest

from service.testing import ServiceStack

from svc_helpers import FLIGHT_KEY, KEY, LIMITS, OTHER_KEY, client_for, new_job

FRAME_LIMIT = int(LIMITS["PMVIR_MAX_FRAME_BYTES"])


def storage_files(stack: ServiceStack) -> set[str]:
    return {
        p.relative_to(stack.root).as_posix()
        for p in stack.root.rglob("*")
        if p.is_file() and "logs" not in p.parts and "redis" not in p.parts
    }


@pytest.fixture()
def c(stack: ServiceStack):
    """A client whose jobs are deleted after the test (the key's in-flight limit stays free)."""
    with client_for(stack) as client:
        yield client
        for j in client.get("/v1/jobs", params={"limit": 500}).json()["jobs"]:
            client.delete(f"/v1/jobs/{j['id']}")


# ----------------------------------------------------------------------------- keys and ownership


def test_no_key_is_401(stack: ServiceStack) -> None:
    r = httpx.post(stack.url + "/v1/jobs", json={})
    assert r.status_code == 401 and r.json()["error"] == "unauthorized"


def test_wrong_key_is_401(stack: ServiceStack) -> None:
    r = httpx.get(stack.url + "/v1/jobs", headers={"Authorization": "Bearer not-a-key"})
    assert r.status_code == 401 and r.json()["message"] == "invalid API key"


def test_prefix_of_a_key_is_401(stack: ServiceStack) -> None:
    r = httpx.get(stack.url + "/v1/jobs", headers={"Authorization": f"Bearer {KEY[:-1]}"})
    assert r.status_code == 401


def test_another_keys_job_is_404_everywhere(stack: ServiceStack, small_capture: Path) -> None:
    with client_for(stack) as alice, client_for(stack, OTHER_KEY) as bob:
        job_id = new_job(alice, small_capture)
        j = f"/v1/jobs/{job_id}"
        for method, path in [
            ("GET", j),
            ("GET", j + "/log"),
            ("POST", j + "/start"),
            ("POST", j + "/cancel"),
            ("PUT", j + "/files/frames/000.png"),
            ("GET", j + "/result/result.zip"),
            ("DELETE", j),
        ]:
            r = bob.request(method, path, content=b"x" if method == "PUT" else None)
            assert r.status_code == 404, (method, path, r.text)
            assert r.json() == {"error": "not_found", "message": "job not found", "errors": []}
        # nothing changed for the owner
        job = alice.get(j).json()
        assert job["status"] == "created" and len(job["files"]) == 9


# ----------------------------------------------------------------------------- paths


@pytest.mark.parametrize(
    "path, problem",
    [
        ("%2E%2E/capture.json", "path traversal"),
        ("frames/%2E%2E/%2E%2E/%2E%2E/evil.png", "path traversal"),
        ("frames/..%2Fevil.png", "path traversal"),
        ("/etc/passwd", "absolute path"),
        ("C:%5Cwindows%5Cevil.png", "backslash"),
        ("frames/sub/000.png", "capture layout"),
        ("notes.txt", "capture layout"),
        ("frames/000.exe", "must end in one of"),
        ("masks/000.tif", "must end in one of"),
        ("frames/.hidden.png", "unsupported file name"),
        ("frames/-x.png", "unsupported file name"),
        ("frames/" + "a" * 129 + ".png", "unsupported file name"),
        ("frames/a%00b.png", "NUL"),
    ],
)
def test_bad_upload_paths_are_rejected(stack: ServiceStack, c: httpx.Client, path: str, problem: str) -> None:
    job_id = new_job(c)
    before = storage_files(stack)
    r = c.put(f"/v1/jobs/{job_id}/files/{path}", content=b"payload")
    assert r.status_code == 422, r.text
    assert r.json()["error"] == "invalid_path" and problem in r.json()["message"]
    assert storage_files(stack) == before
    assert c.get(f"/v1/jobs/{job_id}").json()["files"] == []


# ----------------------------------------------------------------------------- sizes and counts


def test_oversize_frame_is_413(stack: ServiceStack, c: httpx.Client) -> None:
    job_id = new_job(c)
    r = c.put(f"/v1/jobs/{job_id}/files/frames/000.png", content=b"\0" * (FRAME_LIMIT + 1))
    assert r.status_code == 413 and r.json()["error"] == "too_large"
    assert c.get(f"/v1/jobs/{job_id}").json()["files"] == []


def test_oversize_streamed_frame_without_length_is_413(stack: ServiceStack, c: httpx.Client) -> None:
    def body():  # chunked transfer encoding: the size is only known while streaming
        for _ in range(FRAME_LIMIT // 65536 + 2):
            yield b"\1" * 65536

    job_id = new_job(c)
    r = c.put(f"/v1/jobs/{job_id}/files/frames/000.raw", content=body())
    assert r.status_code == 413
    incoming = stack.storage / "jobs" / job_id / "incoming"
    assert not incoming.exists() or list(incoming.iterdir()) == []  # the partial temp file is gone


def test_oversize_manifest_is_413(stack: ServiceStack, c: httpx.Client) -> None:
    job_id = new_job(c)
    r = c.put(
        f"/v1/jobs/{job_id}/files/capture.json", content=b" " * (int(LIMITS["PMVIR_MAX_MANIFEST_BYTES"]) + 1)
    )
    assert r.status_code == 413


def test_content_range_total_over_the_limit_is_413(stack: ServiceStack, c: httpx.Client) -> None:
    job_id = new_job(c)
    r = c.put(
        f"/v1/jobs/{job_id}/files/frames/000.raw",
        content=b"x" * 10,
        headers={"Content-Range": f"bytes 0-9/{FRAME_LIMIT + 1}"},
    )
    assert r.status_code == 413


def test_job_byte_limit_is_413(stack: ServiceStack, c: httpx.Client) -> None:
    per = FRAME_LIMIT - 1024
    fit = int(LIMITS["PMVIR_MAX_JOB_BYTES"]) // per
    job_id = new_job(c)
    for i in range(fit):
        assert c.put(f"/v1/jobs/{job_id}/files/frames/{i:03d}.raw", content=b"\2" * per).status_code == 200
    r = c.put(f"/v1/jobs/{job_id}/files/frames/{fit:03d}.raw", content=b"\2" * per)
    assert r.status_code == 413 and "limit" in r.json()["message"]
    # replacing an existing file does not count twice
    assert c.put(f"/v1/jobs/{job_id}/files/frames/000.raw", content=b"\3" * per).status_code == 200


def test_frame_count_limit_is_413(stack: ServiceStack, c: httpx.Client) -> None:
    n = int(LIMITS["PMVIR_MAX_FRAMES"])
    job_id = new_job(c)
    for i in range(n):
        assert c.put(f"/v1/jobs/{job_id}/files/frames/{i:03d}.png", content=b"f").status_code == 200
    r = c.put(f"/v1/jobs/{job_id}/files/frames/{n:03d}.png", content=b"f")
    assert r.status_code == 413 and f"limit is {n}" in r.json()["message"]
    assert c.put(f"/v1/jobs/{job_id}/files/masks/{n:03d}.png", content=b"m").status_code == 200  # masks ok


def test_jobs_in_flight_per_key_is_429(stack: ServiceStack) -> None:
    n = int(LIMITS["PMVIR_MAX_JOBS_IN_FLIGHT"])
    with client_for(stack, FLIGHT_KEY) as c:
        ids = [c.post("/v1/jobs", json={}).json()["id"] for _ in range(n)]
        r = c.post("/v1/jobs", json={})
        assert r.status_code == 429 and r.headers["retry-after"]
        with client_for(stack) as other:  # other keys are not affected
            assert other.post("/v1/jobs", json={}).status_code == 201
        assert c.post(f"/v1/jobs/{ids[0]}/cancel").status_code == 202  # a finished job frees a slot
        assert c.post("/v1/jobs", json={}).status_code == 201


def test_low_free_disk_is_507(tmp_path: Path) -> None:
    """A service told to keep more free space than any disk has refuses every upload."""
    with (
        ServiceStack(tmp_path / "st", api_keys=("k507",), env={"PMVIR_MIN_FREE_BYTES": str(1 << 62)}) as st,
        client_for(st, "k507") as c,
    ):
        job_id = c.post("/v1/jobs", json={}).json()["id"]
        r = c.put(f"/v1/jobs/{job_id}/files/frames/000.png", content=b"abc")
        assert r.status_code == 507 and r.json()["error"] == "insufficient_storage"
        assert c.get(f"/v1/jobs/{job_id}").json()["files"] == []
        zipped = c.post(
            "/v1/jobs",
            files={"capture": ("c.zip", zip_bytes({"capture.json": b"{}"}), "application/zip")},
        )
        assert zipped.status_code == 507


# ----------------------------------------------------------------------------- zipped captures


def zip_bytes(members: dict[str, bytes], *, compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return buf.getvalue()


def post_zip(c: httpx.Client, data: bytes) -> httpx.Response:
    return c.post("/v1/jobs", files={"capture": ("c.zip", data, "application/zip")})


def assert_nothing_kept(
    c: httpx.Client, stack: ServiceStack, before_jobs: int, before_files: set[str]
) -> None:
    assert c.get("/v1/jobs").json()["total"] == before_jobs
    assert storage_files(stack) == before_files


@pytest.fixture()
def zc(stack: ServiceStack):
    with client_for(stack, OTHER_KEY) as c:
        yield c, c.get("/v1/jobs").json()["total"], storage_files(stack)


def test_zip_bomb_is_rejected_before_extraction(stack: ServiceStack, zc) -> None:
    c, jobs, files = zc
    bomb = zip_bytes({"capture.json": b"{}", "frames/000.png": b"\0" * (64 << 20)})
    assert len(bomb) < 200_000  # 64 MiB of zeros deflate to almost nothing
    r = post_zip(c, bomb)
    assert r.status_code == 413 and "frames/000.png" in r.json()["message"]
    assert_nothing_kept(c, stack, jobs, files)


def test_zip_with_too_many_members_is_rejected(stack: ServiceStack, zc) -> None:
    c, jobs, files = zc
    n = int(LIMITS["PMVIR_MAX_ZIP_MEMBERS"]) + 1
    r = post_zip(c, zip_bytes({"capture.json": b"{}", **{f"masks/{i:03d}.png": b"m" for i in range(n)}}))
    assert r.status_code == 413 and "members" in r.json()["message"]
    assert_nothing_kept(c, stack, jobs, files)


@pytest.mark.parametrize(
    "member", ["../evil.png", "/etc/evil.png", "frames/../../evil.png", "notes/readme.txt", "frames/x.exe"]
)
def test_zip_member_outside_the_layout_is_422(stack: ServiceStack, zc, member: str) -> None:
    c, jobs, files = zc
    r = post_zip(c, zip_bytes({"capture.json": b"{}", member: b"x"}))
    assert r.status_code == 422, r.text
    assert [e["file"] for e in r.json()["errors"]] == [member]
    assert_nothing_kept(c, stack, jobs, files)
    assert not (stack.root / "evil.png").exists() and not (stack.storage / "evil.png").exists()


def test_zip_whose_member_lies_about_its_size_is_422(stack: ServiceStack, zc) -> None:
    c, jobs, files = zc
    data = bytearray(
        zip_bytes({"capture.json": b"{}", "frames/000.raw": b"\7" * 5000}, compression=zipfile.ZIP_STORED)
    )
    # claim 50 uncompressed bytes in the central directory entry of frames/000.raw
    cd = data.rfind(b"PK\x01\x02")
    data[cd + 24 : cd + 28] = (50).to_bytes(4, "little")
    r = post_zip(c, bytes(data))
    assert r.status_code == 422, r.text
    assert_nothing_kept(c, stack, jobs, files)


def test_zip_too_large_for_one_request_is_413(stack: ServiceStack, zc) -> None:
    c, jobs, files = zc
    big = bytes(range(256)) * (int(LIMITS["PMVIR_MAX_ZIP_BYTES"]) // 256 + 8192)
    r = post_zip(c, big)
    assert r.status_code == 413
    assert_nothing_kept(c, stack, jobs, files)


def test_not_a_zip_is_422(stack: ServiceStack, zc) -> None:
    c, jobs, files = zc
    r = post_zip(c, b"this is not a zip file")
    assert r.status_code == 422 and r.json()["error"] == "invalid_zip"
    assert_nothing_kept(c, stack, jobs, files)


def test_zip_without_manifest_is_422_when_its_frames_are_not_frames(stack: ServiceStack, zc) -> None:
    """A zip without capture.json is inferred from its frames: an unreadable frame is named, and a
    zip with no frame at all names the missing manifest."""
    c, jobs, files = zc
    r = post_zip(c, zip_bytes({"frames/000.png": b"x"}))
    assert r.status_code == 422 and r.json()["errors"][0]["file"] == "frames/000.png"
    r = post_zip(c, zip_bytes({"notes.txt": b"x"}))
    assert r.status_code == 422 and r.json()["errors"][0]["file"] == "capture.json"
    assert_nothing_kept(c, stack, jobs, files)
