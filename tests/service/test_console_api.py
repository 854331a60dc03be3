"""The console's routes without a browser: the result listing and per-path download, the pages, offline docs."""

from __future__ import annotations

import re

import httpx
import pytest

from service.console import NODE_MODULES, VENDOR_FILES

from svc_helpers import DECODE_ONLY, OTHER_KEY, client_for, new_job, wait_for


def _decoded_job(api: httpx.Client, small_capture) -> str:
    job_id = new_job(api, small_capture, DECODE_ONLY)
    assert api.post(f"/v1/jobs/{job_id}/start").status_code == 202
    wait_for(api, job_id, lambda j: j["status"] == "succeeded", what="succeeded")
    return job_id


def test_results_are_listed_and_served_by_path_and_nothing_else(
    stack, api: httpx.Client, small_capture
) -> None:
    job_id = _decoded_job(api, small_capture)
    files = api.get(f"/v1/jobs/{job_id}/results").json()["files"]
    paths = {f["path"] for f in files}
    assert {"report.json", "result.zip", "previews/000_int.png", "previews/000_aop.png"} <= paths
    png = next(f for f in files if f["path"] == "previews/000_dop.png")
    assert png["media_type"] == "image/png" and png["stage"] == "decode"
    r = api.get(f"/v1/jobs/{job_id}/results/previews/000_dop.png")
    assert r.status_code == 200 and r.content[:8] == b"\x89PNG\r\n\x1a\n" and len(r.content) == png["size"]
    part = api.get(f"/v1/jobs/{job_id}/results/report.json", headers={"Range": "bytes=0-9"})
    assert part.status_code == 206 and len(part.content) == 10
    for bad in ("../capture/capture.json", "previews/../../capture/capture.json", "frames/000.png", "nope.png"):
        assert api.get(f"/v1/jobs/{job_id}/results/{bad}").status_code == 404, bad
    with client_for(stack, OTHER_KEY) as other:  # another key's job is not found
        assert other.get(f"/v1/jobs/{job_id}/results").status_code == 404
    assert httpx.get(f"{stack.url}/v1/jobs/{job_id}/results").status_code == 401


def test_a_job_without_result_lists_nothing(api: httpx.Client) -> None:
    job_id = new_job(api)
    assert api.get(f"/v1/jobs/{job_id}/results").json() == {"files": []}


def test_console_pages_and_docs_load_nothing_from_elsewhere(stack) -> None:
    if not all((NODE_MODULES / p).is_file() for p in VENDOR_FILES):
        pytest.skip("the npm assets are not installed: run make setup")
    for page in ("/ui/", f"/ui/jobs/{'0' * 32}", "/docs", "/redoc"):
        r = httpx.get(stack.url + page)
        assert r.status_code == 200 and r.headers["content-type"].startswith("text/html"), page
        refs = re.findall(r'(?:src|href)="([^"]+)"', r.text)
        assert refs, page
        for ref in refs:
            assert ref.startswith(("/", "data:")), f"{page} loads {ref}"
            if ref.startswith("/ui/"):
                assert httpx.get(stack.url + ref).status_code == 200, ref
    for module in ("console.js", "shading.js"):  # console.js imports ./shading.js
        js = httpx.get(stack.url + "/ui/static/" + module)
        assert js.status_code == 200 and js.headers["content-type"].startswith("text/javascript"), module
    for module in VENDOR_FILES:
        assert httpx.get(f"{stack.url}/ui/vendor/{module}").status_code == 200, module
    for other in ("three/package.json", "three/examples/jsm/Addons.js", "three/../../package.json"):
        assert httpx.get(f"{stack.url}/ui/vendor/{other}").status_code == 404, other
