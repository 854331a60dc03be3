"""Fair dispatch across tenants: the store's claim order, and one worker serving two tenants."""

from __future__ import annotations

import threading
import uuid
from pathlib import Path

import pytest

from service.store import Claim, JobStore
from service.testing import ServiceStack

from svc_helpers import KEY, LIMITS, OTHER_KEY, client_for, finished, new_job, wait_for


@pytest.fixture()
def fair(store: JobStore) -> JobStore:
    """The module's Redis under a prefix of the test's own (ready lists are global to a prefix)."""
    return JobStore(store.r, prefix=f"fair-{uuid.uuid4().hex[:8]}")


def queue(store: JobStore, owner: str) -> str:
    job_id = f"{owner}-{uuid.uuid4().hex[:8]}"
    assert store.create(job_id, owner, options={}, label=None, max_open=100) is None
    assert store.transition(store.get(job_id), ("created",), "queued")[0]
    return job_id


def claim(store: JobStore, hint: str = "none") -> tuple[Claim, str]:
    what, job_id, _ = store.claim_next(hint, uuid.uuid4().hex, lease_seconds=30, max_deliveries=3)
    return what, job_id


def test_tenants_take_turns_whatever_order_they_queued(fair: JobStore) -> None:
    a = [queue(fair, "a") for _ in range(4)]
    b = [queue(fair, "b") for _ in range(2)]
    order = [claim(fair, hint=a[0])[1] for _ in range(6)]
    assert order == [a[0], b[0], a[1], b[1], a[2], a[3]]
    assert claim(fair, hint=a[0]) == (Claim.BUSY, a[0])  # nothing ready: the message's own job


def test_a_tenant_arriving_late_goes_before_the_busy_tenants_next_job(fair: JobStore) -> None:
    a = [queue(fair, "a") for _ in range(3)]
    assert claim(fair)[1] == a[0]
    b = queue(fair, "b")  # b was never served: its job is next
    assert [claim(fair)[1] for _ in range(3)] == [b, a[1], a[2]]


def test_jobs_that_left_the_queue_are_skipped_and_a_requeued_job_is_first_of_its_tenant(fair: JobStore) -> None:
    a = [queue(fair, "a") for _ in range(3)]
    fair.cancel(fair.get(a[1]))
    fair.delete(fair.get(a[2]))
    assert claim(fair) == (Claim.OK, a[0])
    later = queue(fair, "a")
    fair.r.delete(fair.key(a[0], "lease"))  # its worker died
    assert fair.requeue_lapsed(a[0])
    assert [claim(fair)[1] for _ in range(2)] == [a[0], later]
    assert fair.get(a[0]).deliveries == 2
    assert claim(fair, hint=later) == (Claim.BUSY, later)


def test_concurrent_claims_from_many_workers_take_each_job_once(fair: JobStore) -> None:
    jobs = {queue(fair, owner) for owner in ("a", "b", "c") for _ in range(10)}
    taken: list[str] = []
    lock = threading.Lock()

    def worker() -> None:
        other = JobStore(fair.r.__class__(connection_pool=fair.r.connection_pool), prefix=fair.p)
        while True:
            what, job_id = claim(other)
            if what is not Claim.OK:
                return
            with lock:
                taken.append(job_id)

    threads = [threading.Thread(target=worker) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=60)
    assert sorted(taken) == sorted(jobs)


@pytest.mark.slow
def test_one_worker_runs_a_second_tenants_job_before_the_first_tenants_backlog(
    tmp_path: Path, small_capture: Path
) -> None:
    with (
        ServiceStack(tmp_path / "st", api_keys=(KEY, OTHER_KEY), env=LIMITS) as st,
        client_for(st, KEY) as alice,
        client_for(st, OTHER_KEY) as bob,
    ):
        jobs = []
        for c in (alice, alice, bob):
            job_id = new_job(c, small_capture)
            assert c.post(f"/v1/jobs/{job_id}/start").status_code == 202
            wait_for(c, job_id, lambda j: j["status"] == "queued", timeout=60, what="queued")
            jobs.append((c, job_id))
        st.start_worker()  # every job waits in the queue before the one worker takes any
        done = [wait_for(c, job_id, finished, timeout=120, what="finish") for c, job_id in jobs]
    assert all(j["status"] == "succeeded" for j in done), done
    by_start = [j["id"] for j in sorted(done, key=lambda j: j["started_at"])]
    bobs = jobs[-1][1]
    # FIFO would run bob's job last; fair dispatch runs it first or second (the tenants tie at first)
    assert by_start.index(bobs) <= 1, by_start


def test_the_hard_time_limit_fails_the_job_its_task_claimed(fair: JobStore, tmp_path: Path) -> None:
    from service.runner import fail_now
    from service.settings import Settings

    kw = fair.r.connection_pool.connection_kwargs
    settings = Settings(redis_url=f"redis://{kw['host']}:{kw['port']}/0", key_prefix=fair.p, storage=tmp_path)
    a, b = queue(fair, "a"), queue(fair, "b")
    what, job_id, _ = fair.claim_next(b, "run", lease_seconds=30, max_deliveries=3, task_id="task-of-b")
    assert (what, job_id) == (Claim.OK, a)  # b's message woke the worker; a's job was next
    assert fail_now("task-of-b", settings, "hard time limit exceeded")
    assert fair.get(a).status == "failed" and fair.get(b).status == "queued"
    assert not fail_now("task-of-nobody", settings, "hard time limit exceeded")
