"""The /v1 API end to end: real redis-server, Celery worker and uvicorn on loopback ports."""

from __future__ import annotations

import hashlib
import io
import json
import zipfile
from pathlib import Path

import httpx
import numpy as np
import pytest

from pmvir.io.frames import write_frame
from service.testing import ServiceStack, write_noise_capture

from svc_helpers import (
    DECODE_ONLY,
    KEY,
    OTHER_KEY,
    client_for,
    finished,
    new_job,
    start_refused,
    upload,
    wait_for,
)


def sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


@pytest.fixture(scope="module")
def done_job(stack: ServiceStack, small_capture: Path) -> dict:
    """One job run through the whole flow: create, upload, start, poll until it ends."""
    with client_for(stack) as c:
        job_id = new_job(c)
        answers = upload(c, job_id, small_capture)
        started = c.post(f"/v1/jobs/{job_id}/start")
        seen: list[dict] = []
        job = wait_for(c, job_id, lambda j: seen.append(j) or finished(j), timeout=90, what="finish")
        return {"id": job_id, "uploads": answers, "start": started, "job": job, "seen": seen}


def test_job_runs_end_to_end_and_its_result_parses(
    api: httpx.Client, done_job: dict, small_capture: Path
) -> None:
    for rel, answer in done_job["uploads"].items():
        assert answer["sha256"] == sha((small_capture / rel).read_bytes()), rel
        assert answer["complete"] is True
    assert done_job["start"].status_code == 202 and done_job["start"].json()["status"] == "validating"
    assert [j["status"] for j in done_job["seen"]][-1] == "succeeded"
    job = done_job["job"]
    assert job["status"] == "succeeded", job
    assert job["progress"] == 1.0 and job["stage"] == "decode"
    assert job["stage_timings"]["decode"] > 0
    assert job["deliveries"] == 1 and job["error"] is None
    assert set(job["results"]) == {"capture.json", "decoded.zip", "previews.zip", "report.json", "result.zip"}
    assert {f["path"] for f in job["files"]} == set(done_job["uploads"])
    progresses = [j["progress"] for j in done_job["seen"]]
    assert progresses == sorted(progresses)

    report = api.get(f"/v1/jobs/{job['id']}/result/report.json")
    assert report.status_code == 200 and report.headers["content-type"] == "application/json"
    assert report.json()["stages"] == ["decode"] and report.json()["counts"]["frames"] == 4

    r = api.get(f"/v1/jobs/{job['id']}/result/result.zip")
    assert r.status_code == 200 and r.headers["content-type"] == "application/zip"
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        assert zf.testzip() is None
        assert "report.json" in zf.namelist()
        with zf.open("decoded/002.npz") as f:
            data = np.load(io.BytesIO(f.read()))
            assert data["i_int"].shape == (48, 64, 3) and data["i_int"].dtype == np.float32
    missing = api.get(f"/v1/jobs/{job['id']}/result/mesh.ply")
    assert missing.status_code == 404 and missing.json()["error"] == "not_found"


def test_log_lines_are_paged_with_since(api: httpx.Client, done_job: dict) -> None:
    job_id = done_job["id"]
    full = api.get(f"/v1/jobs/{job_id}/log").json()
    messages = [ln["message"] for ln in full["lines"]]
    assert messages[0] == "job created" and messages[-1] == "succeeded"
    assert any(m.startswith("stage decode") for m in messages)
    assert full["next"] == full["total"] == len(messages)
    tail = api.get(f"/v1/jobs/{job_id}/log", params={"since": 2}).json()
    assert [ln["index"] for ln in tail["lines"]] == list(range(2, full["total"]))
    assert api.get(f"/v1/jobs/{job_id}/log", params={"since": full["total"]}).json()["lines"] == []


def test_a_runs_warnings_reach_the_job_log(
    api: httpx.Client, stack: ServiceStack, tmp_path_factory: pytest.TempPathFactory
) -> None:
    """A specular-dominated capture (masked, DoP 0.3 everywhere): the pipeline's warning is a
    "warning: ..." line of the job's log before "succeeded", and in report.json."""
    capture = write_noise_capture(tmp_path_factory.mktemp("cap") / "shiny", frames=3, masks=True, seed=3, dop=0.3)
    with client_for(stack) as c:
        job_id = new_job(c, capture)
        assert c.post(f"/v1/jobs/{job_id}/start").status_code == 202
        job = wait_for(c, job_id, finished, timeout=90, what="finish")
    assert job["status"] == "succeeded", job
    messages = [ln["message"] for ln in api.get(f"/v1/jobs/{job_id}/log").json()["lines"]]
    warnings = [m for m in messages if m.startswith("warning: ")]
    assert len(warnings) == 1 and "specular-dominated" in warnings[0], messages
    assert messages.index(warnings[0]) < messages.index("succeeded")
    report = api.get(f"/v1/jobs/{job_id}/result/report.json").json()
    assert report["warnings"] == [warnings[0].removeprefix("warning: ")]


