"""Presigned URLs of the bucket (moto's S3 server on loopback): uploads and downloads that bypass
the API, with the API checking what lands."""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from pmvir.client import PmvirClient, ServiceError
from service.testing import ServiceStack

from svc_helpers import (
    DECODE_ONLY,
    KEY,
    LIMITS,
    OTHER_KEY,
    client_for,
    finished,
    new_job,
    running_stack,
    wait_for,
)

pytest.importorskip("boto3")
pytest.importorskip("moto")


@pytest.fixture(scope="module")
def s3_stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceStack]:
    """moto, Redis, the API and a worker, with presigned uploads and downloads on."""
    env = {"PMVIR_S3_PRESIGN_UPLOADS": "1", "PMVIR_S3_PRESIGN_DOWNLOADS": "1"}
    with running_stack(
        tmp_path_factory.mktemp("presigned"), keys=(KEY, OTHER_KEY), bucket="pmvir-test", env=env
    ) as st:
        yield st


class _Recorder(httpx.HTTPTransport):
    """The API client's transport, noting every request it sends to the API."""

    def __init__(self) -> None:
        super().__init__()
        self.sent: list[str] = []

    def handle_request(self, request: httpx.Request) -> httpx.Response:
        self.sent.append(f"{request.method} {request.url.path}")
        return super().handle_request(request)


def _offer(c: httpx.Client, job_id: str, path: str, data: bytes, **over: object) -> dict:
    body = {"path": path, "size": len(data), "sha256": hashlib.sha256(data).hexdigest(), **over}
    r = c.post(f"/v1/jobs/{job_id}/uploads", json=body)
    assert r.status_code == 201, r.text
    offer = r.json()
    assert offer["url"].startswith(("http://127.0.0.1", "https://")) and "Authorization" not in offer["headers"]
    return offer


def _put(offer: dict, data: bytes) -> None:
    r = httpx.put(offer["url"], content=data, headers=offer["headers"])
    assert r.status_code == 200, r.text


@pytest.mark.slow
def test_the_client_uploads_to_the_bucket_and_downloads_from_it(
    s3_stack: ServiceStack, small_capture: Path, tmp_path: Path
) -> None:
    st = s3_stack
    recorder = _Recorder()
    with PmvirClient(st.url, KEY, transport=recorder) as client:
        assert client.info()["presigned_uploads"] and client.info()["presigned_downloads"]
        job_id = client.create_job(options=DECODE_ONLY)["id"]
        client.upload_capture(job_id, small_capture)
        local = {p.relative_to(small_capture).as_posix(): p for p in small_capture.rglob("*") if p.is_file()}
        held = {f["path"]: f["sha256"] for f in client.job(job_id)["files"]}
        assert held == {rel: hashlib.sha256(p.read_bytes()).hexdigest() for rel, p in local.items()}
        assert not [s for s in recorder.sent if s.startswith("PUT ")]  # no byte went through the API
        assert sum(s.endswith("/complete") for s in recorder.sent) == len(local)
        keys = {o["Key"] for o in st.s3_client().list_objects_v2(Bucket="pmvir-test")["Contents"]}
        assert not [k for k in keys if "/incoming/" in k]  # every landed upload was moved
        assert client.start(job_id)["status"] in ("queued", "running", "succeeded")
        assert client.wait(job_id, timeout=120)["status"] == "succeeded"
        report = client.download(job_id, "report.json", tmp_path / "report.json")
        assert json.loads(report.read_text())["counts"]["frames"] == 4

    with client_for(st) as c:
        r = c.get(f"/v1/jobs/{job_id}/result/result.zip")
        assert r.status_code == 307 and "/jobs-root/jobs/" in r.headers["location"]
        whole = httpx.get(r.headers["location"])  # no API key: the URL is the credential
        assert whole.status_code == 200 and zipfile.ZipFile(io.BytesIO(whole.content)).testzip() is None
        part = httpx.get(r.headers["location"], headers={"Range": "bytes=10-19"})
        assert part.status_code == 206 and part.content == whole.content[10:20]
        assert c.get(f"/v1/jobs/{job_id}/result/mesh.ply").status_code == 404  # decode only: no mesh
    with client_for(st, OTHER_KEY) as other:
        assert other.get(f"/v1/jobs/{job_id}/result/result.zip").status_code == 404


