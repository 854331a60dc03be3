"""Bare frames (no capture.json) through the real stack (Redis, API, Celery worker): a zip's
manifest is inferred at import, listed with the job's files, and the job runs to a mesh; ``pmvir
submit`` of a folder of frames sends the frames and the service infers the manifest. A zip whose
frames cannot give a manifest is a 422 naming the file.

The capture is 24 views of 320x256 of an object on a textured table, stripped to its frames, so SfM
estimates the poses and the focal length; the stack's zip and job limits are raised to hold it.
"""

from __future__ import annotations

import io
import json
import zipfile
from collections.abc import Iterator
from pathlib import Path

import httpx
import numpy as np
import pytest

from pmvir.capture import parse_manifest
from pmvir.cli import main
from pmvir.io.frames import write_frame
from pmvir.io.ply import read_mesh
from pmvir.synth import synthesize
from service.testing import ServiceStack, write_noise_capture

from svc_helpers import KEY, LIMITS, ONE_REFINE_STAGE, client_for, finished, require_redis, wait_for

MiB = 1024 * 1024


@pytest.fixture(scope="module")
def stack(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ServiceStack]:
    require_redis()
    env = {
        **LIMITS,
        "PMVIR_MAX_ZIP_BYTES": str(16 * MiB),
        "PMVIR_MAX_JOB_BYTES": str(32 * MiB),
        "PMVIR_MAX_FRAME_BYTES": str(1 * MiB),
        # the default lease: COLMAP's mapping can keep the heartbeat from running for seconds
        "PMVIR_LEASE_SECONDS": "30",
    }
    st = ServiceStack(tmp_path_factory.mktemp("stack"), api_keys=(KEY,), env=env)
    try:
        st.start()
        yield st
    finally:
        st.stop()


@pytest.fixture()
def api(stack: ServiceStack) -> Iterator[httpx.Client]:
    with client_for(stack) as c:
        yield c


def _zip_of(files: dict[str, bytes]) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, data in files.items():
            zf.writestr(name, data)
    return buf.getvalue()


def _post(api: httpx.Client, data: bytes, options: dict) -> httpx.Response:
    return api.post(
        "/v1/jobs",
        data={"options": json.dumps(options)},
        files={"capture": ("frames.zip", data, "application/zip")},
    )


def test_a_zip_of_frames_of_two_sizes_is_refused_naming_the_file(api: httpx.Client, tmp_path: Path) -> None:
    for name, width in (("a.png", 24), ("b.png", 28)):
        write_frame(tmp_path / name, np.zeros((16, width), np.uint16), bit_depth=12)
    r = _post(api, _zip_of({n: (tmp_path / n).read_bytes() for n in ("a.png", "b.png")}), {"stop_after": "decode"})
    assert r.status_code == 422, r.text
    body = r.json()
    assert body["errors"][0]["file"] == "b.png" and "differs from a.png's 24x16" in body["errors"][0]["msg"], body


def test_a_zip_without_frames_or_manifest_is_refused(api: httpx.Client) -> None:
    r = _post(api, _zip_of({"notes/readme.txt": b"nothing"}), {"stop_after": "decode"})
    assert r.status_code == 422 and r.json()["errors"][0]["file"] == "capture.json", r.text


def test_submit_sends_a_folder_of_frames_and_the_service_infers_the_manifest(
    stack: ServiceStack, tmp_path: Path
) -> None:
    capture = write_noise_capture(tmp_path / "cap", frames=3, seed=3)
    bare = tmp_path / "bare"
    bare.mkdir()
    for p in sorted((capture / "frames").iterdir()):
        (bare / p.name).write_bytes(p.read_bytes())
    out = tmp_path / "result"
    args = ["submit", str(bare), "--server", stack.url, "--api-key", KEY, "--out", str(out)]
    assert main([*args, "--stop-after", "decode", "--quiet", "--poll", "0.1"]) == 0
    used = parse_manifest((out / "capture.json").read_bytes())
    assert [f.file for f in used.frames] == [f"frames/{p.name}" for p in sorted(bare.iterdir())]
    assert json.loads((out / "report.json").read_text())["capture"]["manifest"] == "inferred"


@pytest.mark.slow
def test_a_zip_of_bare_frames_reconstructs_to_a_mesh(api: httpx.Client, tmp_path: Path) -> None:
    capture = synthesize(
        tmp_path / "cap", shape="blob", scene="table", views=24, size=(320, 256), material="plastic", seed=4
    )
    frames = {f"shots/{p.name}": p.read_bytes() for p in sorted((capture / "frames").iterdir())}
    options = {
        "geometry": {"subdivision": {"max_area_px": 16.0}},
        "refine": ONE_REFINE_STAGE,
        "export": {"face_budget": 3000, "texture_size": 256},
    }
    r = _post(api, _zip_of(frames), options)
    assert r.status_code == 201, r.text
    job = r.json()
    paths = {f["path"] for f in job["files"]}
    assert paths == {"capture.json"} | {f"frames/{n.split('/')[1]}" for n in frames}
    assert api.post(f"/v1/jobs/{job['id']}/start").status_code == 202
    done = wait_for(api, job["id"], finished, timeout=900, what="the job finishing")
    assert done["status"] == "succeeded", done
    assert {"mesh.ply", "capture.json", "report.json"} <= set(done["results"])
    manifest = parse_manifest(api.get(f"/v1/jobs/{job['id']}/result/capture.json").content)
    assert manifest.sensor.layout == "IMX250MYR" and manifest.sensor.bit_depth == 12 and len(manifest.frames) == 24
    report = api.get(f"/v1/jobs/{job['id']}/result/report.json").json()
    assert report["geometry"]["poses"]["mode"] == "sfm" and report["geometry"]["poses"]["registered_views"] >= 22
    r = api.get(f"/v1/jobs/{job['id']}/result/mesh.ply")
    assert r.status_code == 200
    (tmp_path / "mesh.ply").write_bytes(r.content)
    assert len(read_mesh(tmp_path / "mesh.ply").faces) > 100