def test_result_download_honours_range(api: httpx.Client, done_job: dict) -> None:
    url = f"/v1/jobs/{done_job['id']}/result/result.zip"
    full = api.get(url)
    size = len(full.content)
    part = api.get(url, headers={"Range": "bytes=10-19"})
    assert part.status_code == 206 and part.content == full.content[10:20]
    assert part.headers["content-range"] == f"bytes 10-19/{size}"
    suffix = api.get(url, headers={"Range": "bytes=-7"})
    assert suffix.status_code == 206 and suffix.content == full.content[-7:]
    open_end = api.get(url, headers={"Range": f"bytes={size - 3}-"})
    assert open_end.content == full.content[-3:]
    past = api.get(url, headers={"Range": f"bytes={size}-"})
    assert past.status_code == 416 and past.headers["content-range"] == f"bytes */{size}"
    assert past.json()["error"] == "range_not_satisfiable"
    stale = api.get(url, headers={"Range": "bytes=0-9", "If-Range": '"stale"'})
    assert stale.status_code == 200 and stale.content == full.content
    fresh = api.get(url, headers={"Range": "bytes=0-9", "If-Range": full.headers["etag"]})
    assert fresh.status_code == 206 and fresh.content == full.content[:10]


def test_unknown_and_out_of_range_options_are_422_naming_each(api: httpx.Client) -> None:
    r = api.post(
        "/v1/jobs",
        json={"options": {"decode": {"noise_floor": 5.0, "colour": 1}, "stop_after": "x"}, "extra": True},
    )
    assert r.status_code == 422
    locs = {tuple(e["loc"]) for e in r.json()["errors"]}
    assert locs == {
        ("body", "options", "decode", "noise_floor"),
        ("body", "options", "decode", "colour"),
        ("body", "options", "stop_after"),
        ("body", "extra"),
    }


def test_body_that_is_not_json_is_422(api: httpx.Client) -> None:
    r = api.post("/v1/jobs", content=b"{not json", headers={"Content-Type": "application/json"})
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body"]


def test_other_content_type_is_415(api: httpx.Client) -> None:
    r = api.post("/v1/jobs", content=b"hello", headers={"Content-Type": "text/plain"})
    assert r.status_code == 415 and r.json()["error"] == "unsupported_media_type"


def test_idempotency_key_makes_a_retried_create_return_the_same_job(api: httpx.Client) -> None:
    body = {"options": DECODE_ONLY, "label": "retry me"}
    first = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "create-42"})
    again = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "create-42"})
    assert first.status_code == 201 and again.status_code == 200
    assert again.json()["id"] == first.json()["id"]
    other = api.post("/v1/jobs", json={**body, "label": "changed"}, headers={"Idempotency-Key": "create-42"})
    assert other.status_code == 409
    # once the job is deleted, the key makes a new one
    assert api.delete(f"/v1/jobs/{first.json()['id']}").status_code == 204
    fresh = api.post("/v1/jobs", json=body, headers={"Idempotency-Key": "create-42"})
    assert fresh.status_code == 201 and fresh.json()["id"] != first.json()["id"]
    # the same key from another API key is another job
    with client_for_other(api) as bob:
        assert (
            bob.post("/v1/jobs", json=body, headers={"Idempotency-Key": "create-42"}).json()["id"]
            != first.json()["id"]
        )


def client_for_other(api: httpx.Client) -> httpx.Client:
    return httpx.Client(base_url=api.base_url, headers={"Authorization": f"Bearer {OTHER_KEY}"})


