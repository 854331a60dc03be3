"""API keys: ``Authorization: Bearer <key>``, compared in constant time.

A key's jobs belong to its *owner id*, a digest of the key, so the key itself
is never stored; a job of another owner is answered 404, like a job that does
not exist.
"""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.errors import ApiError

bearer = HTTPBearer(auto_error=False, description="An API key from PMVIR_API_KEYS.")


def owner_for_key(presented: str, key_owners: tuple[tuple[bytes, str], ...]) -> str | None:
    """The owner id of ``presented``, or None. Every configured key is compared (constant time each)."""
    candidate = presented.encode()
    found = None
    for key, owner in key_owners:
        if hmac.compare_digest(candidate, key):
            found = owner
    return found


def _unauthorized(message: str) -> ApiError:
    return ApiError(401, "unauthorized", message, headers={"WWW-Authenticate": "Bearer"})


def require_owner(
    request: Request, creds: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> str:
    """FastAPI dependency: the caller's owner id, or 401."""
    if creds is None or creds.scheme.lower() != "bearer" or not creds.credentials:
        raise _unauthorized("missing API key: send Authorization: Bearer <key>")
    owner = owner_for_key(creds.credentials, request.app.state.settings.key_owners)
    if owner is None:
        raise _unauthorized("invalid API key")
    return owner
