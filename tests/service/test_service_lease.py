"""A run's lease holds while its process is inside a native call that holds the GIL."""

from __future__ import annotations

import math
import re
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
from celery.exceptions import SoftTimeLimitExceeded

from service.runner import _Run
from service.settings import Settings
from service.store import Claim, JobStore

LEASE = 2.0

#: A reaper in a process of its own: requeues the job the moment its lease is seen lapsed.
REAPER = """
import sys, time
from service.store import JobStore
store = JobStore.from_url(sys.argv[1], prefix=sys.argv[2])
print("ready", flush=True)
while not store.r.exists(sys.argv[4]):
    if store.requeue_lapsed(sys.argv[3]):
        print("requeued", flush=True)
        break
    time.sleep(0.02)
"""


def hold_the_gil(seconds: float) -> float:
    """Regular-expression matches (CPython's re never releases the GIL) of growing length until one
    lasts at least ``seconds``; returns how long that one took."""
    n, took = 16, 0.0
    while took < 0.05:  # calibrate: each extra character doubles the backtracking
        n += 2
        t0 = time.perf_counter()
        re.match(r"(a|a)*b", "a" * n)
        took = time.perf_counter() - t0
    n += max(0, math.ceil(math.log2(seconds / took)) - 1)
    while took < seconds:  # a loaded machine runs slower than calibrated: one more character each
        n += 1
        t0 = time.perf_counter()
        re.match(r"(a|a)*b", "a" * n)
        took = time.perf_counter() - t0
    return took


@pytest.mark.slow
def test_the_lease_outlives_a_native_call_longer_than_the_lease(store: JobStore, tmp_path: Path) -> None:
    kw = store.r.connection_pool.connection_kwargs
    url = f"redis://{kw['host']}:{kw['port']}/{kw.get('db', 0)}"
    st = JobStore(store.r, prefix=f"lease-{uuid.uuid4().hex[:8]}")
    settings = Settings(redis_url=url, key_prefix=st.p, lease_seconds=LEASE, storage=tmp_path)
    job_id = uuid.uuid4().hex
    st.create(job_id, "o", options={}, label=None, max_open=10)
    st.transition(st.get(job_id), ("created",), "queued")
    run_id = uuid.uuid4().hex
    what, claimed, _ = st.claim_next(job_id, run_id, lease_seconds=LEASE, max_deliveries=3)
    assert (what, claimed) == (Claim.OK, job_id)
    stop_key = f"{st.p}:stop-reaper"
    reaper = subprocess.Popen(
        [sys.executable, "-c", REAPER, url, st.p, job_id, stop_key], stdout=subprocess.PIPE, text=True
    )
    try:
        assert reaper.stdout is not None and reaper.stdout.readline().strip() == "ready"
        with _Run(st, st.get(job_id), run_id, settings):
            held = hold_the_gil(3 * LEASE)
            job = st.get(job_id)
        st.r.set(stop_key, "1")
        reaper.wait(timeout=30)
        said = reaper.stdout.read()
    finally:
        reaper.kill()
        reaper.wait()
    assert held >= 2 * LEASE, f"the GIL was held {held:.1f} s only"
    assert "requeued" not in said, f"the lease lapsed during a {held:.1f} s native call"
    assert job is not None and job.status == "running" and job.run_id == run_id


def test_the_keeper_stops_with_its_run(store: JobStore, tmp_path: Path) -> None:
    from service import lease_keeper

    kw = store.r.connection_pool.connection_kwargs
    url = f"redis://{kw['host']}:{kw['port']}/{kw.get('db', 0)}"
    st = JobStore(store.r, prefix=f"lease-{uuid.uuid4().hex[:8]}")
    job_id = uuid.uuid4().hex
    st.create(job_id, "o", options={}, label=None, max_open=10)
    st.transition(st.get(job_id), ("created",), "queued")
    st.claim(job_id, "run", lease_seconds=LEASE, max_deliveries=3)
    keeper = lease_keeper.start(url, st.p, job_id, "run", LEASE)
    assert keeper is not None and keeper.poll() is None
    st.r.delete(st.key(job_id, "lease"))
    assert st.requeue_lapsed(job_id)  # another worker took the job over: the keeper's run lost it
    assert keeper.wait(timeout=30) == 0
    assert not st.r.exists(st.key(job_id, "lease"))
    lease_keeper.stop(keeper)


class _LimitLandsInRedis(JobStore):
    """A job store whose progress and cancel reads end as Celery's soft time limit does when its signal
    lands during the Redis call (the calls the pipeline makes most often)."""

    def progress(self, *args: object, **kwargs: object) -> bool:
        raise SoftTimeLimitExceeded()

    def should_stop(self, *args: object, **kwargs: object) -> bool:
        raise SoftTimeLimitExceeded()


def test_the_soft_time_limit_is_not_taken_for_a_redis_failure(store: JobStore, tmp_path: Path) -> None:
    """The progress callback and the cancel check ride out Redis errors, but not the time limit: a
    job whose limit falls in one of them must end, not go on and succeed."""
    st = _LimitLandsInRedis(store.r, prefix=f"limit-{uuid.uuid4().hex[:8]}")
    job_id = uuid.uuid4().hex
    st.create(job_id, "o", options={}, label=None, max_open=10)
    run = _Run(st, st.get(job_id), "run", Settings(storage=tmp_path))
    with pytest.raises(SoftTimeLimitExceeded):
        run.progress("decode", 0.5)
    with pytest.raises(SoftTimeLimitExceeded):
        run.should_cancel()