def test_zipped_capture_in_one_request(api: httpx.Client, small_capture: Path, tmp_path: Path) -> None:
    zpath = tmp_path / "cap.zip"
    with zipfile.ZipFile(zpath, "w", zipfile.ZIP_DEFLATED) as zf:
        for p in sorted(small_capture.rglob("*")):
            if p.is_file():
                zf.write(p, "mycapture/" + p.relative_to(small_capture).as_posix())
    r = api.post(
        "/v1/jobs",
        data={"options": json.dumps(DECODE_ONLY), "label": "zipped"},
        files={"capture": ("cap.zip", zpath.read_bytes(), "application/zip")},
    )
    assert r.status_code == 201, r.text
    job = r.json()
    assert job["label"] == "zipped" and job["options"]["stop_after"] == "decode"
    local = {
        p.relative_to(small_capture).as_posix(): sha(p.read_bytes())
        for p in small_capture.rglob("*")
        if p.is_file()
    }
    assert {f["path"]: f["sha256"] for f in job["files"]} == local
    assert api.post(f"/v1/jobs/{job['id']}/start").status_code == 202
    assert wait_for(api, job["id"], finished, timeout=60)["status"] == "succeeded"


def test_idempotency_key_with_a_zipped_capture(api: httpx.Client, small_capture: Path) -> None:
    def zipped(
        extra: bytes = b"", when: tuple[int, ...] = (2026, 1, 2, 3, 4, 6), reverse: bool = False
    ) -> bytes:
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
            for p in sorted(small_capture.rglob("*"), reverse=reverse):
                if p.is_file():
                    zf.writestr(
                        zipfile.ZipInfo(p.relative_to(small_capture).as_posix(), date_time=when),
                        p.read_bytes() + (extra if p.suffix == ".png" and "masks" in p.parts else b""),
                    )
            if reverse:  # zipped on a Mac: metadata the import skips
                zf.writestr("__MACOSX/._capture.json", b"\0\5\26\7")
                zf.writestr(".DS_Store", b"Bud1")
        return buf.getvalue()

    def post(data: bytes) -> httpx.Response:
        return api.post(
            "/v1/jobs",
            files={"capture": ("c.zip", data, "application/zip")},
            headers={"Idempotency-Key": "zip-7"},
        )

    # the retry zips the same frames again: other timestamps, member order and bytes, Mac metadata
    rezipped = zipped(when=(2026, 5, 6, 7, 8, 10), reverse=True)
    assert rezipped != zipped()
    first, again = post(zipped()), post(rezipped)
    assert (first.status_code, again.status_code) == (201, 200)
    assert again.json()["id"] == first.json()["id"] and len(again.json()["files"]) == 9
    assert post(zipped(b"changed")).status_code == 409


def test_zip_with_invalid_options_is_422_and_leaves_no_job(
    api: httpx.Client, small_capture: Path, tmp_path: Path
) -> None:
    before = api.get("/v1/jobs").json()["total"]
    zpath = tmp_path / "c.zip"
    with zipfile.ZipFile(zpath, "w") as zf:
        zf.write(small_capture / "capture.json", "capture.json")
    r = api.post(
        "/v1/jobs",
        data={"options": json.dumps({"decode": {"noise_floor": -1}})},
        files={"capture": ("c.zip", zpath.read_bytes(), "application/zip")},
    )
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == [
        "body",
        "options",
        "decode",
        "noise_floor",
    ]
    assert api.get("/v1/jobs").json()["total"] == before


def test_start_answers_422_with_per_file_errors(
    api: httpx.Client, small_capture: Path, tmp_path: Path
) -> None:
    job_id = new_job(api, small_capture)
    # frames/001.png: not an image; frames/002.png: a decodable frame of the wrong size
    assert api.put(f"/v1/jobs/{job_id}/files/frames/001.png", content=b"not a png").status_code == 200
    write_frame(tmp_path / "small.png", np.zeros((24, 32), np.uint16), bit_depth=12)
    assert (
        api.put(
            f"/v1/jobs/{job_id}/files/frames/002.png", content=(tmp_path / "small.png").read_bytes()
        ).status_code
        == 200
    )
    refused = start_refused(api, job_id)
    files = {e["file"] for e in refused["errors"]}
    # the mask of frame 002 no longer matches its frame's size: named too
    assert files == {"frames/001.png", "frames/002.png", "masks/002.png"}, refused
    assert "3 problem(s)" in refused["message"]
    # re-uploading replaces the bad files; then the job starts
    for rel in ("frames/001.png", "frames/002.png"):
        fixed = api.put(f"/v1/jobs/{job_id}/files/{rel}", content=(small_capture / rel).read_bytes())
        assert fixed.json()["sha256"] == sha((small_capture / rel).read_bytes())
    assert api.post(f"/v1/jobs/{job_id}/start").status_code == 202


