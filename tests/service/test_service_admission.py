"""Admission: POST /start answers at once (the capture is validated off the request path), the
global queue cap, and created jobs abandoned by their uploader."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import pytest

from service.housekeeping import sweep_abandoned
from service.jobs import interrupted_validations
from service.storage import JobFiles
from service.store import JobStatus, JobStore
from service.testing import ServiceStack

from svc_helpers import KEY, LIMITS, client_for, new_job, require_redis, wait_for


def _validating(store: JobStore) -> str:
    job_id = uuid.uuid4().hex
    assert store.create(job_id, "o1", options={}, label=None, max_open=100) is None
    assert store.transition(store.get(job_id), (JobStatus.CREATED,), JobStatus.VALIDATING)[0]
    store.validating_begin(job_id)
    return job_id


def test_a_validating_job_is_not_claimed_and_cancels_at_once(store: JobStore) -> None:
    job_id = _validating(store)
    assert store.claim(job_id, "r", lease_seconds=30, max_deliveries=3) == ("not_queued", 0)
    assert store.cancel(store.get(job_id)) is JobStatus.CANCELED
    assert store.get(job_id).status is JobStatus.CANCELED


def test_an_interrupted_validation_sends_the_job_back_to_created(store: JobStore) -> None:
    job_id = _validating(store)
    assert interrupted_validations(store, older_than=3600) == []  # still young
    assert interrupted_validations(store, older_than=0) == [job_id]
    job = store.get(job_id)
    assert job.status is JobStatus.CREATED and "interrupted" in (job.error or "")
    assert interrupted_validations(store, older_than=0) == []  # forgotten once handled


def test_start_answers_validating_then_the_job_is_queued(stack: ServiceStack, small_capture: Path) -> None:
    with client_for(stack) as c:
        job_id = new_job(c, small_capture)
        r = c.post(f"/v1/jobs/{job_id}/start")
        assert r.status_code == 202 and r.json()["status"] == "validating"
        job = wait_for(c, job_id, lambda j: j["status"] != "validating", timeout=60, what="validated")
        assert job["status"] in ("queued", "running", "succeeded") and job["problems"] == []
        wait_for(c, job_id, lambda j: j["status"] == "succeeded", timeout=60, what="succeeded")
        log = [ln["message"] for ln in c.get(f"/v1/jobs/{job_id}/log").json()["lines"]]
        assert log.index("validating the capture") < log.index("capture valid; job queued")


def test_a_refused_capture_can_be_fixed_and_started_again(stack: ServiceStack, small_capture: Path) -> None:
    with client_for(stack) as c:
        job_id = new_job(c, small_capture)
        assert c.put(f"/v1/jobs/{job_id}/files/frames/001.png", content=b"not a png").status_code == 200
        assert c.post(f"/v1/jobs/{job_id}/start").status_code == 202
        job = wait_for(c, job_id, lambda j: j["status"] != "validating", timeout=60, what="validated")
        assert job["status"] == "created" and [p["file"] for p in job["problems"]] == ["frames/001.png"]
        assert "1 problem(s)" in job["error"]
        fixed = (small_capture / "frames/001.png").read_bytes()
        assert c.put(f"/v1/jobs/{job_id}/files/frames/001.png", content=fixed).status_code == 200
        assert c.post(f"/v1/jobs/{job_id}/start").status_code == 202
        job = wait_for(c, job_id, lambda j: j["status"] != "validating", timeout=60, what="validated")
        assert job["status"] != "created" and job["problems"] == [] and job["error"] is None


def test_client_start_waits_for_the_validation(stack: ServiceStack, small_capture: Path) -> None:
    from pmvir.client import PmvirClient, ServiceError

    with PmvirClient(stack.url, KEY) as client, client_for(stack) as c:
        job_id = new_job(c, small_capture)
        assert client.start(job_id)["status"] in ("queued", "running", "succeeded")
        bad = new_job(c, small_capture)
        assert c.put(f"/v1/jobs/{bad}/files/frames/001.png", content=b"not a png").status_code == 200
        with pytest.raises(ServiceError) as err:
            client.start(bad)
        assert err.value.status == 422 and [e["file"] for e in err.value.body["errors"]] == ["frames/001.png"]


def test_a_created_job_left_untouched_is_deleted_and_frees_its_slot(store: JobStore, tmp_path: Path) -> None:
    files = JobFiles(tmp_path)
    old, fresh = uuid.uuid4().hex, uuid.uuid4().hex
    for job_id in (old, fresh):
        assert store.create(job_id, "o2", options={}, label=None, max_open=100) is None
        files.create(job_id)
    store.r.hset(store.key(old), "updated_at", repr(time.time() - 7200))
    assert sweep_abandoned(store, files, ttl=3600) == [old]
    assert store.get(old) is None and not files.exists(old)
    assert store.r.smembers(f"{store.p}:owner:o2:open") == {fresh}
    assert sweep_abandoned(store, files, ttl=0) == []  # 0: never


def test_starts_beyond_the_queue_cap_are_503_with_retry_after(tmp_path: Path, small_capture: Path) -> None:
    require_redis()
    env = {**LIMITS, "PMVIR_MAX_QUEUED": "1"}
    with ServiceStack(tmp_path / "st", api_keys=(KEY,), env=env) as st, client_for(st) as c:
        # no worker: what is queued stays queued
        first, second = new_job(c, small_capture), new_job(c, small_capture)
        assert c.post(f"/v1/jobs/{first}/start").status_code == 202
        wait_for(c, first, lambda j: j["status"] == "queued", timeout=60, what="queued")
        store = JobStore.from_url(st.redis_url)
        deadline = time.monotonic() + 30
        while store.queue_length("pmvir") < 1 and time.monotonic() < deadline:  # its message is sent after
            time.sleep(0.05)
        r = c.post(f"/v1/jobs/{second}/start")
        assert r.status_code == 503 and r.json()["error"] == "queue_full" and r.headers["retry-after"] == "30"
        assert c.get(f"/v1/jobs/{second}").json()["status"] == "created"
