"""Fault tests: the worker SIGKILLed mid-job, the API and Redis restarted, a running job canceled.

Each test has a stack of its own (Redis with an append-only file, so its state
survives a Redis restart). Jobs decode 64 frames of 256x256: long enough to be
caught mid-way, with no sleep anywhere in the library.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest

from service.testing import ServiceStack, write_noise_capture

from svc_helpers import KEY, LIMITS, client_for, finished, new_job, wait_for

pytestmark = pytest.mark.slow


def mid_job(job: dict) -> bool:
    return job["status"] == "running" and 0.05 < job["progress"] < 0.8


def assert_whole_result(c: httpx.Client, job_id: str, frames: int) -> None:
    r = c.get(f"/v1/jobs/{job_id}/result/result.zip")
    assert r.status_code == 200
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        assert zf.testzip() is None
        names = zf.namelist()
        assert sum(n.endswith(".npz") for n in names) == frames
        with zf.open(f"decoded/{frames - 1:03d}.npz") as f:
            assert np.load(io.BytesIO(f.read()))["aop"].shape == (256, 256)
    report = c.get(f"/v1/jobs/{job_id}/result/report.json").json()
    assert report["counts"]["frames"] == frames


def test_worker_killed_mid_job_then_restarted_completes_the_job(
    fresh_stack: ServiceStack, long_capture: Path
) -> None:
    st = fresh_stack
    worker = st.start_worker()
    with client_for(st) as c:
        job_id = new_job(c, long_capture)
        assert c.post(f"/v1/jobs/{job_id}/start").status_code == 202
        before = wait_for(c, job_id, mid_job, timeout=60, what="running mid-way")
        worker.kill()  # SIGKILL to the worker and its pool process
        assert not worker.alive()
        stalled = c.get(f"/v1/jobs/{job_id}").json()
        assert stalled["status"] == "running" and stalled["progress"] >= before["progress"]
        st.start_worker()
        job = wait_for(c, job_id, finished, timeout=90, what="finish after the restart")
        assert job["status"] == "succeeded", job
        assert job["deliveries"] == 2 and job["progress"] == 1.0
        assert_whole_result(c, job_id, frames=64)
        log = [ln["message"] for ln in c.get(f"/v1/jobs/{job_id}/log").json()["lines"]]
        assert any("requeued" in m for m in log)
        # the killed run's temporary folder was not published and is not left beside the result
        runs = st.storage / "jobs" / job_id / "runs"
        assert not runs.exists() or len(list(runs.iterdir())) <= 1


def test_job_that_keeps_killing_its_worker_fails(tmp_path: Path, long_capture: Path) -> None:
    with ServiceStack(tmp_path / "st", api_keys=(KEY,), env={**LIMITS, "PMVIR_MAX_DELIVERIES": "1"}) as st:
        worker = st.start_worker()
        with client_for(st) as c:
            job_id = new_job(c, long_capture)
            c.post(f"/v1/jobs/{job_id}/start")
            wait_for(c, job_id, mid_job, timeout=60, what="running mid-way")
            worker.kill()
            st.start_worker()
            job = wait_for(c, job_id, finished, timeout=60, what="give up")
            assert job["status"] == "failed" and job["deliveries"] == 2
            assert "worker died" in job["error"]
            assert job["results"] == []


def test_api_restarted_mid_job_keeps_the_state(fresh_stack: ServiceStack, long_capture: Path) -> None:
    st = fresh_stack
    st.start_worker()
    with client_for(st) as c:
        job_id = new_job(c, long_capture)
        c.post(f"/v1/jobs/{job_id}/start")
        before = wait_for(c, job_id, mid_job, timeout=60, what="running mid-way")
    st.restart_api()
    with client_for(st) as c:
        after = c.get(f"/v1/jobs/{job_id}").json()
        assert after["status"] in ("running", "succeeded")
        assert after["progress"] >= before["progress"]
        assert {f["path"] for f in after["files"]} == {f["path"] for f in before["files"]}
        job = wait_for(c, job_id, finished, timeout=90)
        assert job["status"] == "succeeded" and job["deliveries"] == 1
        assert_whole_result(c, job_id, frames=64)


def test_redis_restarted_between_jobs_the_next_job_runs(
    fresh_stack: ServiceStack, small_capture: Path
) -> None:
    st = fresh_stack
    st.start_worker()
    with client_for(st) as c:
        first = new_job(c, small_capture)
        c.post(f"/v1/jobs/{first}/start")
        assert wait_for(c, first, finished, timeout=60)["status"] == "succeeded"
        st.restart_redis()
        # the state survived (append-only file), and the API reconnects by itself
        again = c.get(f"/v1/jobs/{first}")
        assert again.status_code == 200 and again.json()["status"] == "succeeded"
        second = new_job(c, small_capture)
        assert c.post(f"/v1/jobs/{second}/start").status_code == 202
        job = wait_for(c, second, finished, timeout=60, what="the job after the Redis restart")
        assert job["status"] == "succeeded", job
        assert httpx.get(st.url + "/readyz").json()["redis"] is True


def test_cancel_stops_a_running_job_within_seconds(
    fresh_stack: ServiceStack, long_capture: Path, small_capture: Path
) -> None:
    import time

    st = fresh_stack
    st.start_worker()
    with client_for(st) as c:
        job_id = new_job(c, long_capture)
        c.post(f"/v1/jobs/{job_id}/start")
        wait_for(c, job_id, mid_job, timeout=60, what="running mid-way")
        t0 = time.monotonic()
        r = c.post(f"/v1/jobs/{job_id}/cancel")
        assert r.status_code == 202 and r.json()["cancel_requested"] is True
        job = wait_for(c, job_id, finished, timeout=10, what="cancel")
        assert job["status"] == "canceled" and time.monotonic() - t0 < 5.0
        assert job["results"] == [] and job["progress"] < 1.0
        assert (
            not (st.storage / "jobs" / job_id / "runs").exists()
            or list((st.storage / "jobs" / job_id / "runs").iterdir()) == []
        )
        # the worker goes on with the next job
        nxt = new_job(c, small_capture)
        c.post(f"/v1/jobs/{nxt}/start")
        assert wait_for(c, nxt, finished, timeout=60)["status"] == "succeeded"


def test_delete_of_a_running_job_stops_it_and_leaves_no_files(
    fresh_stack: ServiceStack, long_capture: Path
) -> None:
    st = fresh_stack
    st.start_worker()
    with client_for(st) as c:
        job_id = new_job(c, long_capture)
        c.post(f"/v1/jobs/{job_id}/start")
        wait_for(c, job_id, mid_job, timeout=60, what="running mid-way")
        assert c.delete(f"/v1/jobs/{job_id}").status_code == 204
        assert c.get(f"/v1/jobs/{job_id}").status_code == 404
        import time

        deadline = time.monotonic() + 10
        folder = st.storage / "jobs" / job_id
        while folder.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not folder.exists()


def test_job_over_its_soft_time_limit_fails(tmp_path: Path) -> None:
    # 64 frames of 512x512 decode for several seconds even on a fast machine: well over the 1-s limit
    # (the 256x256 capture of the other fault tests can finish inside it).
    capture = write_noise_capture(tmp_path / "cap", frames=64, width=512, height=512, seed=3)
    env = {
        **LIMITS,
        "PMVIR_MAX_FRAME_BYTES": str(1024 * 1024),
        "PMVIR_MAX_JOB_BYTES": str(64 * 1024 * 1024),
        "PMVIR_JOB_SOFT_TIME_LIMIT": "1",
        "PMVIR_JOB_HARD_TIME_LIMIT": "20",
        "PMVIR_VISIBILITY_TIMEOUT": "60",
    }
    with ServiceStack(tmp_path / "st", api_keys=(KEY,), env=env) as st:
        st.start_worker()
        with client_for(st) as c:
            job_id = new_job(c, capture)
            c.post(f"/v1/jobs/{job_id}/start")
            job = wait_for(c, job_id, finished, timeout=60)
            assert job["status"] == "failed" and job["error"] == "time limit exceeded (1 s)"
            assert job["deliveries"] == 1 and job["results"] == []


def test_redis_down_is_503_with_a_json_body_and_readyz_says_so(fresh_stack: ServiceStack) -> None:
    st = fresh_stack
    with client_for(st) as c:
        job_id = new_job(c)
        st.redis.stop()
        ready = httpx.get(st.url + "/readyz")
        assert ready.status_code == 503
        assert ready.json() == {"status": "unavailable", "redis": False, "storage": True}
        r = c.get(f"/v1/jobs/{job_id}")
        assert r.status_code == 503 and r.json()["error"] == "unavailable" and r.headers["retry-after"]
        st.start_redis()
        assert c.get(f"/v1/jobs/{job_id}").json()["status"] == "created"
        assert httpx.get(st.url + "/readyz").status_code == 200
