"""Request dependencies as ``Annotated`` aliases: state, settings, session, caller.

Latency note: FastAPI runs every *sync* dependency and endpoint in the thread pool, and a sync
generator dependency (``SessionDep``) costs two hops. ``StateDep``, ``SettingsDep`` and
``PrincipalDep`` are async (no hop). Endpoints that are polled or on a hot path are ``async``
and do their database work in ONE ``run_in_threadpool`` call with
``state.database.sessions()``, which under load measurably lowers GET latency.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, Request, Security
from fastapi.security import APIKeyHeader
from sqlalchemy.orm import Session
from starlette.concurrency import run_in_threadpool

from service.api.metrics import Metrics
from service.api.problems import ProblemException
from service.api.results import ResultCache
from service.jobs.runner import JobRegistry, RunnerHandle
from service.security import KeyVerifier, Principal
from service.settings import Settings
from service.storage.db import Database
from service.storage.files import FileStore

API_PREFIX = "/api/v1"


@dataclass
class ServiceState:
    """Everything the routes share, built once per app."""

    settings: Settings
    database: Database
    files: FileStore
    registry: JobRegistry
    runner: RunnerHandle
    verifier: KeyVerifier
    metrics: Metrics
    results: ResultCache
    local_tenant: Principal | None = None


async def get_state(request: Request) -> ServiceState:
    state: ServiceState = request.app.state.kincal
    return state


StateDep = Annotated[ServiceState, Depends(get_state)]


async def get_settings(state: StateDep) -> Settings:
    return state.settings


SettingsDep = Annotated[Settings, Depends(get_settings)]


def get_session(state: StateDep) -> Iterator[Session]:
    with state.database.sessions() as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session)]

api_key_header = APIKeyHeader(
    name="X-API-Key",
    auto_error=False,
    description="API key from `kincal keys create --tenant NAME`. Optional only when the "
    "service is bound to 127.0.0.1 (keyless mode).",
)


async def authenticate(
    state: StateDep, api_key: Annotated[str | None, Security(api_key_header)] = None
) -> Principal:
    """The caller's tenant: from the API key, or tenant 'local' in keyless mode.

    Async on purpose: a key verified in the last ``api_key_cache_s`` costs one SHA-256 and no
    thread hop or database query; only a cache miss goes to the database (in a thread).
    """
    challenge = {"WWW-Authenticate": 'ApiKey header="X-API-Key"'}
    if api_key is None:
        if state.local_tenant is not None:
            return state.local_tenant
        raise ProblemException(
            401,
            "missing X-API-Key header; create a key with `kincal keys create --tenant NAME` "
            "and send it as X-API-Key",
            slug="missing-api-key",
            headers=challenge,
        )
    principal = state.verifier.verify_cached(api_key)
    if principal is None:
        principal = await run_in_threadpool(state.verifier.verify, api_key)
    if principal is None:
        raise ProblemException(
            401,
            "X-API-Key is not a valid, unrevoked key; check for typos or create a new key with "
            "`kincal keys create --tenant NAME`",
            slug="invalid-api-key",
            headers=challenge,
        )
    return principal


PrincipalDep = Annotated[Principal, Depends(authenticate)]
