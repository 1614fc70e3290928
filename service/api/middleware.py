"""Request context (pure ASGI, no per-request thread hops): request id, body-size limit,
metrics, one access-log line per request, and the last line of defence against exceptions.
"""

from __future__ import annotations

import logging
import re
import time
import uuid
from dataclasses import dataclass
from typing import Any

from starlette.exceptions import HTTPException
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.api.metrics import Metrics
from service.api.problems import PROBLEM_MEDIA_TYPE, problem_bytes
from service.jobs import logs
from service.settings import Settings

log = logging.getLogger("kincal.http")
_REQUEST_ID = re.compile(r"^[A-Za-z0-9._-]{1,128}$")


@dataclass(frozen=True)
class BodyLimit:
    """The largest body of requests whose method and path match, and the setting raising it."""

    bytes: int
    setting: str


class BodyLimits:
    """Request body limits per route, applied before anything reads the body: a dataset upload
    may be large, a ranking moderately, everything else is small."""

    def __init__(self, settings: Settings) -> None:
        urdf = BodyLimit(2 * settings.max_urdf_bytes + 64 * 1024, "KINCAL_MAX_URDF_BYTES")
        self._routes: tuple[tuple[str, str, BodyLimit], ...] = (
            (
                "POST",
                "/api/v1/datasets",
                BodyLimit(settings.max_request_bytes, "KINCAL_MAX_REQUEST_BYTES"),
            ),
            (
                "POST",
                "/api/v1/rankings",
                BodyLimit(settings.max_ranking_request_bytes, "KINCAL_MAX_RANKING_REQUEST_BYTES"),
            ),
            ("POST", "/api/v1/robots", urdf),  # JSON-escaped URDF text
        )
        self._default = BodyLimit(
            settings.max_small_request_bytes, "KINCAL_MAX_SMALL_REQUEST_BYTES"
        )

    def of(self, method: str, path: str) -> BodyLimit:
        for route_method, route_path, limit in self._routes:
            if method == route_method and path.rstrip("/") == route_path:
                return limit
        return self._default


class BodyTooLargeError(HTTPException):
    """Raised from ``receive`` once the body passes the limit.

    An HTTPException, so that FastAPI's body parsing lets it through (it turns other errors
    into a 400) and the problem handlers answer 413.
    """

    def __init__(self, limit: BodyLimit) -> None:
        super().__init__(413, too_large_detail(limit))


def too_large_detail(limit: BodyLimit) -> str:
    return (
        f"request body is larger than the limit of {limit.bytes} bytes for this route; split "
        f"the data or ask the operator to raise {limit.setting}"
    )


class RequestContextMiddleware:
    def __init__(self, app: ASGIApp, *, metrics: Metrics, limits: BodyLimits) -> None:
        self.app = app
        self.metrics = metrics
        self.limits = limits

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        offered = headers.get("x-request-id", "")
        request_id = offered if _REQUEST_ID.match(offered) else uuid.uuid4().hex
        token = logs.request_id.set(request_id)
        started = time.perf_counter()
        response: dict[str, Any] = {"status": 500, "started": False}
        path = scope.get("path", "")

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                response["status"] = message["status"]
                response["started"] = True
                message.setdefault("headers", [])
                message["headers"] = [
                    *message["headers"],
                    (b"x-request-id", request_id.encode()),
                ]
            await send(message)

        received = 0
        limit = self.limits.of(scope["method"], path)

        async def limited_receive() -> Message:
            nonlocal received
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > limit.bytes:
                    raise BodyTooLargeError(limit)
            return message

        try:
            declared = _content_length(headers)
            if declared is not None and declared > limit.bytes:
                await self._problem(
                    send_with_id, 413, too_large_detail(limit), path, "body-too-large"
                )
            elif declared == -1:
                await self._problem(
                    send_with_id,
                    400,
                    "Content-Length header is not a non-negative integer; send a valid length",
                    path,
                    "bad-content-length",
                )
            else:
                await self.app(scope, limited_receive, send_with_id)
        except BodyTooLargeError:
            if not response["started"]:
                await self._problem(
                    send_with_id, 413, too_large_detail(limit), path, "body-too-large"
                )
        except Exception:
            log.exception("unhandled error while serving %s %s", scope["method"], path)
            if not response["started"]:
                await self._problem(
                    send_with_id,
                    500,
                    f"internal error; quote request id {request_id} when reporting it",
                    path,
                    "internal-error",
                )
        finally:
            elapsed = time.perf_counter() - started
            route = scope.get("route")
            template = getattr(route, "path", None) or "<unmatched>"
            self.metrics.observe_request(scope["method"], template, response["status"], elapsed)
            log.info(
                "%s %s %d",
                scope["method"],
                path,
                response["status"],
                extra={
                    "route": template,
                    "duration_ms": round(elapsed * 1000, 2),
                    "request_id": request_id,
                },
            )
            logs.request_id.reset(token)

    @staticmethod
    async def _problem(send: Send, status: int, detail: str, path: str, slug: str) -> None:
        body = problem_bytes(status, detail, instance=path, slug=slug)
        await send(
            {
                "type": "http.response.start",
                "status": status,
                "headers": [
                    (b"content-type", PROBLEM_MEDIA_TYPE.encode()),
                    (b"content-length", str(len(body)).encode()),
                    (b"connection", b"close"),
                ],
            }
        )
        await send({"type": "http.response.body", "body": body})


def _content_length(headers: dict[str, str]) -> int | None:
    """The declared body length; None if absent, -1 if malformed."""
    value = headers.get("content-length")
    if value is None:
        return None
    return int(value) if value.isdigit() else -1
