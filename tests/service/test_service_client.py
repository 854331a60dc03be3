"""The Python client (pmvir.client) and `pmvir submit` against the live service."""

from __future__ import annotations

import hashlib
import json
import zipfile
from pathlib import Path

import numpy as np
import pytest

from pmvir.cli import main
from pmvir.client import PmvirClient, ServiceError
from service.testing import ServiceStack, write_noise_capture

from svc_helpers import KEY, client_for, finished, new_job, wait_for


def sha(p: Path) -> str:
    return hashlib.sha256(p.read_bytes()).hexdigest()


def test_submit_runs_a_capture_folder_end_to_end(
    stack: ServiceStack, small_capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    out = tmp_path / "result"
    code = main(
        [
            "submit",
            str(small_capture),
            "--server",
            stack.url,
            "--api-key",
            KEY,
            "--out",
            str(out),
            "--stop-after",
            "decode",
            "--set",
            "decode.noise_floor=0.02",
            "--quiet",
            "--poll",
            "0.1",
        ]
    )
    assert code == 0
    assert capsys.readouterr().out.strip() == str(out)
    report = json.loads((out / "report.json").read_text())
    assert report["stages"] == ["decode"] and report["parameters"]["decode"]["noise_floor"] == 0.02
    assert np.load(out / "decoded" / "003.npz")["valid"].shape == (48, 64)
    with zipfile.ZipFile(out / "result.zip") as zf:
        assert zf.testzip() is None


def test_submit_sends_a_small_zip_in_one_request(
    stack: ServiceStack, small_capture: Path, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    zpath = tmp_path / "cap.zip"
    with zipfile.ZipFile(zpath, "w") as zf:
        for p in small_capture.rglob("*"):
            if p.is_file():
                zf.write(p, p.relative_to(small_capture).as_posix())
    code = main(
        [
            "submit",
            str(zpath),
            "--server",
            stack.url,
            "--api-key",
            KEY,
            "--stop-after",
            "decode",
            "--quiet",
            "--poll",
            "0.1",
            "--label",
            "from-zip",
        ]
    )
    assert code == 0
    assert (tmp_path / "cap-result" / "report.json").is_file()
    with client_for(stack) as c:
        job = c.get("/v1/jobs").json()["jobs"][0]
        assert job["label"] == "from-zip" and job["status"] == "succeeded"
        log = [ln["message"] for ln in c.get(f"/v1/jobs/{job['id']}/log").json()["lines"]]
        assert any("zipped capture imported" in m for m in log)


def test_submit_no_wait_prints_the_job_id(
    stack: ServiceStack, small_capture: Path, capsys: pytest.CaptureFixture
) -> None:
    code = main(
        [
            "submit",
            str(small_capture),
            "--server",
            stack.url,
            "--api-key",
            KEY,
            "--stop-after",
            "decode",
            "--quiet",
            "--no-wait",
        ]
    )
    assert code == 0
    job_id = capsys.readouterr().out.strip()
    with client_for(stack) as c:
        assert wait_for(c, job_id, finished, timeout=60)["status"] == "succeeded"


def test_submit_with_bad_options_fails_before_contacting_the_server(
    small_capture: Path, capsys: pytest.CaptureFixture
) -> None:
    code = main(
        [
            "submit",
            str(small_capture),
            "--server",
            "http://127.0.0.1:9",
            "--api-key",
            "k",
            "--set",
            "decode.noise_floor=7",
        ]
    )
    assert code == 2 and "decode.noise_floor" in capsys.readouterr().err


def test_submit_with_an_invalid_capture_is_refused_locally(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    cap = write_noise_capture(tmp_path / "cap", frames=2)
    (cap / "frames" / "001.png").unlink()
    code = main(["submit", str(cap), "--server", "http://127.0.0.1:9", "--api-key", "k"])
    assert code == 2 and "frames/001.png" in capsys.readouterr().err


def test_submit_without_a_key_is_refused(
    small_capture: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture
) -> None:
    monkeypatch.delenv("PMVIR_API_KEY", raising=False)
    assert main(["submit", str(small_capture), "--server", "http://127.0.0.1:9"]) == 2
    assert "API key" in capsys.readouterr().err


def test_submit_reports_a_failed_start(
    stack: ServiceStack, small_capture: Path, capsys: pytest.CaptureFixture
) -> None:
    code = main(
        [
            "submit",
            str(small_capture),
            "--server",
            stack.url,
            "--api-key",
            "wrong",
            "--quiet",
            "--retries",
            "0",
        ]
    )
    assert code == 2 and "401" in capsys.readouterr().err


def test_client_uploads_in_resumable_parts_and_resumes_a_partial(stack: ServiceStack, tmp_path: Path) -> None:
    data = np.random.default_rng(5).integers(0, 256, 10_000, dtype=np.uint8).tobytes()
    local = tmp_path / "000.raw"
    local.write_bytes(data)
    with PmvirClient(stack.url, KEY, chunk_size=3000) as client:
        job = client.create_job({"stop_after": "decode"})
        sent: list[int] = []
        out = client.upload_file(job["id"], "frames/000.raw", local, on_bytes=sent.append)
        assert out["sha256"] == sha(local) and sum(sent) == len(data) and len(sent) >= 4
        # an interrupted upload: the server holds 4000 bytes; the client sends only the rest
        with client_for(stack) as c:
            r = c.put(
                f"/v1/jobs/{job['id']}/files/frames/001.raw",
                content=data[:4000],
                headers={"Content-Range": "bytes 0-3999/10000"},
            )
            assert r.status_code == 202
        sent.clear()
        out = client.upload_file(job["id"], "frames/001.raw", local, on_bytes=sent.append)
        assert out["sha256"] == sha(local)
        assert sent == [4000, 3000, 3000]  # the 4000 bytes on the server are counted, not sent again
        assert client.job(job["id"])["partial_uploads"] == []


def test_client_resumes_a_partial_download(stack: ServiceStack, small_capture: Path, tmp_path: Path) -> None:
    with client_for(stack) as c:
        job_id = new_job(c, small_capture)
        c.post(f"/v1/jobs/{job_id}/start")
        wait_for(c, job_id, finished, timeout=60)
        full = c.get(f"/v1/jobs/{job_id}/result/result.zip").content
    dest = tmp_path / "r.zip"
    dest.with_name("r.zip.part").write_bytes(full[:1000])
    got: list[int] = []
    with PmvirClient(stack.url, KEY) as client:
        client.download(job_id, "result.zip", dest, on_bytes=got.append)
    assert dest.read_bytes() == full and sum(got) == len(full) - 1000
    assert not dest.with_name("r.zip.part").exists()


def test_client_create_is_idempotent_and_errors_carry_the_body(stack: ServiceStack) -> None:
    with PmvirClient(stack.url, KEY) as client:
        a = client.create_job({"stop_after": "decode"}, idempotency_key="same")
        b = client.create_job({"stop_after": "decode"}, idempotency_key="same")
        assert a["id"] == b["id"]
        with pytest.raises(ServiceError) as err:
            client.create_job({"decode": {"noise_floor": 2}})
        assert err.value.status == 422 and err.value.code == "validation_error"
        assert "options.decode.noise_floor" in str(err.value)
        with pytest.raises(ServiceError) as missing:
            client.job("0" * 32)
        assert missing.value.status == 404
        client.delete(a["id"])
        client.delete(a["id"])  # a retried delete finds it gone: no error


def test_client_uploads_a_whole_capture_and_starts_it(stack: ServiceStack, small_capture: Path) -> None:
    with PmvirClient(stack.url, KEY) as client:
        job = client.create_job({"stop_after": "decode"})
        answers = client.upload_capture(job["id"], small_capture)
        assert {a["path"] for a in answers} == {
            p.relative_to(small_capture).as_posix() for p in small_capture.rglob("*") if p.is_file()
        }
        assert client.start(job["id"])["status"] in ("queued", "running", "succeeded")  # validated first
        assert client.start(job["id"])["status"] in ("queued", "running", "succeeded")  # a retried start
        assert client.wait(job["id"], poll=0.1, timeout=60)["status"] == "succeeded"
