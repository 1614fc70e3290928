"""API keys and tenants.

A key looks like ``kc_<key id>_<secret>``: the id (12 hex characters) is public and indexes the
row, the secret has 256 random bits. Only the SHA-256 of the whole key is stored; a presented key
is hashed and compared in constant time. A fast hash is right here: the secret is random, not a
password, so there is nothing to brute-force.

Every dataset, robot and job belongs to the tenant of the key that created it. In keyless mode
(service bound to a loopback address) requests without a key act as tenant ``local``.
"""

from __future__ import annotations

import hashlib
import hmac
import re
import secrets
import threading
import time
from dataclasses import dataclass

from service.settings import load_settings
from service.storage import repository
from service.storage.db import Database
from service.storage.models import ApiKey, Tenant, utcnow
from solver.errors import KincalError

KEY_PREFIX = "kc"
TENANT_NAME = re.compile(r"^[a-z0-9][a-z0-9_.-]{0,63}$")
_KEY_FORMAT = re.compile(r"^kc_([0-9a-f]{12})_([A-Za-z0-9_-]{43})$")


@dataclass(frozen=True)
class Principal:
    """Who is calling: a tenant, and the key used (None in keyless mode)."""

    tenant_id: str
    tenant_name: str
    key_id: str | None


def hash_api_key(key: str) -> str:
    return hashlib.sha256(key.encode()).hexdigest()


def generate_api_key() -> tuple[str, str]:
    """(key id, full key). The full key is shown once and never stored."""
    key_id = secrets.token_hex(6)
    return key_id, f"{KEY_PREFIX}_{key_id}_{secrets.token_urlsafe(32)}"


def check_tenant_name(name: str) -> str:
    if not TENANT_NAME.match(name):
        raise KincalError(
            f"tenant name {name!r} is not allowed; use 1-64 lower-case letters, digits, '.', "
            "'_' or '-', starting with a letter or digit"
        )
    return name


def create_api_key(database: Database, tenant_name: str) -> tuple[str, str]:
    """Create a key for ``tenant_name`` (the tenant too if new); returns (key id, full key)."""
    check_tenant_name(tenant_name)
    key_id, key = generate_api_key()
    with database.session() as session:
        tenant = repository.ensure_tenant(session, tenant_name)
        session.add(ApiKey(id=key_id, tenant_id=tenant.id, key_sha256=hash_api_key(key)))
    return key_id, key


def revoke_api_key(database: Database, key_id: str) -> bool:
    with database.session() as session:
        row = repository.api_key(session, key_id)
        if row is None or row.revoked_at is not None:
            return False
        row.revoked_at = utcnow()
    return True


class KeyVerifier:
    """Checks presented keys; a verified key is trusted for ``cache_s`` without a DB query.

    The cache keeps the per-request cost of authentication at one dict lookup and one SHA-256,
    so hot paths (rankings) do not touch the database for it.
    """

    def __init__(self, database: Database, cache_s: float) -> None:
        self._database = database
        self._cache_s = cache_s
        self._cache: dict[str, tuple[str, Principal, float]] = {}
        self._lock = threading.Lock()

    def verify_cached(self, presented: str) -> Principal | None:
        """The key's principal if it was verified recently (no database access), else None."""
        match = _KEY_FORMAT.match(presented)
        if match is None:
            return None
        with self._lock:
            cached = self._cache.get(match.group(1))
        if cached is None or cached[2] < time.monotonic():
            return None
        return self._check(presented, cached)

    def verify(self, presented: str) -> Principal | None:
        """The key's principal, or None for a malformed, unknown, revoked or wrong key."""
        match = _KEY_FORMAT.match(presented)
        if match is None:
            return None
        key_id = match.group(1)
        now = time.monotonic()
        with self._lock:
            cached = self._cache.get(key_id)
        if cached is None or cached[2] < now:
            cached = self._load(key_id, now)
            if cached is None:
                return None
        return self._check(presented, cached)

    @staticmethod
    def _check(presented: str, entry: tuple[str, Principal, float]) -> Principal | None:
        stored_digest, principal, _ = entry
        return principal if hmac.compare_digest(hash_api_key(presented), stored_digest) else None

    def _load(self, key_id: str, now: float) -> tuple[str, Principal, float] | None:
        with self._database.session() as session:
            row = repository.api_key(session, key_id)
            if row is None or row.revoked_at is not None:
                with self._lock:
                    self._cache.pop(key_id, None)
                return None
            tenant = session.get(Tenant, row.tenant_id)
            assert tenant is not None
            entry = (row.key_sha256, Principal(tenant.id, tenant.name, key_id), now + self._cache_s)
        with self._lock:
            self._cache[key_id] = entry
        return entry


def create_key(tenant: str) -> tuple[str, str]:
    """Migrate the configured database if needed, then create a key: (key id, full key)."""
    database = Database(load_settings().resolved_database_url)
    try:
        database.migrate()
        return create_api_key(database, tenant)
    finally:
        database.dispose()


def revoke_key(key_id: str) -> bool:
    database = Database(load_settings().resolved_database_url)
    try:
        database.migrate()
        return revoke_api_key(database, key_id)
    finally:
        database.dispose()
