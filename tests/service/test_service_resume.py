"""`pmvir submit --resume`: an interrupted submission continues with the same job and skips what is there."""

from __future__ import annotations

from pathlib import Path

import pytest

from pmvir.cli import main
from pmvir.client import PmvirClient, ServiceError
from service.testing import ServiceStack

from svc_helpers import KEY, client_for


def _submit(stack: ServiceStack, capture: Path, *extra: str) -> int:
    argv = ["submit", str(capture), "--server", stack.url, "--api-key", KEY, "--stop-after", "decode"]
    return main([*argv, "--quiet", "--retries", "0", "--parallel", "1", *extra])


def test_resume_uploads_only_the_missing_files_of_the_same_job(
    stack: ServiceStack,
    small_capture: Path,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture,
) -> None:
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    real_upload = PmvirClient.upload_file
    sent: list[str] = []

    def flaky(self: PmvirClient, job_id: str, path: str, local: Path, **kw: object) -> dict:
        if len(sent) == 3:  # the network goes away after three files
            raise ServiceError(503, {"error": "unavailable", "message": "connection lost"})
        sent.append(path)
        return real_upload(self, job_id, path, local, **kw)  # type: ignore[arg-type]

    monkeypatch.setattr(PmvirClient, "upload_file", flaky)
    assert _submit(stack, small_capture, "--out", str(tmp_path / "out")) == 2
    assert "resuming" not in capsys.readouterr().err and len(sent) == 3
    uploaded_first = list(sent)

    sent.clear()
    monkeypatch.setattr(
        PmvirClient, "upload_file", lambda self, *a, **kw: sent.append(a[1]) or real_upload(self, *a, **kw)
    )
    assert _submit(stack, small_capture, "--resume", "--out", str(tmp_path / "out")) == 0
    err = capsys.readouterr().err
    assert "resuming job" in err
    total = 1 + 2 * 4  # capture.json, 4 frames, 4 masks
    assert len(sent) == total - 3 and not set(sent) & set(uploaded_first)
    job_id = err.split("resuming job ")[1].split()[0]
    with client_for(stack) as c:
        job = c.get(f"/v1/jobs/{job_id}").json()
    assert job["status"] == "succeeded" and len(job["files"]) == total
    assert (tmp_path / "out" / "report.json").is_file()
    assert not list((tmp_path / "cache").rglob("*.json"))  # the finished submission's state is gone
