"""GET /v1/info, signed webhooks on a loopback receiver, and retention deleting expired jobs."""

from __future__ import annotations

import http.server
import json
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import ClassVar

import httpx
import pytest

from pmvir import __version__
from pmvir.client import verify_webhook
from service.testing import ServiceStack

from svc_helpers import KEY, LIMITS, client_for, finished, require_redis, wait_for

SECRET = "webhook-secret-for-tests"
ADMIN = "key-operator"


class _Receiver(http.server.BaseHTTPRequestHandler):
    """Answers 500 to the first event of each job, 200 to the next; keeps what it got."""

    received: ClassVar[list[tuple[dict[str, str], bytes]]] = []

    def do_POST(self) -> None:
        body = self.rfile.read(int(self.headers["Content-Length"]))
        self.received.append((dict(self.headers), body))
        first = (
            sum(json.loads(b)["job"]["id"] == json.loads(body)["job"]["id"] for _, b in self.received) == 1
        )
        self.send_response(500 if first else 200)
        self.send_header("Content-Length", "0")
        self.end_headers()

    def log_message(self, *args: object) -> None:
        pass


@pytest.fixture(scope="module")
def receiver() -> Iterator[http.server.HTTPServer]:
    server = http.server.HTTPServer(("127.0.0.1", 0), _Receiver)
    t = threading.Thread(target=server.serve_forever, daemon=True)
    t.start()
    yield server
    server.shutdown()


@pytest.fixture(scope="module")
def hk_stack(
    tmp_path_factory: pytest.TempPathFactory, receiver: http.server.HTTPServer
) -> Iterator[ServiceStack]:
    """A stack whose worker delivers webhooks to the receiver and sweeps expired jobs every 0.3 s."""
    require_redis()
    env = {
        **LIMITS,
        "PMVIR_WEBHOOK_HOSTS": f"127.0.0.1:{receiver.server_port}",
        "PMVIR_WEBHOOK_SECRET": SECRET,
        "PMVIR_WEBHOOK_BACKOFF": "0.3",
        "PMVIR_JANITOR_INTERVAL": "0.3",
    }
    st = ServiceStack(tmp_path_factory.mktemp("hk"), api_keys=(KEY,), env={**env, "PMVIR_ADMIN_KEYS": ADMIN})
    try:
        st.start()
        yield st
    finally:
        st.stop()


@pytest.fixture()
def hk(hk_stack: ServiceStack) -> Iterator[httpx.Client]:
    with client_for(hk_stack) as c:
        yield c


def _run(c: httpx.Client, capture: Path, **create: object) -> dict:
    r = c.post("/v1/jobs", json={"options": {"stop_after": "decode"}, **create})
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    for p in sorted(capture.rglob("*")):
        if p.is_file():
            assert c.put(
                f"/v1/jobs/{job_id}/files/{p.relative_to(capture).as_posix()}", content=p.read_bytes()
            )
    assert c.post(f"/v1/jobs/{job_id}/start").status_code == 202
    return wait_for(c, job_id, finished, timeout=60)


def test_info_reports_version_limits_queue_workers_cuda_and_disk(
    hk: httpx.Client, small_capture: Path
) -> None:
    _run(hk, small_capture)  # something on disk
    tenant = hk.get("/v1/info").json()  # a tenant's key: what the service is, not what it holds
    assert tenant["admin"] is False and tenant["limits"]["max_frames"] == int(LIMITS["PMVIR_MAX_FRAMES"])
    assert all(tenant[k] is None for k in ("queue_length", "workers_online", "workers", "cuda_available", "disk"))
    admin = {"Authorization": f"Bearer {ADMIN}"}
    deadline = time.monotonic() + 20
    while (info := hk.get("/v1/info", headers=admin).json())["workers_online"] < 1 and time.monotonic() < deadline:
        time.sleep(0.2)
    assert info["admin"] is True
    assert info["version"] == __version__ and info["stages"] == ["decode", "geometry", "refine"]
    assert info["limits"]["max_frames"] == int(LIMITS["PMVIR_MAX_FRAMES"])
    assert info["limits"]["max_frame_pixels"] > 0 and info["limits"]["result_ttl"] == 0
    assert info["queue_length"] == 0 and info["workers_online"] == 1
    import torch

    assert info["cuda_available"] is torch.cuda.is_available()
    assert info["workers"][0]["version"] == __version__
    assert info["disk"]["free"] > 0 and info["disk"]["jobs"] >= 1 and info["disk"]["jobs_bytes"] > 0
    assert info["webhooks_enabled"] is True
    assert hk.get("/v1/info", headers={"Authorization": "Bearer nope"}).status_code == 401


