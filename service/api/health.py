"""Operations: liveness and readiness (no API key needed), Prometheus metrics (an API key of
any tenant when keys are required: the numbers span every tenant)."""

from __future__ import annotations

import logging

from fastapi import APIRouter, Response
from fastapi.responses import JSONResponse
from starlette.concurrency import run_in_threadpool

from schemas.api import Health, Readiness
from service.api.deps import PrincipalDep, StateDep
from service.api.metrics import CONTENT_TYPE
from service.api.problems import STANDARD_PROBLEMS

router = APIRouter(tags=["operations"])
log = logging.getLogger("kincal.health")


@router.get("/healthz", response_model=Health)
async def healthz() -> Health:
    """Liveness: the process answers."""
    return Health(status="ok")


@router.get(
    "/readyz",
    response_model=Readiness,
    responses={503: {"model": Readiness, "description": "Not ready."}},
)
def readyz(state: StateDep) -> JSONResponse:
    """Readiness: database reachable and migrated, workers alive, data folder writable."""
    checks = {"database": False, "migrations": False}
    try:
        state.database.ping()
        checks["database"] = True
        checks["migrations"] = state.database.migrations_applied()
    except Exception as exc:
        log.warning("readiness: database check failed: %s", exc)
    checks["workers"] = state.runner.healthy()
    checks["storage"] = state.files.writable()
    ready = all(checks.values())
    body = Readiness(
        status="ready" if ready else "not ready",
        checks=checks,
        workers_alive=state.runner.workers_alive(),
        workers_configured=state.settings.workers,
    )
    return JSONResponse(body.model_dump(), status_code=200 if ready else 503)


@router.get("/metrics", response_class=Response, responses=STANDARD_PROBLEMS)
async def metrics(state: StateDep, _: PrincipalDep) -> Response:
    """Prometheus metrics: requests, latency, jobs by state, job durations, latest checks."""
    body = await run_in_threadpool(state.metrics.render)
    return Response(body, media_type=CONTENT_TYPE)
