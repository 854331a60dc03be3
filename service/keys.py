"""API keys as the API holds them: scrypt hashes, several per tenant.

An entry of ``PMVIR_API_KEYS`` (or ``PMVIR_ADMIN_KEYS``) is either

* ``<tenant>=scrypt:<salt hex>:<hash hex>``: the key's scrypt hash (n=2^14, r=8,
  p=1, 32 bytes), made by ``python -m service.keys <tenant>`` (the key is read
  from stdin). The jobs belong to the tenant, so a tenant's several keys see the
  same jobs and a key can be rotated without orphaning them; or
* a plain key (``key1``): its own tenant, named by a digest of the key.

A presented key is checked against every entry once; the answer is kept in a
small in-process table under the key's SHA-256, so scrypt runs once per key and
process, not once per request. Workers need no keys.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import sys
from dataclasses import dataclass
from threading import Lock

_N, _R, _P, _LEN = 2**14, 8, 1, 32
_TENANT = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_HASHED = re.compile(r"^(?P<tenant>[^=]+)=scrypt:(?P<salt>[0-9a-f]{16,64}):(?P<hash>[0-9a-f]{64})$")
_CACHE_SIZE = 4096


@dataclass(frozen=True)
class KeyEntry:
    """One configured key: its tenant (the owner of its jobs), and how to recognise it."""

    tenant: str
    salt: bytes = b""
    digest: bytes = b""
    plain: bytes = b""

    def matches(self, presented: bytes) -> bool:
        if self.plain:
            return hmac.compare_digest(presented, self.plain)
        return hmac.compare_digest(scrypt(presented, self.salt), self.digest)


def scrypt(key: bytes, salt: bytes) -> bytes:
    return hashlib.scrypt(key, salt=salt, n=_N, r=_R, p=_P, dklen=_LEN, maxmem=64 * 1024 * 1024)


def plain_tenant(key: str) -> str:
    """The tenant of a plain (unhashed) key: a digest of it, never the key itself."""
    return hashlib.sha256(key.encode()).hexdigest()[:24]


def parse_entry(entry: str) -> KeyEntry:
    """A ``PMVIR_API_KEYS`` entry.

    >>> parse_entry("lab-a=scrypt:" + "00" * 16 + ":" + "ab" * 32).tenant
    'lab-a'

    Raises:
        ValueError: a hashed entry whose tenant is not 1-64 of ``A-Z a-z 0-9 _ . -``.
    """
    m = _HASHED.match(entry)
    if m is None:
        return KeyEntry(tenant=plain_tenant(entry), plain=entry.encode())
    if not _TENANT.match(m["tenant"]):
        raise ValueError(f"API key entry: tenant {m['tenant']!r} is not 1-64 of A-Z a-z 0-9 _ . -")
    return KeyEntry(tenant=m["tenant"], salt=bytes.fromhex(m["salt"]), digest=bytes.fromhex(m["hash"]))


def hash_entry(tenant: str, key: str) -> str:
    """The ``PMVIR_API_KEYS`` entry of ``key`` for ``tenant`` (a fresh salt each time)."""
    if not _TENANT.match(tenant):
        raise ValueError(f"tenant {tenant!r} is not 1-64 of A-Z a-z 0-9 _ . -")
    salt = secrets.token_bytes(16)
    return f"{tenant}=scrypt:{salt.hex()}:{scrypt(key.encode(), salt).hex()}"


class KeyRing:
    """The configured keys; :meth:`tenant` answers which tenant a presented key belongs to."""

    def __init__(self, entries: tuple[str, ...], admin_entries: tuple[str, ...] = ()):
        self.entries = [parse_entry(e) for e in dict.fromkeys((*entries, *admin_entries))]
        self.admins = frozenset(parse_entry(e).tenant for e in admin_entries)
        self._seen: dict[bytes, str | None] = {}
        self._lock = Lock()

    def tenant(self, presented: str) -> str | None:
        """The tenant of ``presented``, or None. Every entry is compared (constant time each)."""
        candidate = presented.encode()
        cache_key = hashlib.sha256(candidate).digest()
        with self._lock:
            if cache_key in self._seen:
                return self._seen[cache_key]
        found = None
        for entry in self.entries:
            if entry.matches(candidate):
                found = entry.tenant
        with self._lock:
            if len(self._seen) >= _CACHE_SIZE:
                self._seen.clear()
            self._seen[cache_key] = found
        return found


def main(argv: list[str] | None = None) -> int:
    """``python -m service.keys TENANT``: read a key from stdin, print its PMVIR_API_KEYS entry."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        sys.stderr.write("usage: python -m service.keys TENANT < key\n")
        return 2
    key = sys.stdin.readline().strip()
    if len(key) < 16:
        sys.stderr.write("the key must be at least 16 characters\n")
        return 2
    sys.stdout.write(hash_entry(args[0], key) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
