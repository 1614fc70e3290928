"""``Idempotency-Key`` on POSTs (IETF draft "The Idempotency-Key HTTP Header Field").

Same key + same request -> the stored response again (header ``Idempotent-Replayed: true``);
same key + a different request -> 422; same key while the first request is still being handled
-> 409. The request is compared by a fingerprint of its *content* (for multipart: the file
bytes and fields, not the random boundary). Only successful answers are stored; after an
error the key can be reused. Keys are kept for ``RETENTION``.
"""

from __future__ import annotations

import datetime as dt
import hashlib
import json
from collections.abc import Callable
from typing import Any

from fastapi import Response
from sqlalchemy import delete
from sqlalchemy.exc import IntegrityError

from service.api.problems import ProblemException, problem_responses
from service.storage import repository
from service.storage.db import Database
from service.storage.models import IdempotencyRecord, utcnow

RETENTION = dt.timedelta(hours=24)
STALE_PENDING = dt.timedelta(minutes=2)
MAX_KEY_LENGTH = 255
IDEMPOTENCY_PROBLEMS = problem_responses(400, 409, 422)
"""What a route taking ``Idempotency-Key`` can answer because of it (OpenAPI)."""


def fingerprint(*parts: Any) -> str:
    """SHA-256 over JSON-able parts and bytes, in order."""
    digest = hashlib.sha256()
    for part in parts:
        data = part if isinstance(part, bytes) else json.dumps(part, sort_keys=True).encode()
        digest.update(len(data).to_bytes(8, "big"))
        digest.update(data)
    return digest.hexdigest()


class Idempotency:
    """One POST's idempotency bookkeeping; inert when the request has no key."""

    def __init__(self, database: Database, tenant_id: str, key: str | None, scope: str) -> None:
        if key is not None and not (0 < len(key) <= MAX_KEY_LENGTH and key.isprintable()):
            raise ProblemException(
                400,
                f"Idempotency-Key must be 1-{MAX_KEY_LENGTH} printable characters; a UUID is "
                "a good choice",
                slug="invalid-idempotency-key",
            )
        self.database = database
        self.tenant_id = tenant_id
        self.key = key
        self.scope = scope
        self._claimed = False

    def run(
        self, request_fingerprint: Callable[[], str], produce: Callable[[], Response]
    ) -> Response:
        """Replay the stored answer, or call ``produce`` and store what it answers.

        ``request_fingerprint`` is only called when the request has a key (it may hash megabytes).
        """
        replay = self.begin(request_fingerprint)
        if replay is not None:
            return replay
        try:
            response = produce()
        except BaseException:
            self.abandon()
            raise
        return self.finish(response)

    def begin(self, request_fingerprint: Callable[[], str]) -> Response | None:
        """The stored response to replay, or None after reserving the key for this request."""
        if self.key is None:
            return None
        digest = fingerprint(self.scope, request_fingerprint())
        now = utcnow()
        with self.database.session() as session:
            session.execute(
                delete(IdempotencyRecord).where(
                    IdempotencyRecord.tenant_id == self.tenant_id,
                    IdempotencyRecord.created_at < now - RETENTION,
                )
            )
            record = repository.idempotency_record(session, self.tenant_id, self.key)
            if record is not None:
                if record.request_sha256 != digest:
                    raise ProblemException(
                        422,
                        f"Idempotency-Key {self.key!r} was already used for a different request "
                        f"({record.scope}); use a new key for a new request",
                        slug="idempotency-key-reused",
                    )
                if record.status_code:
                    return _replay(record)
                if now - record.created_at < STALE_PENDING:
                    raise ProblemException(
                        409,
                        f"a request with Idempotency-Key {self.key!r} is still being processed; "
                        "retry in a moment",
                        slug="idempotency-key-in-use",
                        headers={"Retry-After": "1"},
                    )
                session.delete(record)  # the first attempt died; this one takes over
                session.flush()
        try:
            with self.database.session() as session:
                session.add(
                    IdempotencyRecord(
                        tenant_id=self.tenant_id,
                        key=self.key,
                        scope=self.scope,
                        request_sha256=digest,
                        status_code=0,
                        body=b"",
                    )
                )
        except IntegrityError:  # a concurrent request with the same key won the race
            raise ProblemException(
                409,
                f"a request with Idempotency-Key {self.key!r} is still being processed; retry "
                "in a moment",
                slug="idempotency-key-in-use",
                headers={"Retry-After": "1"},
            ) from None
        self._claimed = True
        return None

    def finish(self, response: Response) -> Response:
        """Store a successful answer (or release the key after an error); returns it."""
        if not self._claimed:
            return response
        with self.database.session() as session:
            record = repository.idempotency_record(session, self.tenant_id, self.key or "")
            if record is None:
                return response
            if 200 <= response.status_code < 300:
                record.status_code = response.status_code
                record.body = bytes(response.body)
                record.location = response.headers.get("location")
            else:
                session.delete(record)
        self._claimed = False
        return response

    def abandon(self) -> None:
        """Release the key after an exception so the client may retry with it."""
        if not self._claimed:
            return
        with self.database.session() as session:
            repository.delete_idempotency_record(session, self.tenant_id, self.key or "")
        self._claimed = False


def _replay(record: IdempotencyRecord) -> Response:
    headers = {"Idempotent-Replayed": "true"}
    if record.location:
        headers["Location"] = record.location
    return Response(
        record.body,
        status_code=record.status_code,
        headers=headers,
        media_type="application/json",
    )