def test_start_without_a_manifest_is_422_naming_capture_json(api: httpx.Client) -> None:
    job_id = new_job(api)
    refused = start_refused(api, job_id)
    assert [e["file"] for e in refused["errors"]] == ["capture.json"]
    assert "/jobs/" not in str(refused)  # no storage paths in answers


def test_invalid_manifest_upload_is_422(api: httpx.Client) -> None:
    job_id = new_job(api)
    r = api.put(
        f"/v1/jobs/{job_id}/files/capture.json", content=b'{"format": "pmvir-capture/1", "frames": []}'
    )
    assert r.status_code == 422 and r.json()["errors"][0]["file"] == "capture.json"
    assert api.get(f"/v1/jobs/{job_id}").json()["files"] == []


def test_resumable_upload_with_content_range(api: httpx.Client) -> None:
    job_id = new_job(api)
    data = np.random.default_rng(3).integers(0, 256, 3000, dtype=np.uint8).tobytes()
    url = f"/v1/jobs/{job_id}/files/frames/000.raw"
    r = api.put(url, content=data[:1000], headers={"Content-Range": "bytes 0-999/3000"})
    assert r.status_code == 202 and r.json() == {
        "path": "frames/000.raw",
        "size": 1000,
        "complete": False,
        "sha256": None,
    }
    assert api.get(f"/v1/jobs/{job_id}").json()["partial_uploads"] == [
        {"path": "frames/000.raw", "received": 1000, "total": 3000}
    ]
    gap = api.put(url, content=data[2000:], headers={"Content-Range": "bytes 2000-2999/3000"})
    assert gap.status_code == 409 and gap.json()["received"] == 1000
    assert (
        api.put(url, content=data[1000:2000], headers={"Content-Range": "bytes 1000-1999/3000"}).status_code
        == 202
    )
    done = api.put(url, content=data[2000:], headers={"Content-Range": "bytes 2000-2999/3000"})
    assert done.status_code == 200 and done.json()["sha256"] == sha(data) and done.json()["size"] == 3000
    job = api.get(f"/v1/jobs/{job_id}").json()
    assert job["partial_uploads"] == [] and job["files"] == [
        {"path": "frames/000.raw", "size": 3000, "sha256": sha(data)}
    ]


def test_malformed_content_range_is_400(api: httpx.Client) -> None:
    job_id = new_job(api)
    r = api.put(
        f"/v1/jobs/{job_id}/files/frames/000.png",
        content=b"x" * 10,
        headers={"Content-Range": "bytes 5-2/10"},
    )
    assert r.status_code == 400 and r.json()["error"] == "bad_content_range"


def test_reupload_replaces_the_file(api: httpx.Client) -> None:
    job_id = new_job(api)
    api.put(f"/v1/jobs/{job_id}/files/masks/000.png", content=b"first")
    r = api.put(f"/v1/jobs/{job_id}/files/masks/000.png", content=b"second version")
    assert r.json()["sha256"] == sha(b"second version")
    assert api.get(f"/v1/jobs/{job_id}").json()["files"] == [
        {"path": "masks/000.png", "size": 14, "sha256": sha(b"second version")}
    ]


def test_upload_after_start_is_409(api: httpx.Client, small_capture: Path) -> None:
    job_id = new_job(api, small_capture)
    assert api.post(f"/v1/jobs/{job_id}/start").status_code == 202
    r = api.put(f"/v1/jobs/{job_id}/files/frames/009.png", content=b"late")
    assert r.status_code == 409
    assert api.post(f"/v1/jobs/{job_id}/start").status_code == 409


def test_cancel_created_job_and_cancel_after_success(api: httpx.Client, done_job: dict) -> None:
    job_id = new_job(api)
    r = api.post(f"/v1/jobs/{job_id}/cancel")
    assert r.status_code == 202 and r.json()["status"] == "canceled" and r.json()["finished_at"]
    assert api.post(f"/v1/jobs/{job_id}/cancel").json()["status"] == "canceled"  # idempotent
    assert api.post(f"/v1/jobs/{job_id}/start").status_code == 409
    late = api.post(f"/v1/jobs/{done_job['id']}/cancel")
    assert late.status_code == 409 and "succeeded" in late.json()["message"]


