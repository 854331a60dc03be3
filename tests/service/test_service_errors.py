"""Library errors reaching the service become 4xx answers that carry their message."""

from __future__ import annotations

import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient

from pmvir.errors import ConfigError, DTypeError, InputError, PmvirError, ShapeError
from service.errors import install_error_handlers


def _app_raising(exc: Exception) -> TestClient:
    app = FastAPI()
    install_error_handlers(app)

    @app.get("/boom")
    def boom() -> None:
        raise exc

    return TestClient(app, raise_server_exceptions=False)


@pytest.mark.parametrize(
    "exc",
    [
        ShapeError("expected (..., 3) normals, got (2, 2)"),
        DTypeError("expected a float32 mosaic, got float64"),
        InputError("vertices contain NaN or infinity"),
    ],
    ids=lambda e: type(e).__name__,
)
def test_input_errors_are_422_with_their_message(exc: PmvirError) -> None:
    r = _app_raising(exc).get("/boom")
    assert r.status_code == 422
    assert r.json() == {"error": type(exc).__name__, "message": str(exc), "errors": []}


def test_config_error_is_a_422_config_error() -> None:
    r = _app_raising(ConfigError("scale must lie in (0, 1], got 2.0")).get("/boom")
    assert r.status_code == 422
    assert r.json()["error"] == "config_error" and r.json()["message"] == "scale must lie in (0, 1], got 2.0"


def test_a_bare_value_error_stays_an_internal_error() -> None:
    """Only the library's own errors are the caller's fault; anything else is a 500 without details."""
    r = _app_raising(ValueError("secret detail")).get("/boom")
    assert r.status_code == 500 and "secret" not in r.text
