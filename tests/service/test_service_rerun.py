"""POST /v1/jobs/{id}/rerun: a new job on the same capture, reusing the earlier stages' cached outputs."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import httpx
import pytest

from pmvir.cli import main
from pmvir.synth import synthesize
from service.testing import ServiceStack

from svc_helpers import KEY, ONE_REFINE_STAGE, finished, new_job, wait_for


@pytest.fixture(scope="module")
def geometry_job(stack: ServiceStack, tmp_path_factory: pytest.TempPathFactory) -> dict:
    """A finished job that ran decode and geometry on a synthetic capture (known poses)."""
    capture = synthesize(
        tmp_path_factory.mktemp("rerun") / "cap", shape="blob", views=16, size=(256, 216), seed=3
    )
    shutil.rmtree(capture / "gt")  # over the shared stack's small file limit, and not needed
    with httpx.Client(base_url=stack.url, headers={"Authorization": f"Bearer {KEY}"}, timeout=60) as c:
        job_id = new_job(
            c, capture, {"stop_after": "geometry", "geometry": {"subdivision": {"max_area_px": 16.0}}}
        )
        assert c.post(f"/v1/jobs/{job_id}/start").status_code == 202
        job = wait_for(c, job_id, finished, timeout=240)
    assert job["status"] == "succeeded", job
    return job


@pytest.mark.slow
def test_rerun_from_refine_reuses_the_capture_and_skips_geometry(
    api: httpx.Client, geometry_job: dict, stack: ServiceStack, tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    code = main(
        [
            "rerun", geometry_job["id"], "--server", stack.url, "--api-key", KEY, "--from", "refine",
            "--set", "stop_after=refine", "--set", f"refine={json.dumps(ONE_REFINE_STAGE)}",
        ]
    )  # fmt: skip
    assert code == 0
    rerun = json.loads(capsys.readouterr().out)
    assert rerun["source_job"] == geometry_job["id"] and rerun["resume_from"] == "refine"
    assert rerun["status"] in ("queued", "running")  # no upload, no start: queued at once
    assert {f["sha256"] for f in rerun["files"]} == {f["sha256"] for f in geometry_job["files"]}
    assert rerun["options"]["geometry"]["subdivision"]["max_area_px"] == 16.0  # merged, nested, not replaced
    done = wait_for(api, rerun["id"], finished, timeout=240)
    assert done["status"] == "succeeded", done
    before, after = geometry_job["stage_timings"], done["stage_timings"]
    assert before["geometry"] > 1.0 and after["geometry"] < 0.2 * before["geometry"], (before, after)
    assert after["decode"] < max(0.5, before["decode"])
    assert {"mesh.ply", "illumination.json", "initial.ply"} <= set(done["results"])
    report = api.get(f"/v1/jobs/{done['id']}/result/report.json").json()
    assert report["resumed_from"] == "refine" and report["stages"] == ["decode", "geometry", "refine"]


@pytest.mark.slow
def test_rerun_after_changed_geometry_options_must_start_at_geometry(
    api: httpx.Client, geometry_job: dict
) -> None:
    r = api.post(
        f"/v1/jobs/{geometry_job['id']}/rerun",
        json={
            "options": {"stop_after": "refine", "geometry": {"subdivision": {"max_area_px": 32.0}}},
            "from_stage": "refine",
        },
    )
    assert r.status_code == 409 and "rerun from geometry" in r.json()["message"], r.text
    r = api.post(f"/v1/jobs/{geometry_job['id']}/rerun", json={"options": {"stop_after": "decode"}})
    assert r.status_code == 422 and r.json()["errors"][0]["loc"] == ["body", "from_stage"], r.text
    r = api.post(
        f"/v1/jobs/{geometry_job['id']}/rerun",
        json={"options": {"refine": {"solver": {"max_iterations": -1}}}},
    )
    assert r.status_code == 422 and r.json()["errors"][0]["loc"][:5] == [
        "body",
        "options",
        "refine",
        "solver",
        "max_iterations",
    ]


def test_rerun_of_an_unfinished_job_is_409(api: httpx.Client) -> None:
    job = new_job(api)
    r = api.post(f"/v1/jobs/{job}/rerun", json={"from_stage": "decode"})
    assert r.status_code == 409 and "created" in r.json()["message"], r.text
