"""The committed OpenAPI document is the app's: regenerate with ``python -m service.openapi --write``."""

from __future__ import annotations

import json

import httpx

from service.openapi import DOCUMENT, generate, render
from service.testing import ServiceStack


def test_committed_openapi_document_matches_the_app() -> None:
    assert DOCUMENT.is_file(), f"{DOCUMENT} is missing: run python -m service.openapi --write"
    committed = DOCUMENT.read_text()
    assert committed == render(generate()), (
        f"{DOCUMENT} drifted from the app (routes, models or pmvir.config changed): "
        "run python -m service.openapi --write and commit it"
    )


def test_served_document_is_the_committed_one(stack: ServiceStack) -> None:
    served = httpx.get(stack.url + "/openapi.json").json()
    assert served == json.loads(DOCUMENT.read_text())


def test_document_describes_the_api() -> None:
    doc = json.loads(DOCUMENT.read_text())
    assert doc["openapi"].startswith("3.")
    paths = doc["paths"]
    assert set(paths) >= {
        "/v1/jobs",
        "/v1/jobs/{job_id}",
        "/v1/jobs/{job_id}/start",
        "/v1/jobs/{job_id}/cancel",
        "/v1/jobs/{job_id}/log",
        "/v1/jobs/{job_id}/files/{path}",
        "/v1/jobs/{job_id}/result/{name}",
        "/healthz",
        "/readyz",
    }
    create = paths["/v1/jobs"]["post"]
    assert set(create["requestBody"]["content"]) == {"application/json", "multipart/form-data"}
    # the job options are the pipeline's own typed configuration
    options = doc["components"]["schemas"]["JobCreate"]["properties"]["options"]
    assert options["$ref"] == "#/components/schemas/PipelineConfig"
    assert doc["components"]["schemas"]["PipelineConfig"]["additionalProperties"] is False
    assert doc["components"]["securitySchemes"]["HTTPBearer"]["scheme"] == "bearer"
    for path, ops in paths.items():
        for method, op in ops.items():
            errors = [c for c in op["responses"] if c.startswith(("4", "5"))]
            for code in errors:
                if code == "503" and path == "/readyz":
                    continue
                schema = op["responses"][code]["content"]["application/json"]["schema"]
                assert schema == {"$ref": "#/components/schemas/ErrorBody"}, (method, path, code)
