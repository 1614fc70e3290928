"""``POST /api/v1/rankings`` for the planners' common case without FastAPI's routing, dependency
injection and response classes (issue 29).

A 100-candidate ranking is ~0.5 ms of numpy; through the framework (matching the path against
every route, solving the dependency graph of state, API key and body, building the response) the
request cost about as much again. :class:`RankingFastPath` is a pure ASGI layer inside
:class:`~service.api.middleware.RequestContextMiddleware` (request id, body limit, metrics and the
access-log line are unchanged) that answers the common case with the route's own functions:

* a JSON body with a declared length of at most ``INLINE_PARSE_BYTES``;
* a key verified in the last ``api_key_cache_s`` (no database), or keyless mode;
* a calibration whose ranking context is cached (no database, no file);
* rows or named configurations, at most ``INLINE_MAX_CONFIGURATIONS``.

Every other request, and every request the route would answer with a problem, goes on to the
route with its body replayed: the fast path only ever answers 200 with the bytes the route would
send, so each error keeps the route's status, message and headers.
"""

from __future__ import annotations

from collections.abc import Iterable

import pydantic
from starlette.routing import BaseRoute
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from schemas.api import RankingCreate
from service.api import rankings
from service.api.deps import ServiceState
from service.security import Principal

_JSON = b"application/json"


class RankingFastPath:
    def __init__(self, app: ASGIApp, *, state: ServiceState, route: BaseRoute) -> None:
        self.app = app
        self.state = state
        self.route = route
        self.answered = 0
        """Requests answered here rather than by the route."""

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        length = _declared_length(scope) if _is_ranking(scope) else None
        if length is None or length > rankings.INLINE_PARSE_BYTES:
            await self.app(scope, receive, send)
            return
        received = [await receive()]
        while received[-1]["type"] == "http.request" and received[-1].get("more_body", False):
            received.append(await receive())
        content = None
        if received[-1]["type"] == "http.request":
            body = b"".join(message.get("body", b"") for message in received)
            content = self.answer(scope, body)
        if content is None:
            await self.app(scope, _replay(received, receive), send)
            return
        self.answered += 1
        scope["route"] = self.route  # as the router sets it: the metrics' route label
        headers = [(b"content-length", str(len(content)).encode()), (b"content-type", _JSON)]
        await send({"type": "http.response.start", "status": 200, "headers": headers})
        await send({"type": "http.response.body", "body": content})

    def answer(self, scope: Scope, body: bytes) -> bytes | None:
        """The route's 200 answer to this request, or None if it is not the common case or
        the route would answer with a problem (a body parsed here is left in the scope's
        state for the route)."""
        headers = scope["headers"]
        key, media = _first(headers, b"x-api-key"), _first(headers, b"content-type")
        if media not in (None, _JSON):
            return None
        principal = self._principal(key)
        if principal is None:
            return None
        try:
            request = RankingCreate.model_validate_json(body)
        except pydantic.ValidationError:
            return None
        scope.setdefault("state", {})[rankings.PARSED_BODY] = (body, request)
        if request.target is not None or (
            rankings.count_candidates(request) > rankings.INLINE_MAX_CONFIGURATIONS
        ):
            return None
        context = rankings.cached_context(self.state, principal.tenant_id, request.calibration_id)
        if context is None:
            return None
        try:
            rankings.check_limits(request, self.state.settings.max_ranking_candidates)
            return rankings.rank_configurations(context, request)
        except Exception:  # a problem, or a failure: the route answers it, its way
            return None

    def _principal(self, key: bytes | None) -> Principal | None:
        if not key:  # as FastAPI's APIKeyHeader: an empty header is no header
            return self.state.local_tenant
        return self.state.verifier.verify_cached(key.decode("latin-1"))


def _is_ranking(scope: Scope) -> bool:
    return bool(
        scope["type"] == "http"
        and scope["method"] == "POST"
        and scope.get("path") == rankings.PREFIX
    )


def _declared_length(scope: Scope) -> int | None:
    value = _first(scope["headers"], b"content-length")
    return int(value) if value is not None and value.isdigit() else None


def _first(headers: Iterable[tuple[bytes, bytes]], name: bytes) -> bytes | None:
    """The first value of header ``name`` (lower case), as Starlette's ``Headers.get``."""
    for header, value in headers:
        if header == name:
            return value
    return None


def _replay(received: list[Message], receive: Receive) -> Receive:
    """``receive`` that hands out the messages already read, then reads on."""
    pending = list(received)

    async def replay() -> Message:
        if pending:
            return pending.pop(0)
        return await receive()

    return replay
