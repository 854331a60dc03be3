"""Fuzzing: schemathesis against the running app's own OpenAPI document.

Every operation of the document served by the live uvicorn server gets a
bounded number of generated requests (Hypothesis derandomized, so the run is
deterministic), sent with a valid API key; operations on a job are fuzzed
both with generated job ids and with the id of a real job (with a capture
uploaded), so the handlers behind the 404 are reached too. Every built-in
check must pass: no 5xx, only documented status codes and content types,
bodies that match their schemas.

(schemathesis' ``from_fixture`` does not run under pytest 9, so the
operations are driven here through ``APIOperation.as_strategy``.)
"""

from __future__ import annotations

from pathlib import Path

import pytest

schemathesis = pytest.importorskip("schemathesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis.errors import Unsatisfiable  # noqa: E402
from schemathesis import GenerationMode  # noqa: E402

from service.testing import ServiceStack  # noqa: E402

from svc_helpers import FUZZ_KEY, client_for, finished, upload, wait_for  # noqa: E402

EXAMPLES = 12
STATUS_SEEN: dict[str, set[int]] = {}
AUTH = {"Authorization": f"Bearer {FUZZ_KEY}"}


#: Not applicable here: it expects every schema-valid request to succeed, but whether a request can
#: succeed depends on state and content the schema cannot express (a job's status, a capture's frames,
#: PipelineConfig's cross-field checks): those are answered 409/422 with the problem named.
EXCLUDED = [schemathesis.checks.positive_data_acceptance]


def fuzz(operation, *, mode, path_parameters: dict | None = None) -> None:
    @given(case=operation.as_strategy(mode, path_parameters=path_parameters))
    @settings(
        max_examples=EXAMPLES,
        derandomize=True,
        deadline=None,
        database=None,
        suppress_health_check=list(HealthCheck),
    )
    def run(case) -> None:
        response = case.call_and_validate(headers=AUTH, timeout=30, excluded_checks=EXCLUDED)
        STATUS_SEEN.setdefault(operation.label, set()).add(response.status_code)

    run()


def test_api_conforms_to_its_schema(stack: ServiceStack, small_capture: Path) -> None:
    schema = schemathesis.openapi.from_url(stack.url + "/openapi.json")
    failures = []
    ran = []
    with client_for(stack, FUZZ_KEY) as c:  # a finished job, for the result downloads
        done = c.post("/v1/jobs", json={"options": {"stop_after": "decode"}}).json()["id"]
        upload(c, done, small_capture)
        c.post(f"/v1/jobs/{done}/start")
        assert wait_for(c, done, finished, timeout=120)["status"] == "succeeded"
    for result in schema.get_all_operations():
        operation = result.ok()
        variants: list[dict | None] = [None]
        if operation.path.endswith("/result/{name}"):
            variants.append({"job_id": done})
        elif "{job_id}" in operation.path:
            with client_for(stack, FUZZ_KEY) as c:
                job_id = c.post("/v1/jobs", json={"options": {"stop_after": "decode"}}).json()["id"]
                upload(c, job_id, small_capture)
            variants.append({"job_id": job_id})
            if "{path}" in operation.path:  # generated paths shrink to capture.json: fuzz a frame too
                variants.append({"job_id": job_id, "path": "frames/001.png"})
        for params in variants:
            for mode in (GenerationMode.POSITIVE, GenerationMode.NEGATIVE):
                try:
                    fuzz(operation, mode=mode, path_parameters=params)
                except Unsatisfiable:
                    assert mode is GenerationMode.NEGATIVE  # nothing to break in a request without inputs
                except Exception as exc:  # noqa: BLE001 - collect every failure, then report them all
                    failures.append(f"{operation.label} {mode.value} {params or ''}:\n{exc}")
            ran.append(operation.label)
        with client_for(stack, FUZZ_KEY) as c:  # keep the key under its in-flight limit
            for j in c.get("/v1/jobs", params={"limit": 500}).json()["jobs"]:
                if j["id"] != done:
                    c.delete(f"/v1/jobs/{j['id']}")
    assert len(set(ran)) >= 9, ran
    assert not failures, "\n\n".join(failures)
    # the generated requests got past authentication and lookup to the handlers
    assert 200 in STATUS_SEEN["PUT /v1/jobs/{job_id}/files/{path}"], STATUS_SEEN
    assert 200 in STATUS_SEEN["GET /v1/jobs/{job_id}/result/{name}"], STATUS_SEEN
    assert 202 in STATUS_SEEN["POST /v1/jobs/{job_id}/start"], STATUS_SEEN
