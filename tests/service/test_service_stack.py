"""The local launcher used by the tests, the benchmark and `make demo` stops everything it started."""

from __future__ import annotations

import os
import shutil
import socket
from pathlib import Path

import httpx
import pytest

from service.testing import ServiceStack, _ephemeral_range, free_port

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


def test_ports_lie_below_the_ephemeral_range() -> None:
    # an outgoing connection is only ever given a port inside that range, so it
    # cannot take a chosen port before the server binds it
    lo, _ = _ephemeral_range()
    ports = {free_port() for _ in range(20)}
    assert all(1024 <= p < lo for p in ports)
    assert len(ports) > 1


def test_a_port_taken_before_the_first_start_moves_redis_and_the_api(tmp_path: Path) -> None:
    # bound, not listening: as an outgoing connection holds its local port
    stack = ServiceStack(tmp_path, api_keys=("k",))
    with socket.socket() as r, socket.socket() as a:
        r.bind(("127.0.0.1", stack.redis_port))
        a.bind(("127.0.0.1", stack.api_port))
        taken = (stack.redis_port, stack.api_port)
        with stack:
            assert stack.redis_port != taken[0] and stack.api_port != taken[1]
            assert stack.redis_url.endswith(f":{stack.redis_port}/0")
            assert stack.env["PMVIR_REDIS_URL"] == stack.redis_url
            assert httpx.get(stack.url + "/readyz").json()["redis"] is True
