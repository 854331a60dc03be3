"""Full-size frames (2448x2048, the IMX250MYR's) through the real stack (Redis, API, Celery worker)
with an 8 GiB job memory limit (``PMVIR_JOB_MEMORY``, the worker's address space): a capture is
uploaded and decoded at full size; a reconstruction whose estimated peak is over the limit fails at
once with an error naming the limit and what would fit, and the same worker takes the next job (no
out-of-memory kill, no redelivery)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import httpx
import pytest

from service.testing import ServiceStack, write_noise_capture

from svc_helpers import KEY, client_for, finished, new_job, running_stack, wait_for

GiB = 2**30
MiB = 2**20
FULL = (2448, 2048)


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceStack]:
    env = {
        "PMVIR_MAX_FRAME_BYTES": str(64 * MiB),
        "PMVIR_MAX_JOB_BYTES": str(512 * MiB),
        "PMVIR_JOB_MEMORY": str(8 * GiB),
        "PMVIR_LEASE_SECONDS": "30",
    }
    with running_stack(tmp_path_factory.mktemp("stack"), keys=(KEY,), env=env) as st:
        yield st


@pytest.fixture(scope="module")
def capture(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_noise_capture(
        tmp_path_factory.mktemp("full") / "cap", frames=4, width=FULL[0], height=FULL[1], masks=True, dop=0.1
    )


@pytest.fixture()
def api(stack: ServiceStack) -> Iterator[httpx.Client]:
    with client_for(stack) as c:
        yield c


def _run(api: httpx.Client, capture: Path, options: dict) -> dict:
    job_id = new_job(api, capture, options)
    r = api.post(f"/v1/jobs/{job_id}/start")
    assert r.status_code == 202, r.text
    return wait_for(api, job_id, finished, timeout=300, what="finished")


@pytest.mark.slow
def test_full_size_frames_decode_through_the_service(api: httpx.Client, capture: Path) -> None:
    job = _run(api, capture, {"stop_after": "decode"})
    assert job["status"] == "succeeded", job
    report = api.get(f"/v1/jobs/{job['id']}/results/report.json").json()
    assert report["resolution"]["frames"] == "2448x2048" and report["resolution"]["decode"] == "2448x2048"
    assert report["counts"]["frames"] == 4 and report["resolution"]["binning"] == 1, report
    assert "decoded.zip" in job["results"], job["results"]


@pytest.mark.slow
def test_a_reconstruction_over_the_memory_limit_fails_at_once_and_the_worker_goes_on(
    api: httpx.Client, capture: Path
) -> None:
    # at the full working size (no binning) four views need about 10 GiB by pmvir.memory's estimate
    over = {"decode": {"max_working_size_px": FULL[0]}, "stop_after": "refine"}
    job = _run(api, capture, over)
    assert job["status"] == "failed", job
    message = job["error"]
    assert "2448x2048" in message and "8.0 GiB (PMVIR_JOB_MEMORY)" in message, message
    assert "decode.max_working_size_px=" in message, message
    assert job["progress"] < 0.05, job  # refused before decoding
    after = _run(api, capture, {"stop_after": "decode"})
    assert after["status"] == "succeeded", after
