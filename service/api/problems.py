"""Every error is an RFC 9457 problem document (``application/problem+json``).

Domain errors (:mod:`solver.errors`) become 422 with their one-line message as ``detail``;
FastAPI/pydantic validation errors become 422 naming each field; HTTP errors keep their status.
Unexpected exceptions are turned into a 500 problem by the request middleware, never showing
internals.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from http import HTTPStatus
from typing import Any

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import ValidationError
from starlette.exceptions import HTTPException as StarletteHTTPException

from schemas.api import Problem
from service.jobs import logs
from solver.errors import CalibrationError, DatasetError, KincalError, ModelError, SolverError

PROBLEM_MEDIA_TYPE = "application/problem+json"
PROBLEM_BASE = "urn:kincal:problem:"


class ProblemException(Exception):
    """Raise anywhere in a request to answer with this problem."""

    def __init__(
        self,
        status: int,
        detail: str,
        *,
        slug: str | None = None,
        title: str | None = None,
        headers: dict[str, str] | None = None,
        errors: list[dict[str, Any]] | None = None,
    ) -> None:
        super().__init__(detail)
        self.status = status
        self.detail = detail
        self.slug = slug
        self.title = title or HTTPStatus(status).phrase
        self.headers = headers
        self.errors = errors


def problem_body(
    status: int,
    detail: str | None,
    *,
    instance: str | None,
    slug: str | None = None,
    title: str | None = None,
    errors: list[dict[str, Any]] | None = None,
) -> dict[str, Any]:
    body: dict[str, Any] = {
        "type": PROBLEM_BASE + slug if slug else "about:blank",
        "title": title or HTTPStatus(status).phrase,
        "status": status,
        "detail": detail,
        "instance": instance,
        "request_id": logs.request_id.get(),
    }
    if errors:
        body["errors"] = errors
    return body


def problem_response(
    status: int,
    detail: str | None,
    *,
    instance: str | None,
    slug: str | None = None,
    title: str | None = None,
    headers: Mapping[str, str] | None = None,
    errors: list[dict[str, Any]] | None = None,
) -> JSONResponse:
    body = problem_body(status, detail, instance=instance, slug=slug, title=title, errors=errors)
    return JSONResponse(body, status_code=status, headers=headers, media_type=PROBLEM_MEDIA_TYPE)


def problem_bytes(status: int, detail: str, *, instance: str | None, slug: str) -> bytes:
    """A problem document as bytes, for the raw ASGI middleware."""
    return json.dumps(problem_body(status, detail, instance=instance, slug=slug)).encode()


def _location(loc: tuple[Any, ...] | list[Any]) -> str:
    return ".".join(str(part) for part in loc)


def _pointer(loc: tuple[Any, ...] | list[Any]) -> str | None:
    if not loc or loc[0] != "body":
        return None
    return "#/" + "/".join(str(part).replace("~", "~0").replace("/", "~1") for part in loc[1:])


def validation_errors(errors: list[Any], prefix: tuple[str, ...] = ()) -> list[dict[str, Any]]:
    """Pydantic/FastAPI error dicts -> ``errors`` members (location, pointer, detail)."""
    out = []
    for error in errors:
        loc = (*prefix, *error.get("loc", ()))
        out.append({"location": _location(loc), "pointer": _pointer(loc), "detail": error["msg"]})
    return out


def validation_detail(errors: list[dict[str, Any]]) -> str:
    """One line naming the first bad field (and how many more there are)."""
    first = errors[0]
    more = (
        f" (and {len(errors) - 1} more problem(s), listed in 'errors')" if len(errors) > 1 else ""
    )
    where = first["location"] or "request"
    return f"{where}: {first['detail']}{more}; fix the field and resend (schema: /docs)"


def validation_problem(errors: list[dict[str, Any]], instance: str | None) -> JSONResponse:
    detail = validation_detail(errors)
    return problem_response(422, detail, instance=instance, slug="invalid-request", errors=errors)


def pydantic_problem(
    exc: ValidationError, instance: str | None, prefix: str = "body"
) -> JSONResponse:
    return validation_problem(validation_errors(exc.errors(), (prefix,)), instance)


_DOMAIN_SLUGS: tuple[tuple[type[KincalError], str], ...] = (
    (DatasetError, "invalid-dataset"),
    (ModelError, "invalid-robot-model"),
    (CalibrationError, "calibration-impossible"),
    (SolverError, "solver-error"),
    (KincalError, "invalid-input"),
)


def domain_problem(exc: KincalError, instance: str | None) -> JSONResponse:
    slug = next(s for cls, s in _DOMAIN_SLUGS if isinstance(exc, cls))
    return problem_response(422, str(exc), instance=instance, slug=slug)


def install_problem_handlers(app: FastAPI) -> None:
    """Turn every handled error into problem+json."""

    async def on_problem(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, ProblemException)
        return problem_response(
            exc.status,
            exc.detail,
            instance=request.url.path,
            slug=exc.slug,
            title=exc.title,
            headers=exc.headers,
            errors=exc.errors,
        )

    async def on_http(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, StarletteHTTPException)
        phrase = HTTPStatus(exc.status_code).phrase
        detail = exc.detail if isinstance(exc.detail, str) and exc.detail != phrase else None
        if exc.status_code == 404 and detail is None:
            detail = f"no resource at {request.url.path}; the API is under /api/v1 (see /docs)"
        if exc.status_code == 405 and detail is None:
            detail = f"{request.method} is not allowed on {request.url.path}; see /docs"
        slug = "body-too-large" if exc.status_code == 413 else None
        return problem_response(
            exc.status_code, detail, instance=request.url.path, slug=slug, headers=exc.headers
        )

    async def on_validation(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, RequestValidationError)
        return validation_problem(validation_errors(list(exc.errors())), request.url.path)

    async def on_domain(request: Request, exc: Exception) -> JSONResponse:
        assert isinstance(exc, KincalError)
        return domain_problem(exc, request.url.path)

    app.add_exception_handler(ProblemException, on_problem)
    app.add_exception_handler(StarletteHTTPException, on_http)
    app.add_exception_handler(RequestValidationError, on_validation)
    app.add_exception_handler(KincalError, on_domain)


def problem_responses(*statuses: int) -> dict[int | str, dict[str, Any]]:
    """OpenAPI ``responses`` entries documenting problem+json answers."""
    return {
        status: {
            "model": Problem,
            "description": HTTPStatus(status).phrase,
            "content": {PROBLEM_MEDIA_TYPE: {"schema": {"$ref": "#/components/schemas/Problem"}}},
        }
        for status in statuses
    }


STANDARD_PROBLEMS = problem_responses(400, 401, 422, 500)
"""What any route can answer: 400 (a body that cannot even be decoded), 401, 422, 500."""
