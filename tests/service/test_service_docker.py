"""The docker files wire the parts as documented (static checks: no Docker daemon needed)."""

from __future__ import annotations

from pathlib import Path

import pytest

yaml = pytest.importorskip("yaml")

DOCKER = Path(__file__).resolve().parents[2] / "docker"


def test_compose_runs_api_worker_and_redis_sharing_the_storage_volume() -> None:
    doc = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    services = doc["services"]
    assert set(services) == {"api", "worker", "redis", "minio", "minio-bucket"}
    assert services["minio"]["profiles"] == ["s3"] and services["minio-bucket"]["profiles"] == ["s3"]
    api, worker = services["api"], services["worker"]
    assert api["command"][:2] == ["pmvir", "serve"] and worker["command"][:2] == ["pmvir", "worker"]
    assert "storage:/data" in api["volumes"] and "storage:/data" in worker["volumes"]
    for svc in (api, worker):
        env = svc["environment"]
        assert env["PMVIR_STORAGE"] == "/data"
        assert env["PMVIR_REDIS_URL"].startswith("redis://redis:")
        assert {"PMVIR_STORAGE_URL", "PMVIR_S3_ENDPOINT_URL", "AWS_ACCESS_KEY_ID"} <= set(env)
        assert svc["depends_on"]["redis"]["condition"] == "service_healthy"
    assert "PMVIR_API_KEYS" in api["environment"] and "PMVIR_API_KEYS" not in worker["environment"]
    assert api["build"]["dockerfile"] == "docker/Dockerfile"
    assert set(doc["volumes"]) == {"storage", "redis-data", "minio-data"}


def test_dockerfile_installs_the_service_and_runs_unprivileged() -> None:
    text = (DOCKER / "Dockerfile").read_text()
    assert "ARG BASE_IMAGE=" in text and "FROM ${BASE_IMAGE}" in text
    assert (
        "-r /tmp/requirements.lock" in text
        and "--extra-index-url" in text
        and 'pip install --no-deps ".[full,service]"' in text
    )
    assert "USER pmvir" in text and "ENV PMVIR_STORAGE=/data" in text
    assert 'CMD ["pmvir", "serve", "--host", "0.0.0.0", "--port", "8000"]' in text
    ignore = [
        ln.strip()
        for ln in (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
        if ln.strip() and not ln.startswith("#")
    ]
    assert ignore[0] == "*" and "!pmvir/" in ignore and "!service/" in ignore
    assert "!docker/requirements.lock" in ignore


def test_lock_file_pins_every_declared_dependency_of_the_image() -> None:
    lock = {
        ln.split("==")[0]: ln.split("==")[1]
        for ln in (DOCKER / "requirements.lock").read_text().splitlines()
        if ln and not ln.startswith("#")
    }
    for name in (
        "torch",
        "fastapi",
        "starlette",
        "python-multipart",
        "pycolmap",
        "pydantic-settings",
        "httpx",
    ):
        assert name in lock, name
    assert all(v[0].isdigit() and "+" not in v for v in lock.values())
