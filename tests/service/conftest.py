"""Fixtures of the service tests: a real redis-server, uvicorn and Celery worker on loopback ports.

Skipped as a whole (with the reason) when redis-server is not installed;
``make setup`` installs it.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.store import JobStore
from service.testing import ServiceStack, write_noise_capture

from svc_helpers import FLIGHT_KEY, FUZZ_KEY, KEY, OTHER_KEY, client_for, require_redis, running_stack


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceStack]:
    """redis + API + one worker, shared by a test module."""
    with running_stack(tmp_path_factory.mktemp("stack"), keys=(KEY, OTHER_KEY, FLIGHT_KEY, FUZZ_KEY)) as st:
        yield st


@pytest.fixture()
def fresh_stack(tmp_path: Path) -> Iterator[ServiceStack]:
    """A stack of its own (for tests that kill or restart its parts); no worker started yet."""
    with running_stack(tmp_path / "stack", keys=(KEY,), worker=False, appendonly=True) as st:
        yield st


@pytest.fixture(scope="module")
def store(tmp_path_factory: pytest.TempPathFactory) -> Iterator[JobStore]:
    """A job store on a redis-server of its own (no API, no worker), shared by a test module."""
    require_redis()
    st = ServiceStack(tmp_path_factory.mktemp("redis"))
    try:
        st.start_redis()
        yield JobStore.from_url(st.redis_url, prefix="t")
    finally:
        st.stop()


@pytest.fixture()
def api(stack: ServiceStack) -> Iterator[httpx.Client]:
    with client_for(stack) as c:
        yield c


@pytest.fixture(scope="session")
def small_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """4 frames of 64x48 with masks: a valid capture for the API tests."""
    return write_noise_capture(tmp_path_factory.mktemp("cap") / "small", frames=4, masks=True, seed=1)


@pytest.fixture(scope="session")
def long_capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Enough frames that decoding takes seconds: a job to kill, restart or cancel mid-way."""
    return write_noise_capture(
        tmp_path_factory.mktemp("cap") / "long", frames=64, width=256, height=256, seed=2
    )


@pytest.hookimpl(wrapper=True, tryfirst=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo):
    rep = yield
    setattr(item, "rep_" + rep.when, rep)
    return rep


@pytest.fixture(autouse=True)
def _service_logs_on_failure(request: pytest.FixtureRequest) -> Iterator[None]:
    """When a test fails, print the logs of the processes it used (redis, API, workers)."""
    yield
    rep = getattr(request.node, "rep_call", None)
    if rep is not None and rep.failed:
        for name in ("stack", "fresh_stack"):
            if name in request.fixturenames:
                print(request.getfixturevalue(name).logs())
