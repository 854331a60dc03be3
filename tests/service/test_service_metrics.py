"""GET /metrics in Prometheus text format, request ids, JSON log lines."""

from __future__ import annotations

import json
import logging
from pathlib import Path

import httpx
from prometheus_client.parser import text_string_to_metric_families

from service import metrics, observability
from service.store import JobStatus, JobStore
from service.testing import ServiceStack

from svc_helpers import finished, new_job, wait_for


def _scrape(stack: ServiceStack) -> dict[str, dict[tuple, float]]:
    r = httpx.get(stack.url + "/metrics", timeout=10)
    assert r.status_code == 200 and r.headers["content-type"].startswith("text/plain")
    out: dict[str, dict[tuple, float]] = {}
    for family in text_string_to_metric_families(r.text):
        for s in family.samples:
            out.setdefault(s.name, {})[tuple(sorted(s.labels.items()))] = s.value
    return out


def test_metrics_count_jobs_stages_failures_workers_and_storage(
    api: httpx.Client, stack: ServiceStack, small_capture: Path
) -> None:
    job_id = new_job(api, small_capture)
    assert api.post(f"/v1/jobs/{job_id}/start").status_code == 202
    assert wait_for(api, job_id, finished, timeout=90)["status"] == "succeeded"
    store = JobStore.from_url(stack.redis_url)
    metrics.record_end(store, JobStatus.FAILED, {}, "CaptureError: frames/001.png: not a PNG")
    m = _scrape(stack)
    assert m["pmvir_jobs"][(("status", "succeeded"),)] >= 1
    assert {dict(k)["status"] for k in m["pmvir_jobs"]} >= {"created", "validating", "queued", "running"}
    assert m["pmvir_queue_depth"][()] >= 0 and m["pmvir_oldest_queued_age_seconds"][()] >= 0
    decode = {
        dict(k).get("le"): v
        for k, v in m["pmvir_stage_duration_seconds_bucket"].items()
        if ("stage", "decode") in k
    }
    assert decode["+Inf"] >= 1 and all(
        a <= b for a, b in zip(list(decode.values()), list(decode.values())[1:], strict=False)
    )
    assert m["pmvir_stage_duration_seconds_count"][(("stage", "decode"),)] >= 1
    assert m["pmvir_job_failures_total"][(("error_class", "CaptureError"),)] >= 1
    assert m["pmvir_workers_online"][()] >= 1 and len(m["pmvir_worker_last_heartbeat_seconds"]) >= 1
    assert m["pmvir_storage_bytes"][(("kind", "jobs"),)] > 0 and m["pmvir_storage_jobs"][()] >= 1


def test_request_id_is_echoed_or_made(stack: ServiceStack) -> None:
    r = httpx.get(stack.url + "/healthz", headers={"X-Request-ID": "rig-7.upload_42"})
    assert r.headers["x-request-id"] == "rig-7.upload_42"
    made = httpx.get(stack.url + "/healthz").headers["x-request-id"]
    assert len(made) == 32 and made != httpx.get(stack.url + "/healthz").headers["x-request-id"]
    odd = httpx.get(stack.url + "/healthz", headers={"X-Request-ID": "a b\tc"}).headers["x-request-id"]
    assert odd != "a b\tc" and len(odd) == 32  # not a token: replaced, never reflected


def test_json_log_lines_carry_the_request_and_job_ids() -> None:
    record = logging.LogRecord("pmvir.api", logging.WARNING, __file__, 1, "job %s: %s", ("j1", "slow"), None)
    t1, t2 = observability.request_id.set("req-1"), observability.job_id.set("0123abcd")
    try:
        observability.ContextFilter().filter(record)
        line = observability.JsonFormatter().format(record)
    finally:
        observability.request_id.reset(t1)
        observability.job_id.reset(t2)
    doc = json.loads(line)
    assert doc["message"] == "job j1: slow" and doc["level"] == "warning" and doc["logger"] == "pmvir.api"
    assert doc["request_id"] == "req-1" and doc["job_id"] == "0123abcd" and doc["time"].endswith("Z")
