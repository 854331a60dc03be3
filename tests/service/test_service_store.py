"""The job store's state machine, against a real redis-server (no API, no worker)."""

from __future__ import annotations

import uuid
from pathlib import Path

from service.store import FileInfo, JobStore


def queued_job(store: JobStore, owner: str = "o1") -> str:
    job_id = uuid.uuid4().hex
    assert store.create(job_id, owner, options={}, label=None, max_open=100) is None
    ok, before = store.transition(store.get(job_id), ("created",), "queued")
    assert ok and before == "created"
    return job_id


def test_progress_never_goes_backwards(store: JobStore) -> None:
    job_id = queued_job(store)
    assert store.claim(job_id, "runA", lease_seconds=30, max_deliveries=3) == ("ok", 1)
    assert store.progress(job_id, "runA", stage="decode", fraction=0.5, stage_timings={"decode": 1.0})
    assert store.progress(job_id, "runA", stage="decode", fraction=0.3, stage_timings={"decode": 2.0})
    job = store.get(job_id)
    assert job.progress == 0.5 and job.stage_timings == {"decode": 2.0}
    assert store.progress(job_id, "runA", stage="decode", fraction=7.0, stage_timings={})
    assert store.get(job_id).progress == 1.0  # clamped


def test_a_superseded_run_changes_nothing(store: JobStore) -> None:
    job_id = queued_job(store)
    store.claim(job_id, "runA", lease_seconds=30, max_deliveries=3)
    assert store.claim(job_id, "runB", lease_seconds=30, max_deliveries=3) == ("busy", 0)  # lease alive
    store.r.delete(store.key(job_id, "lease"))  # runA's worker died: its lease lapses
    assert store.lapsed_running() == [job_id]
    assert store.requeue_lapsed(job_id) and not store.requeue_lapsed(job_id)  # one caller wins
    assert store.get(job_id).status == "queued"
    assert store.claim(job_id, "runB", lease_seconds=30, max_deliveries=3) == ("ok", 2)
    assert not store.progress(job_id, "runA", stage="decode", fraction=0.9, stage_timings={})
    assert not store.heartbeat(job_id, "runA", lease_seconds=30)
    assert store.should_stop(job_id, "runA") and not store.should_stop(job_id, "runB")
    job = store.get(job_id)
    assert not store.finish(job, "runA", "succeeded")
    assert store.finish(job, "runB", "succeeded", progress=1.0)
    job = store.get(job_id)
    assert job.status == "succeeded" and job.finished_at is not None and job.progress == 1.0
    assert store.claim(job_id, "runC", lease_seconds=30, max_deliveries=3) == ("done", 0)  # a late redelivery


def test_a_job_that_keeps_killing_its_worker_is_failed(store: JobStore) -> None:
    job_id = queued_job(store)
    for n in (1, 2):
        assert store.claim(job_id, f"run{n}", lease_seconds=30, max_deliveries=2) == ("ok", n)
        store.r.delete(store.key(job_id, "lease"))
        store.requeue_lapsed(job_id)
    what, n = store.claim(job_id, "run3", lease_seconds=30, max_deliveries=2)
    assert (what, n) == ("exhausted", 3)
    job = store.get(job_id)
    assert job.status == "failed" and "started 2 times" in job.error
    assert store.lapsed_running() == []


def test_claim_of_a_job_not_queued(store: JobStore) -> None:
    job_id = uuid.uuid4().hex
    store.create(job_id, "o1", options={}, label=None, max_open=100)
    assert store.claim(job_id, "r", lease_seconds=30, max_deliveries=3) == ("not_queued", 0)
    assert store.claim(uuid.uuid4().hex, "r", lease_seconds=30, max_deliveries=3) == ("gone", 0)


def test_cancel_ends_waiting_jobs_and_flags_running_ones(store: JobStore) -> None:
    waiting = queued_job(store)
    assert store.cancel(store.get(waiting)) == "canceled"
    running = queued_job(store)
    store.claim(running, "r1", lease_seconds=30, max_deliveries=3)
    assert store.cancel(store.get(running)) == "running"
    job = store.get(running)
    assert job.cancel_requested and store.should_stop(running, "r1")
    assert store.finish(job, "r1", "canceled")
    assert store.cancel(store.get(running)) == "canceled"


def test_open_jobs_are_counted_per_owner(store: JobStore) -> None:
    owner = uuid.uuid4().hex
    ids = [uuid.uuid4().hex for _ in range(3)]
    for i in ids[:2]:
        assert store.create(i, owner, options={}, label=None, max_open=2) is None
    assert store.create(ids[2], owner, options={}, label=None, max_open=2) == 2
    assert store.create(ids[2], "someone-else", options={}, label=None, max_open=2) is None
    store.cancel(store.get(ids[0]))
    assert store.create(uuid.uuid4().hex, owner, options={}, label=None, max_open=2) is None


def test_uploads_block_start_and_start_blocks_uploads(store: JobStore) -> None:
    job_id = uuid.uuid4().hex
    store.create(job_id, "o1", options={}, label=None, max_open=100)
    assert store.upload_begin(job_id, "tok") == "ok"
    assert store.start_lock(job_id) == "uploading"
    assert store.upload_commit(job_id, "tok", FileInfo("capture.json", 2, "0" * 64)) == "ok"
    store.upload_end(job_id, "tok")
    assert store.start_lock(job_id) == "ok"
    assert store.upload_begin(job_id, "tok2") == "starting"
    store.start_unlock(job_id)
    assert store.upload_begin(job_id, "tok3", ttl=-1) == "ok"  # an upload whose API process died
    assert store.start_lock(job_id) == "ok"  # its expired token does not block the start
    assert list(store.files(job_id)) == ["capture.json"]


def test_log_is_paged(store: JobStore, tmp_path: Path) -> None:
    job_id = uuid.uuid4().hex
    for i in range(5):
        store.log(job_id, f"line {i}", max_lines=4)
    lines, total = store.read_log(job_id, 1, 2)
    assert total == 4 and [ln["msg"] for ln in lines] == ["line 1", "line 2"]
