"""The local launcher used by the tests, the benchmark and `make demo` stops everything it started."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

from service.testing import ServiceStack

pytestmark = pytest.mark.skipif(shutil.which("redis-server") is None, reason="redis-server is not installed")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    # a zombie still answers kill(0); treat it as gone when the state says so
    try:
        return Path(f"/proc/{pid}/stat").read_text().split()[2] != "Z"
    except OSError:
        return False


def test_entering_and_starting_again_leaves_no_process_behind(tmp_path: Path) -> None:
    with ServiceStack(tmp_path, api_keys=("k",)) as stack:
        redis_pid, api_pid = stack.redis.pid, stack.api.pid
        stack.start()  # starts only what is missing: the worker
        assert (stack.redis.pid, stack.api.pid) == (redis_pid, api_pid)
        assert len(stack.workers) == 1
        pids = [redis_pid, api_pid, stack.workers[0].pid]
        assert all(_alive(p) for p in pids)
    assert not any(_alive(p) for p in pids)
