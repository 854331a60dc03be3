"""API keys: ``Authorization: Bearer <key>``, checked against their scrypt hashes (:mod:`service.keys`).

A key's jobs belong to its tenant (the *owner id*): the name its hashed entry
gives, or a digest of a plain key, so the key itself is never stored; a job of
another owner is answered 404, like a job that does not exist.
"""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.errors import ApiError

bearer = HTTPBearer(auto_error=False, description="An API key from PMVIR_API_KEYS.")


def _unauthorized(message: str) -> ApiError:
    return ApiError(401, "unauthorized", message, headers={"WWW-Authenticate": "Bearer"})


def require_owner(
    request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> str:
    """FastAPI dependency: the caller's owner id, or 401."""
    if creds is None or creds.scheme.lower() != "bearer" or not creds.credentials:
        raise _unauthorized("missing API key: send Authorization: Bearer <key>")
    owner = request.app.state.settings.keyring.tenant(creds.credentials)
    if owner is None:
        raise _unauthorized("invalid API key")
    return owner
