"""pip install 'pmvir[client]' in a fresh venv: only httpx, pydantic and tqdm come, and the commands work.

The package is built once as a wheel, installed without dependencies into a new
virtual environment, and the client extra's dependencies installed by pip (from
the configured index). The venv must not have numpy, torch, Open3D, pycolmap or
OpenCV; its `pmvir` then submits a capture folder to the live service, lists,
reads, downloads, reruns and cancels, and a reconstruction command says which
extra it needs instead of a traceback.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tomllib
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.testing import ServiceStack

from svc_helpers import KEY

ROOT = Path(__file__).resolve().parents[2]
#: The environment of the venv's processes: without PYTHONPATH, which would show them this checkout.
CLEAN_ENV = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}


def _client_requirements() -> list[str]:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    return [*project["dependencies"], *project["optional-dependencies"]["client"]]


@pytest.fixture(scope="module")
def slim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A fresh venv with pmvir (no dependencies) plus the client extra's requirements; its bin folder."""
    tmp = tmp_path_factory.mktemp("slim")
    wheels = tmp / "wheels"

    def run(*argv: str | Path) -> None:
        argv_s = [str(a) for a in argv]
        done = subprocess.run(argv_s, capture_output=True, text=True, timeout=180, env=CLEAN_ENV, check=False)
        if done.returncode:
            pytest.fail(f"{' '.join(map(str, argv))} failed:\n{done.stdout[-2000:]}\n{done.stderr[-2000:]}")

    run(sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "-w", wheels, ROOT)
    run(sys.executable, "-m", "venv", tmp / "venv")
    pip = tmp / "venv" / "bin" / "pip"
    run(pip, "install", "-q", "--no-deps", next(wheels.glob("pmvir-*.whl")))
    run(pip, "install", "-q", *_client_requirements())
    yield tmp / "venv" / "bin"


def _pmvir(bin_dir: Path, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    done = subprocess.run(
        [str(bin_dir / "pmvir"), *args],
        capture_output=True,
        text=True,
        timeout=120,
        env=CLEAN_ENV,
        cwd=bin_dir.parent,
        check=False,
    )
    if check and done.returncode != 0:
        raise AssertionError(
            f"pmvir {' '.join(args)} exited {done.returncode}:\n{done.stdout}\n{done.stderr}"
        )
    return done


def test_client_extra_pulls_no_reconstruction_library(slim: Path) -> None:
    listed = subprocess.run(
        [str(slim / "pip"), "list", "--format=json"],
        capture_output=True,
        text=True,
        env=CLEAN_ENV,
        check=True,
    )
    names = {p["name"].lower() for p in json.loads(listed.stdout)}
    assert {"pmvir", "httpx", "pydantic", "tqdm"} <= names
    assert not names & {"numpy", "torch", "open3d", "pycolmap", "opencv-python-headless", "scipy", "fastapi"}


def test_reconstruction_commands_name_the_extra_to_install(slim: Path) -> None:
    done = _pmvir(slim, "reconstruct", "cap", "--out", "x", check=False)
    assert (
        done.returncode == 2 and "pip install 'pmvir[full]'" in done.stderr and "Traceback" not in done.stderr
    )
    done = _pmvir(slim, "serve", check=False)
    assert (
        done.returncode == 2
        and "pip install 'pmvir[service]'" in done.stderr
        and "Traceback" not in done.stderr
    )


def test_slim_client_drives_a_job_on_the_live_service(
    slim: Path, stack: ServiceStack, small_capture: Path, tmp_path: Path
) -> None:
    conn = ["--server", stack.url, "--api-key", KEY]
    out = tmp_path / "result"
    _pmvir(slim, "submit", str(small_capture), *conn, "--stop-after", "decode", "--out", str(out), "--quiet")
    assert (out / "report.json").is_file() and (out / "decoded").is_dir()
    jobs = json.loads(_pmvir(slim, "jobs", *conn, "--limit", "5").stdout)["jobs"]
    job_id = jobs[0]["id"]
    assert json.loads(_pmvir(slim, "status", job_id, *conn).stdout)["status"] == "succeeded"
    assert "capture valid; job queued" in _pmvir(slim, "log", job_id, *conn).stdout
    _pmvir(slim, "download", job_id, "report.json", *conn, "--out", str(tmp_path / "r.json"))
    assert json.loads((tmp_path / "r.json").read_text())["stages"] == ["decode"]
    rerun = json.loads(
        _pmvir(
            slim, "rerun", job_id, *conn, "--from", "decode", "--set", "decode.noise_floor=0.02", "--wait"
        ).stdout
    )
    assert rerun["status"] == "succeeded" and rerun["options"]["decode"]["noise_floor"] == 0.02
    created = json.loads(_pmvir(slim, "info", *conn).stdout)
    assert created["version"] and created["admin"] is False and created["workers_online"] is None
    done = _pmvir(slim, "cancel", job_id, *conn, check=False)
    assert done.returncode == 2 and "already succeeded" in done.stderr
