"""Helpers of the service tests (constants, small HTTP helpers); fixtures are in conftest.py."""

from __future__ import annotations

import shutil
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from service.testing import ServiceStack

KEY = "key-alice"
OTHER_KEY = "key-bob"
FLIGHT_KEY = "key-flight"
FUZZ_KEY = "key-fuzz"

#: Limits of the shared stack: small, so the limit tests send little data.
LIMITS = {
    "PMVIR_MAX_FRAME_BYTES": str(256 * 1024),
    "PMVIR_MAX_MANIFEST_BYTES": str(64 * 1024),
    "PMVIR_MAX_FRAMES": "64",
    "PMVIR_MAX_JOB_BYTES": str(8 * 1024 * 1024),
    "PMVIR_MAX_ZIP_BYTES": str(2 * 1024 * 1024),
    "PMVIR_MAX_ZIP_MEMBERS": "60",
    "PMVIR_MAX_JOBS_IN_FLIGHT": "12",
    "PMVIR_MIN_FREE_BYTES": str(64 * 1024 * 1024),
    "PMVIR_LEASE_SECONDS": "2",
}
#: Options that run the stages this build has.
DECODE_ONLY = {"stop_after": "decode"}
#: One refinement stage of one iteration: a full run that takes seconds.
ONE_REFINE_STAGE = {"solver": {"max_iterations": 1}, "stages": {"tau_pol": [60.0], "tau_gsm": [0.1], "tau_psm": [2.0], "gsm_exponent": [2.2]}}


def require_redis() -> None:
    if shutil.which("redis-server") is None:
        pytest.skip("redis-server is not installed (make setup installs it)")


@contextmanager
def running_stack(
    root: Path,
    *,
    keys: tuple[str, ...],
    bucket: str | None = None,
    worker: bool = True,
    appendonly: bool = False,
    env: dict[str, str] | None = None,
) -> Iterator[ServiceStack]:
    """A stack with the shared limits (and ``env``), its jobs in ``bucket`` of moto's S3 server when
    given; stopped on exit."""
    require_redis()
    st = ServiceStack(root, api_keys=keys, env={**LIMITS, **(env or {})}, appendonly=appendonly)
    try:
        if bucket is not None:
            st.start_s3(bucket)
        st.start(worker=worker)
        yield st
    finally:
        st.stop()


def client_for(st: ServiceStack, key: str = KEY) -> httpx.Client:
    return httpx.Client(base_url=st.url, headers={"Authorization": f"Bearer {key}"}, timeout=30)


def upload(c: httpx.Client, job_id: str, capture: Path) -> dict[str, dict]:
    """PUT every file of a capture folder; returns the answers by path."""
    out = {}
    for p in sorted(capture.rglob("*")):
        if p.is_file():
            rel = p.relative_to(capture).as_posix()
            r = c.put(f"/v1/jobs/{job_id}/files/{rel}", content=p.read_bytes())
            assert r.status_code == 200, r.text
            out[rel] = r.json()
    return out


def new_job(c: httpx.Client, capture: Path | None = None, options: dict | None = None) -> str:
    r = c.post("/v1/jobs", json={"options": DECODE_ONLY if options is None else options})
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    if capture is not None:
        upload(c, job_id, capture)
    return job_id


def wait_for(c: httpx.Client, job_id: str, pred, timeout: float = 60.0, what: str = "") -> dict:
    """Poll the job until ``pred(job)``; returns the job. Also checks progress never goes backwards."""
    deadline = time.monotonic() + timeout
    last = 0.0
    job = {}
    while time.monotonic() < deadline:
        r = c.get(f"/v1/jobs/{job_id}")
        if r.status_code == 200:
            job = r.json()
            assert job["progress"] >= last - 1e-12, f"progress went back from {last} to {job['progress']}"
            last = job["progress"]
            if pred(job):
                return job
        time.sleep(0.05)
    raise AssertionError(f"job {job_id}: {what or 'condition'} not met in {timeout} s; last state {job}")


def start_refused(c: httpx.Client, job_id: str, timeout: float = 60.0) -> dict:
    """POST /start, wait for the validation, and return the refusal as an error body
    (``error``, ``message``, ``errors``): the job went back to created with its problems."""
    r = c.post(f"/v1/jobs/{job_id}/start")
    assert r.status_code == 202 and r.json()["status"] == "validating", r.text
    job = wait_for(c, job_id, lambda j: j["status"] != "validating", timeout=timeout, what="validated")
    assert job["status"] == "created" and job["problems"], job
    return {"error": "invalid_capture", "message": job["error"], "errors": job["problems"]}


def finished(job: dict) -> bool:
    return job["status"] in ("succeeded", "failed", "canceled")