def test_webhook_is_signed_retried_and_its_attempts_shown_on_the_job(
    hk: httpx.Client, small_capture: Path, receiver: http.server.HTTPServer
) -> None:
    url = f"http://127.0.0.1:{receiver.server_port}/hook"
    job = _run(hk, small_capture, callback_url=url)
    assert job["status"] == "succeeded"
    job = wait_for(hk, job["id"], lambda j: any(d["ok"] for d in j["webhook"]["deliveries"]), timeout=20)
    attempts = job["webhook"]["deliveries"]
    assert [d["status_code"] for d in attempts] == [500, 200] and attempts[1]["ok"]
    mine = [(h, b) for h, b in _Receiver.received if json.loads(b)["job"]["id"] == job["id"]]
    assert len(mine) == 2
    for headers, body in mine:
        assert verify_webhook(SECRET, body, headers["X-Pmvir-Signature"])
        assert not verify_webhook("another-secret", body, headers["X-Pmvir-Signature"])
        assert not verify_webhook(SECRET, body + b" ", headers["X-Pmvir-Signature"])
    event = json.loads(mine[1][1])
    assert event["type"] == "job.finished" and event["attempt"] == 2
    assert event["job"]["status"] == "succeeded" and "report.json" in event["job"]["results"]


def test_webhook_host_not_allowed_is_422(hk: httpx.Client, stack: ServiceStack) -> None:
    r = hk.post("/v1/jobs", json={"callback_url": "http://169.254.169.254/latest"})
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "callback_url"], r.text
    with client_for(stack) as c:  # the default: no hosts allowed at all
        r = c.post("/v1/jobs", json={"callback_url": "http://127.0.0.1:9/x"})
        assert r.status_code == 422 and "PMVIR_WEBHOOK_HOSTS is empty" in r.json()["message"], r.text


def test_a_canceled_job_sends_its_event_too(hk: httpx.Client, receiver: http.server.HTTPServer) -> None:
    r = hk.post("/v1/jobs", json={"callback_url": f"http://127.0.0.1:{receiver.server_port}/c"})
    job = r.json()["id"]
    assert hk.post(f"/v1/jobs/{job}/cancel").json()["status"] == "canceled"
    done = wait_for(hk, job, lambda j: len(j["webhook"]["deliveries"]) >= 1, timeout=20)
    assert done["webhook"]["deliveries"][0]["status_code"] == 500  # the receiver's first answer


def test_an_expired_job_is_deleted_and_a_kept_one_is_not(
    hk: httpx.Client, hk_stack: ServiceStack, small_capture: Path
) -> None:
    kept = _run(hk, small_capture)
    short = _run(hk, small_capture, result_ttl=1)
    assert short["result_ttl"] == 1 and short["expires_at"] is not None
    folder = hk_stack.storage / "jobs" / short["id"]
    deadline = time.monotonic() + 15
    while hk.get(f"/v1/jobs/{short['id']}").status_code != 404 and time.monotonic() < deadline:
        time.sleep(0.2)
    assert hk.get(f"/v1/jobs/{short['id']}").status_code == 404
    assert not folder.exists()
    assert hk.get(f"/v1/jobs/{kept['id']}").status_code == 200
    logs = "".join(p.read_text() for p in hk_stack.log_dir.glob("worker*.log"))
    assert f"job {short['id']} deleted" in logs


def test_a_zipped_capture_may_name_its_callback_and_ttl_too(
    hk: httpx.Client, receiver: http.server.HTTPServer, small_capture: Path, tmp_path: Path
) -> None:
    from pmvir.io.capture_zip import zip_capture

    zip_capture(small_capture, tmp_path / "cap.zip")
    zipped = (tmp_path / "cap.zip").read_bytes()
    files = {"capture": ("cap.zip", zipped, "application/zip")}
    bad = hk.post("/v1/jobs", files=files, data={"callback_url": "http://169.254.169.254/latest"})
    assert bad.status_code == 422 and bad.json()["errors"][0]["loc"] == ["body", "callback_url"], bad.text
    url = f"http://127.0.0.1:{receiver.server_port}/zip"
    r = hk.post("/v1/jobs", files=files, data={"callback_url": url, "result_ttl": "600"})
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["webhook"]["url"] == url and job["result_ttl"] == 600
    hk.delete(f"/v1/jobs/{job['id']}")
