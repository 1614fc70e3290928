"""The FastAPI application factory.

``create_app(settings)`` builds the app (it only creates the data folder); starting it (the
ASGI lifespan) migrates the database, creates tenant 'local' in keyless mode and starts the
job runner; stopping it lets running jobs finish for ``shutdown_grace_s`` and re-queues the
rest. Under ``kincal serve`` (:mod:`service.jobs.supervisor`) the runner is a process of its
own: each request process gets ``runner=RemoteRunner(...)``, which starts and stops nothing.
"""

from __future__ import annotations

import importlib.resources
import logging
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.openapi.docs import get_redoc_html, get_swagger_ui_html
from fastapi.responses import HTMLResponse
from fastapi.routing import APIRoute
from fastapi.staticfiles import StaticFiles
from starlette.concurrency import run_in_threadpool

from service import kincal_version
from service.api import calibrations, datasets, designs, discoveries, health, rankings, robots
from service.api.checks import router as checks_router
from service.api.deps import ServiceState
from service.api.metrics import Metrics
from service.api.middleware import BodyLimits, RequestContextMiddleware
from service.api.problems import install_problem_handlers
from service.api.ranking_fast_path import RankingFastPath
from service.api.results import ResultCache
from service.jobs.runner import JobRegistry, JobRunner, RunnerHandle, default_registry
from service.security import KeyVerifier, Principal
from service.settings import Settings
from service.storage import repository
from service.storage.db import Database
from service.storage.files import FileStore
from service.storage.repository import LOCAL_TENANT

log = logging.getLogger("kincal.service")

DESCRIPTION = """Calibrate robot kinematics, including the randomness inside the chain.

Upload a recording (`/datasets`), start a calibration job (`/calibrations`), poll it, then read
its result, HTML report and calibrated URDF. Rank candidate configurations or a target pose's IK
solutions by the calibrated uncertainty (`/rankings`, synchronous), or look for the physics a
recording shows and your model lacks (`/discoveries`, a job like calibrations). Choose the poses to
record (`/designs`, synchronous for small candidate sets). Every error is
`application/problem+json` (RFC 9457). Authenticate with `X-API-Key` (not needed when the
service is bound to 127.0.0.1).
"""


def build_state(
    settings: Settings, registry: JobRegistry, runner: RunnerHandle | None = None
) -> ServiceState:
    """The shared state of the routes; the job runner runs in this process unless ``runner``
    is given (a handle on a runner elsewhere)."""
    database = Database(settings.resolved_database_url)
    files = FileStore(settings.data_dir)
    metrics = Metrics(database, registry.names, lambda: handle.workers_alive())
    handle = runner or JobRunner(
        settings, database, files, registry, on_finished=metrics.observe_job
    )
    return ServiceState(
        settings=settings,
        database=database,
        files=files,
        registry=registry,
        runner=handle,
        verifier=KeyVerifier(database, settings.api_key_cache_s),
        metrics=metrics,
        results=ResultCache(files, settings.result_cache_size),
    )


def _start(state: ServiceState) -> None:
    settings = state.settings
    state.database.migrate()  # a no-op under kincal serve: its supervisor migrated already
    if settings.keyless:
        with state.database.session() as session:
            tenant = repository.ensure_tenant(session, LOCAL_TENANT)
            state.local_tenant = Principal(tenant.id, tenant.name, None)
    state.runner.start()
    if not isinstance(state.runner, JobRunner):
        return  # a request process of kincal serve: its supervisor tells the story
    if settings.keyless:
        log.warning(
            "keyless mode: bound to loopback address %s, requests without X-API-Key act as "
            "tenant '%s' (set KINCAL_ALLOW_KEYLESS_LOCALHOST=false to require keys)",
            settings.host,
            LOCAL_TENANT,
        )
    else:
        log.info("API keys required (bound to %s)", settings.host)
    log.info(
        "kincal service started",
        extra={
            "version": kincal_version(),
            "database": state.database.backend,
            "data_dir": str(settings.data_dir),
            "workers": settings.workers,
        },
    )


def _stop(state: ServiceState) -> None:
    embedded = isinstance(state.runner, JobRunner)
    if embedded:
        log.info(
            "shutting down: waiting up to %.0f s for running jobs",
            state.settings.shutdown_grace_s,
        )
    state.runner.stop()
    state.database.dispose()
    if embedded:
        log.info("kincal service stopped")


DOCS_ASSETS = "/docs-assets"


def install_docs(app: FastAPI) -> None:
    """/docs (Swagger UI) and /redoc from the assets of the installed ``fastapi-offline``
    package (Swagger UI: Apache-2.0, ReDoc: MIT), so they render on a machine without internet
    access; FastAPI's defaults load them from a CDN."""
    assets = importlib.resources.files("fastapi_offline") / "static"
    app.mount(DOCS_ASSETS, StaticFiles(directory=str(assets)), name="docs-assets")
    title = f"{app.title} API"

    @app.get("/docs", include_in_schema=False)
    async def swagger_ui() -> HTMLResponse:
        return get_swagger_ui_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=title,
            swagger_js_url=f"{DOCS_ASSETS}/swagger-ui-bundle.js",
            swagger_css_url=f"{DOCS_ASSETS}/swagger-ui.css",
            swagger_favicon_url=f"{DOCS_ASSETS}/favicon.png",
        )

    @app.get("/redoc", include_in_schema=False)
    async def redoc() -> HTMLResponse:
        return get_redoc_html(
            openapi_url=app.openapi_url or "/openapi.json",
            title=title,
            redoc_js_url=f"{DOCS_ASSETS}/redoc.standalone.js",
            redoc_favicon_url=f"{DOCS_ASSETS}/favicon.png",
            with_google_fonts=False,
        )


def create_app(
    settings: Settings | None = None,
    *,
    registry: JobRegistry | None = None,
    runner: RunnerHandle | None = None,
) -> FastAPI:
    """The kincal HTTP service for ``settings`` (default: from the environment); jobs run in
    this process unless ``runner`` is a handle on a runner elsewhere."""
    settings = settings or Settings()
    state = build_state(settings, registry or default_registry(), runner)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        await run_in_threadpool(_start, state)
        try:
            yield
        finally:
            await run_in_threadpool(_stop, state)

    app = FastAPI(
        title="kincal",
        version=kincal_version(),
        description=DESCRIPTION,
        lifespan=lifespan,
        docs_url=None,
        openapi_url="/openapi.json",
        redoc_url=None,
    )
    install_docs(app)
    app.state.kincal = state
    install_problem_handlers(app)
    for module in (robots, datasets, calibrations, rankings, discoveries, designs, health):
        app.include_router(module.router)
    app.include_router(checks_router)
    # The last added is the outermost: the fast path runs inside the request context.
    app.add_middleware(RankingFastPath, state=state, route=ranking_route())
    app.add_middleware(RequestContextMiddleware, metrics=state.metrics, limits=BodyLimits(settings))
    return app


def ranking_route() -> APIRoute:
    """The route of ``POST /api/v1/rankings`` (what the router puts in ``scope["route"]``)."""
    for route in rankings.router.routes:
        if isinstance(route, APIRoute) and route.path == rankings.PREFIX:
            return route
    raise LookupError(rankings.PREFIX)