def test_delete_removes_the_job_and_its_files(
    api: httpx.Client, stack: ServiceStack, small_capture: Path
) -> None:
    job_id = new_job(api, small_capture)
    folder = stack.storage / "jobs" / job_id
    assert (folder / "capture" / "capture.json").is_file()
    assert api.delete(f"/v1/jobs/{job_id}").status_code == 204
    assert api.get(f"/v1/jobs/{job_id}").status_code == 404
    assert not folder.exists()
    assert job_id not in {j["id"] for j in api.get("/v1/jobs", params={"limit": 500}).json()["jobs"]}
    assert api.delete(f"/v1/jobs/{job_id}").status_code == 404


def test_list_shows_only_the_callers_jobs(api: httpx.Client, stack: ServiceStack) -> None:
    mine = new_job(api)
    with client_for(stack, OTHER_KEY) as bob:
        theirs = bob.post("/v1/jobs", json={}).json()["id"]
        assert mine not in {j["id"] for j in bob.get("/v1/jobs", params={"limit": 500}).json()["jobs"]}
    listing = api.get("/v1/jobs", params={"limit": 500}).json()
    ids = [j["id"] for j in listing["jobs"]]
    assert mine in ids and theirs not in ids
    assert ids[0] == mine  # newest first
    page = api.get("/v1/jobs", params={"limit": 1, "offset": 1}).json()
    assert page["jobs"][0]["id"] == ids[1] and page["total"] == listing["total"]


def test_health_and_readiness(stack: ServiceStack) -> None:
    assert httpx.get(stack.url + "/healthz").json() == {"status": "ok"}
    assert httpx.get(stack.url + "/readyz").json() == {"status": "ok", "redis": True, "storage": True}


def test_unknown_route_and_method_are_json_errors(api: httpx.Client) -> None:
    r = api.get("/v1/nothing-here")
    assert r.status_code == 404 and r.json()["error"] == "not_found"
    r = api.patch("/v1/jobs")
    assert r.status_code == 405 and r.json()["error"] == "method_not_allowed"


def test_unknown_query_parameter_is_422(api: httpx.Client) -> None:
    r = api.get("/v1/jobs", params={"limit": 5, "colour": "red"})
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["query", "colour"]


def test_oversize_json_body_is_413(api: httpx.Client) -> None:
    r = api.post(
        "/v1/jobs", content=b"{" + b" " * (1 << 20) + b"}", headers={"Content-Type": "application/json"}
    )
    assert r.status_code == 413 and r.json()["error"] == "too_large"


def test_unknown_result_name_is_422(api: httpx.Client, done_job: dict) -> None:
    r = api.get(f"/v1/jobs/{done_job['id']}/result/notes.txt")
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["path", "name"]


def test_job_id_is_checked_before_the_store(api: httpx.Client) -> None:
    for bad in ("x:files", "0" * 31, "Z" * 32):
        r = api.get(f"/v1/jobs/{bad}")
        assert r.status_code == 404 and r.json()["error"] == "not_found"


def test_stage_this_build_lacks_is_refused_at_start(api: httpx.Client, small_capture: Path) -> None:
    from pmvir.stages import AVAILABLE_STAGES, STAGES

    missing = [s for s in STAGES if s not in AVAILABLE_STAGES]
    if not missing:
        pytest.skip("every stage is available")
    job_id = new_job(api, small_capture, options={"stop_after": missing[-1]})
    r = api.post(f"/v1/jobs/{job_id}/start")
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["options", "stop_after"]


def test_key_is_required_for_every_v1_route(stack: ServiceStack, done_job: dict) -> None:
    j = done_job["id"]
    routes = [
        ("GET", "/v1/jobs"),
        ("POST", "/v1/jobs"),
        ("GET", f"/v1/jobs/{j}"),
        ("POST", f"/v1/jobs/{j}/start"),
        ("POST", f"/v1/jobs/{j}/cancel"),
        ("DELETE", f"/v1/jobs/{j}"),
        ("GET", f"/v1/jobs/{j}/log"),
        ("PUT", f"/v1/jobs/{j}/files/capture.json"),
        ("GET", f"/v1/jobs/{j}/result/report.json"),
    ]
    for method, path in routes:
        r = httpx.request(method, stack.url + path)
        assert r.status_code == 401, (method, path)
        assert r.headers["www-authenticate"] == "Bearer" and r.json()["error"] == "unauthorized"
    assert (
        httpx.get(stack.url + f"/v1/jobs/{j}", headers={"Authorization": f"Bearer {KEY}x"}).status_code == 401
    )
    assert (
        httpx.get(stack.url + f"/v1/jobs/{j}", headers={"Authorization": f"Basic {KEY}"}).status_code == 401
    )
