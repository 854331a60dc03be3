"""Helpers of the console tests and of ``bench/console.py``: a finished job on a live stack, headless Chromium.

Chromium is Debian's (``/usr/bin/chromium``, installed by ``make setup``), driven
by Playwright for Python; ``playwright install`` is never needed.
"""

from __future__ import annotations

import io
import json
import shutil
import time
import zipfile
from pathlib import Path

import httpx

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--use-angle=swiftshader",
    "--enable-unsafe-swiftshader",
]
#: A run that takes seconds on 2 cores: coarse subdivision, one refinement stage of 4 iterations, a
#: small textured export.
TINY_OPTIONS = {
    "geometry": {"subdivision": {"max_area_px": 16.0}},
    "refine": {
        "solver": {"max_iterations": 4},
        "stages": {"tau_pol": [60.0], "tau_gsm": [0.1], "tau_psm": [2.0], "gsm_exponent": [2.2]},
    },
    "export": {"face_budget": 3000, "texture_size": 256},
}


def chromium_missing() -> str | None:
    """Why the browser tests cannot run here, or None."""
    if not Path(CHROMIUM).exists():
        return f"{CHROMIUM} is missing (make setup installs Debian's chromium)"
    try:
        import playwright  # noqa: F401
    except ImportError:
        return "the playwright Python package is missing (make setup installs it)"
    return None


def tiny_capture_zip(
    root: Path, *, views: int = 16, size: tuple[int, int] = (200, 168), seed: int = 3
) -> bytes:
    """A synthetic plastic capture (built-in blob, with its ground-truth mesh and lighting) zipped in memory."""
    from pmvir.synth import synthesize

    capture = synthesize(
        root / "capture", shape="blob", views=views, size=size, material="plastic", seed=seed
    )
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for p in sorted(capture.rglob("*")):
            rel = p.relative_to(capture).as_posix()
            if p.is_file() and (not rel.startswith("gt/") or rel in ("gt/mesh.ply", "gt/illumination.json")):
                zf.write(p, rel)
    shutil.rmtree(capture)
    return buf.getvalue()


def finished_job(
    url: str, key: str, zipped: bytes, *, options: dict, label: str, timeout: float = 300.0
) -> dict:
    """Create a job from a zipped capture over HTTP, start it and wait until it succeeded; returns the job."""
    headers = {"Authorization": f"Bearer {key}"}
    with httpx.Client(base_url=url, headers=headers, timeout=60) as c:
        r = c.post(
            "/v1/jobs",
            files={"capture": ("capture.zip", zipped, "application/zip")},
            data={"options": json.dumps(options), "label": label},
        )
        if r.status_code != 201:
            raise RuntimeError(f"POST /v1/jobs answered {r.status_code}: {r.text}")
        job_id = r.json()["id"]
        r = c.post(f"/v1/jobs/{job_id}/start")
        if r.status_code != 202:
            raise RuntimeError(f"POST /v1/jobs/{job_id}/start answered {r.status_code}: {r.text}")
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            job = c.get(f"/v1/jobs/{job_id}").json()
            if job["status"] in ("succeeded", "failed", "canceled"):
                if job["status"] != "succeeded":
                    raise RuntimeError(f"job {job_id} {job['status']}: {job['error']}")
                return job
            time.sleep(0.5)
    raise TimeoutError(f"job {job_id} did not finish in {timeout} s")
