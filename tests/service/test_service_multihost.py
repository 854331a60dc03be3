"""Workers on separate hosts: nothing shared but Redis and an S3 bucket (moto's server on loopback).

The API and two workers each have a storage root and scratch folder of their
own; captures go up through the client, one worker is SIGKILLed in the middle
of a job, and every job still succeeds with its own capture's result, which is
in the bucket and in no local folder.
"""

from __future__ import annotations

import io
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from pmvir.client import PmvirClient
from service.testing import ServiceStack, write_noise_capture

from svc_helpers import DECODE_ONLY, KEY, LIMITS, require_redis

pytest.importorskip("boto3")
pytest.importorskip("moto")

#: (frames, width, height) of the three captures: each job's result tells which capture it came from.
CAPTURES = ((24, 192, 192), (20, 160, 128), (16, 128, 160))
#: Decode-only jobs with the slowest demosaicing, long enough (seconds each) to be caught mid-way.
SLOW_DECODE = {**DECODE_ONLY, "decode": {"demosaic": "eari"}}


@pytest.fixture()
def hosts(tmp_path: Path) -> Iterator[ServiceStack]:
    """moto's S3 server, Redis, the API and two workers, each with its own storage and scratch folders."""
    require_redis()
    st = ServiceStack(tmp_path / "api", api_keys=(KEY,), env={**LIMITS, "PMVIR_CACHE_KEY": "worker-secret"})
    try:
        st.start_s3()
        st.start(worker=False)
        for n in (1, 2):
            host = tmp_path / f"host{n}"
            st.start_worker(
                env={
                    "PMVIR_STORAGE": str(host / "storage"),
                    "PMVIR_SCRATCH": str(host / "scratch"),
                    "PMVIR_API_KEYS": "",  # workers hold no API keys
                }
            )
        yield st
    finally:
        st.stop()


def _running_on(client: PmvirClient, job_ids: list[str], timeout: float = 300.0) -> tuple[str, int]:
    """A running job and the number of the worker (1 or 2) running it.

    Any running job counts, whatever its progress: a decode-only job reports 1.0 once its
    frames are decoded and then spends most of its run packing and uploading the result.
    """
    deadline = time.monotonic() + timeout
    seen: dict[str, tuple[str, float]] = {}
    while time.monotonic() < deadline:
        for job_id in job_ids:
            job = client.job(job_id)
            seen[job_id] = (job["status"], job["progress"])
            if job["status"] == "running":
                lines = [ln["message"] for ln in client.log(job_id)["lines"]]
                starts = [m for m in lines if " started on w" in m]
                if starts:
                    return job_id, int(starts[-1].split(" started on w")[1].split("@")[0])
        time.sleep(0.05)
    raise AssertionError(f"no job was seen running mid-way; last seen: {seen}")


def _local_files(root: Path) -> list[Path]:
    return [p for p in root.rglob("*") if p.is_file()] if root.exists() else []


def test_two_hosts_share_only_redis_and_s3_and_survive_a_killed_worker(
    hosts: ServiceStack, tmp_path: Path
) -> None:
    st = hosts
    ids = []
    with PmvirClient(st.url, KEY, timeout=30) as client:
        for i, (frames, width, height) in enumerate(CAPTURES):
            cap = write_noise_capture(tmp_path / f"cap{i}", frames=frames, width=width, height=height, seed=i)
            job = client.create_job(SLOW_DECODE, label=f"capture {i}")
            client.upload_capture(job["id"], cap)
            ids.append(job["id"])
        for job_id in ids:  # started together, so that the third is still queued when the watch begins
            client.start(job_id)
        victim_job, n = _running_on(client, ids)
        st.workers[n - 1].kill()  # the whole host is gone: worker and pool process, SIGKILL
        assert not st.workers[n - 1].alive()
        done = {job_id: client.wait(job_id, poll=0.2, timeout=240) for job_id in ids}
        for job_id, (frames, width, height) in zip(ids, CAPTURES, strict=True):
            job = done[job_id]
            assert job["status"] == "succeeded", job
            report = client.request("GET", f"/v1/jobs/{job_id}/result/report.json").json()
            assert report["counts"]["frames"] == frames
            data = client.request("GET", f"/v1/jobs/{job_id}/result/result.zip").content
            with zipfile.ZipFile(io.BytesIO(data)) as zf:
                assert zf.testzip() is None
                assert sum(name.endswith(".npz") for name in zf.namelist()) == frames
                with zf.open(f"decoded/{frames - 1:03d}.npz") as f:
                    assert np.load(io.BytesIO(f.read()))["aop"].shape == (height, width)
            # a Range request is answered from the bucket
            r = client.http.get(f"/v1/jobs/{job_id}/result/result.zip", headers={"Range": "bytes=0-3"})
            assert r.status_code == 206 and r.content == b"PK\x03\x04"
        assert done[victim_job]["deliveries"] == 2
        log = [ln["message"] for ln in client.log(victim_job)["lines"]]
        assert any("requeued" in m for m in log)

    keys = [o["Key"] for o in st.s3_client().list_objects_v2(Bucket="pmvir-test").get("Contents", [])]
    for job_id in ids:
        assert f"jobs-root/jobs/{job_id}/result/result.zip" in keys
        assert f"jobs-root/jobs/{job_id}/capture/capture.json" in keys
        # the stage cache went up signed (PMVIR_CACHE_KEY)
        assert {
            f"jobs-root/jobs/{job_id}/cache/decode.pkl",
            f"jobs-root/jobs/{job_id}/cache/decode.pkl.sig",
        } <= set(keys)
    # results live in the bucket alone: no local folder holds one (the killed host may keep its
    # unfinished run's scratch folder, never a result)
    for root in (st.root, tmp_path / "host1", tmp_path / "host2"):
        stray = [
            p
            for p in _local_files(root)
            if (p.name in ("result.zip", "report.json") or p.suffix == ".npz") and "runs" not in p.parts
        ]
        assert stray == [], stray


def test_a_rerun_on_s3_copies_the_capture_in_the_bucket(hosts: ServiceStack, tmp_path: Path) -> None:
    st = hosts
    cap = write_noise_capture(tmp_path / "cap", frames=8, width=96, height=96, seed=5)
    with PmvirClient(st.url, KEY, timeout=30) as client:
        job = client.create_job(DECODE_ONLY)
        client.upload_capture(job["id"], cap)
        client.start(job["id"])
        assert client.wait(job["id"], poll=0.2, timeout=120)["status"] == "succeeded"
        rerun = client.rerun(job["id"], {"decode": {"noise_floor": 0.02}}, from_stage="decode")
        done = client.wait(rerun["id"], poll=0.2, timeout=120)
        assert done["status"] == "succeeded" and done["options"]["decode"]["noise_floor"] == 0.02
        assert len(done["files"]) == 9  # the source's capture, copied inside the bucket
    keys = {o["Key"] for o in st.s3_client().list_objects_v2(Bucket="pmvir-test").get("Contents", [])}
    assert f"jobs-root/jobs/{rerun['id']}/capture/frames/007.png" in keys
    assert f"jobs-root/jobs/{rerun['id']}/result/report.json" in keys
