"""A new kind of job (as discoveries will be) is a registry entry, a POST and add_job_routes."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

from fastapi import APIRouter, Response
from fastapi.testclient import TestClient
from pydantic import BaseModel

from schemas.api import JobStatus, Page
from service.api.deps import PrincipalDep, StateDep
from service.api.jobs_common import (
    Artifact,
    JobResource,
    add_job_routes,
    job_status,
    json_response,
    submit_job,
)
from service.jobs.runner import default_registry
from service.storage.models import Job
from tests.service.api.conftest import assert_problem


class EchoPublic(BaseModel):
    id: str
    status: JobStatus


class EchoesPublic(Page):
    data: list[EchoPublic]


def _echo_router() -> APIRouter:
    router = APIRouter(prefix="/api/v1/echoes", tags=["echoes"])
    resource = JobResource(
        kind="echo",
        noun="echo",
        prefix="/api/v1/echoes",
        public_model=EchoPublic,
        page_model=EchoesPublic,
        to_public=lambda job: EchoPublic(id=job.id, status=job_status(job)),
    )

    @router.post("", status_code=202, response_model=EchoPublic)
    def create_echo(body: dict[str, Any], principal: PrincipalDep, state: StateDep) -> Response:
        job: Job = submit_job(state, principal.tenant_id, "echo", body)
        public = resource.to_public(job).model_dump_json()
        return json_response(public, 202, location=f"/api/v1/echoes/{job.id}")

    add_job_routes(router, resource, [Artifact("result", "application/json", "The echo.")])
    return router


def test_a_registered_job_kind_with_shared_routes_runs_end_to_end(
    make_app: Callable[..., TestClient],
) -> None:
    registry = default_registry()
    registry.register("echo", "tests.service.api.jobs_for_tests:echo", id_prefix="echo")
    client = make_app(registry=registry, workers=1)
    client.app.include_router(_echo_router())  # type: ignore[attr-defined]
    with client:
        created = client.post("/api/v1/echoes", json={"hello": [1, 2, 3]})
        assert created.status_code == 202
        location = created.headers["location"]
        assert location.startswith("/api/v1/echoes/echo_")
        deadline = time.monotonic() + 30
        while (status := client.get(location).json()["status"])["state"] != "succeeded":
            assert status["state"] in ("queued", "running") and time.monotonic() < deadline
            time.sleep(0.05)
        assert client.get(f"{location}/result").json() == {"hello": [1, 2, 3]}
        assert client.get("/api/v1/echoes").json()["count"] == 1
        assert_problem(client.post(f"{location}/cancel"), 409, "already succeeded")
        assert_problem(client.get("/api/v1/echoes/echo_missing"), 404, "echo_missing")
        assert "/api/v1/echoes/{echo_id}/result" in client.get("/openapi.json").json()["paths"]
