"""A run's lease, extended by a process of its own, so a long native call cannot starve it.

The pipeline may stay for seconds in a native call that holds the GIL (a regular
expression, a big-integer or pure-C loop of an extension that never releases it);
a heartbeat *thread* of the job's process then cannot run, the lease lapses, and a
reaper requeues a job that is still running. The worker therefore starts this
keeper (``python -m service.lease_keeper``) for each run, beside its heartbeat
thread. It reads one JSON line on stdin (Redis URL, key prefix, job, run, lease)
and extends the lease every third of it until

* its stdin ends: the run closed it, or the job's process died (SIGKILL included:
  the kernel closes the pipe's end), or
* its parent changed: the job's process died while a child it forked holds the pipe,
* the run no longer owns the job (canceled, deleted, taken over).

So the lease outlives a busy process but not a dead one.
"""

from __future__ import annotations

import json
import logging
import os
import select
import subprocess
import sys

log = logging.getLogger("pmvir.worker")


def keep(redis_url: str, prefix: str, job_id: str, run_id: str, lease_seconds: float) -> None:
    """Extend the run's lease until stdin ends, the parent changes or the run loses the job."""
    from service.store import JobStore

    store = JobStore.from_url(redis_url, prefix=prefix)
    parent = os.getppid()
    interval = max(lease_seconds / 3.0, 0.2)
    started = False
    while True:
        try:
            if not store.heartbeat(job_id, run_id, lease_seconds=lease_seconds):
                return
        except Exception:  # Redis away: try again next time; the lease may lapse meanwhile
            log.debug("lease keeper: heartbeat failed", exc_info=True)
        if not started:  # the run waits for this line: from now on the lease is kept
            started = True
            os.write(1, b"keeping\n")
        readable, _, _ = select.select([0], [], [], interval)
        if readable and not os.read(0, 4096):
            return
        if os.getppid() != parent:
            return


def start(
    redis_url: str, prefix: str, job_id: str, run_id: str, lease_seconds: float, *, wait: float = 30.0
) -> subprocess.Popen | None:
    """Start the keeper of a run and wait (up to ``wait`` seconds) until it has extended the lease
    once. None (logged) when no process could be started: the heartbeat thread still runs. Close its
    stdin to stop it (:func:`stop`)."""
    try:
        proc = subprocess.Popen(
            [sys.executable, "-m", "service.lease_keeper"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            close_fds=True,
        )
        assert proc.stdin is not None and proc.stdout is not None
        spec = {"redis_url": redis_url, "prefix": prefix, "job": job_id, "run": run_id, "lease": lease_seconds}
        proc.stdin.write((json.dumps(spec) + "\n").encode())
        proc.stdin.flush()
        if select.select([proc.stdout], [], [], wait)[0]:
            proc.stdout.readline()  # "keeping", or nothing when the run lost the job meanwhile
        else:
            log.warning("job %s: the lease keeper did not start in %s s", job_id, wait)
    except (OSError, ValueError) as exc:
        log.warning("job %s: no lease keeper process (%s); the heartbeat thread alone keeps the lease", job_id, exc)
        return None
    return proc


def stop(proc: subprocess.Popen | None) -> None:
    """Stop a keeper: its stdin closes, it exits at once (killed if it has not after 5 s)."""
    if proc is None:
        return
    try:
        if proc.stdin is not None:
            proc.stdin.close()
        proc.wait(timeout=5)
        if proc.stdout is not None:
            proc.stdout.close()
    except (OSError, subprocess.TimeoutExpired):
        proc.kill()
        proc.wait(timeout=5)


def main() -> None:
    line = sys.stdin.buffer.readline()
    if not line:  # the run ended (or its process died) before the keeper read its task
        return
    spec = json.loads(line)
    keep(spec["redis_url"], spec["prefix"], spec["job"], spec["run"], float(spec["lease"]))


if __name__ == "__main__":
    main()