def test_what_lands_is_checked_before_it_joins_the_capture(s3_stack: ServiceStack, small_capture: Path) -> None:
    frame = (small_capture / "frames" / "000.png").read_bytes()
    with client_for(s3_stack) as c:
        job_id = new_job(c)
        base = f"/v1/jobs/{job_id}/uploads"

        offer = _offer(c, job_id, "frames/000.png", frame)
        assert c.post(offer["complete"]).status_code == 409  # nothing landed yet
        _put(offer, frame[:-1])  # a byte short of what the offer named
        r = c.post(offer["complete"])
        assert r.status_code == 422 and r.json()["errors"][0]["file"] == "frames/000.png", r.text

        offer = _offer(c, job_id, "frames/000.png", frame)
        _put(offer, bytes(reversed(frame)))  # the right size, other bytes
        r = c.post(offer["complete"])
        assert r.status_code == 422 and "sha256" in r.json()["message"]

        bad = b'{"format": "pmvir-capture", "layout": 7}'
        offer = _offer(c, job_id, "capture.json", bad)
        _put(offer, bad)
        r = c.post(offer["complete"])
        assert r.status_code == 422 and r.json()["errors"][0]["file"] == "capture.json"

        assert c.post(base, json={"path": "../etc/passwd", "size": 1}).status_code == 422
        big = int(LIMITS["PMVIR_MAX_FRAME_BYTES"]) + 1
        assert c.post(base, json={"path": "frames/001.png", "size": big}).status_code == 413
        assert c.post(base, json={"path": "frames/001.png", "size": -1}).status_code == 422
        assert c.post(f"{base}/{'0' * 32}/complete").status_code == 404
        assert c.get(f"/v1/jobs/{job_id}").json()["files"] == []  # nothing refused was recorded

        offer = _offer(c, job_id, "frames/000.png", frame)
        _put(offer, frame)
        with client_for(s3_stack, OTHER_KEY) as other:  # another tenant can neither ask nor complete
            assert other.post(offer["complete"]).status_code == 404
            assert other.post(base, json={"path": "frames/001.png", "size": 1}).status_code == 404
        r = c.post(offer["complete"])
        assert r.status_code == 200 and r.json()["sha256"] == hashlib.sha256(frame).hexdigest()
        assert c.post(offer["complete"]).status_code == 404  # one offer, one file
        assert [f["path"] for f in c.get(f"/v1/jobs/{job_id}").json()["files"]] == ["frames/000.png"]


def test_an_upload_landing_after_the_start_changes_nothing(s3_stack: ServiceStack, small_capture: Path) -> None:
    with client_for(s3_stack) as c:
        job_id = new_job(c, small_capture)
        frame = (small_capture / "frames" / "001.png").read_bytes()
        offer = _offer(c, job_id, "frames/001.png", frame)
        assert c.post(f"/v1/jobs/{job_id}/start").status_code == 202
        _put(offer, b"\0" * len(frame))  # the URL still takes bytes; the job no longer does
        assert c.post(offer["complete"]).status_code == 409
        job = wait_for(c, job_id, finished, timeout=120, what="finish")
        assert job["status"] == "succeeded", job


def test_a_bucket_out_of_reach_falls_back_to_the_api(s3_stack: ServiceStack, small_capture: Path) -> None:
    with PmvirClient(s3_stack.url, KEY) as client:
        client._bucket.close()
        client._bucket = httpx.Client(transport=httpx.MockTransport(lambda r: httpx.Response(403)))
        job_id = client.create_job(options=DECODE_ONLY)["id"]
        out = client.upload_file(job_id, "capture.json", small_capture / "capture.json")
        assert out["sha256"] == hashlib.sha256((small_capture / "capture.json").read_bytes()).hexdigest()
        with pytest.raises(ServiceError) as err:
            client.request("POST", f"/v1/jobs/{job_id}/uploads", ok=(201,), json={"path": "x.txt", "size": 1})
        assert err.value.status == 422
