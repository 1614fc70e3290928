"""Fixtures for the HTTP service tests: apps on fresh databases, keys, small recordings.

Storage runs on SQLite in a temporary folder. Set ``KINCAL_TEST_DATABASE_URL`` to a PostgreSQL
server URL whose user may create databases, e.g.
``postgresql+psycopg://kincal:kincal@127.0.0.1:5432/postgres``, to run every storage and API test
on a fresh database of its own on that server instead (created for the test, dropped after it);
running the suite with and without it covers both backends. Once set, an unreachable server is
an error, not a skip. (``KINCAL_TEST_POSTGRES_URL`` is the older name of the same setting.)
"""

from __future__ import annotations

import contextlib
import functools
import io
import os
import threading
import time
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
import uvicorn
from fastapi.testclient import TestClient
from sqlalchemy.engine import make_url

from schemas.dataset import PoseDataset, write_dataset
from service.api import create_app
from service.api.client import KincalClient
from service.app import simulate as scenarios
from service.jobs.runner import JobRegistry
from service.security import create_api_key
from service.settings import Settings
from service.storage.db import Database
from tests.conftest import robot


def _test_database_url() -> str | None:
    """The opted-in PostgreSQL server URL, or None for SQLite."""
    url = os.environ.get("KINCAL_TEST_DATABASE_URL") or os.environ.get("KINCAL_TEST_POSTGRES_URL")
    if not url:
        return None
    if make_url(url).get_backend_name() != "postgresql":
        raise pytest.UsageError(
            f"KINCAL_TEST_DATABASE_URL must be a postgresql:// URL (SQLite is the default), "
            f"got {make_url(url).render_as_string(hide_password=True)}"
        )
    return url


POSTGRES_URL = _test_database_url()


@contextlib.contextmanager
def fresh_database_url(folder: Path) -> Iterator[str]:
    """A SQLite file in ``folder``, or a new PostgreSQL database dropped afterwards."""
    if not POSTGRES_URL:
        yield f"sqlite:///{folder / 'kincal.db'}"
        return
    import psycopg

    server = make_url(POSTGRES_URL)
    name = f"kincal_test_{uuid.uuid4().hex[:12]}"
    admin = server.set(drivername="postgresql").render_as_string(hide_password=False)
    with psycopg.connect(admin, autocommit=True) as connection:
        connection.execute(f'CREATE DATABASE "{name}"')
    try:
        yield server.set(database=name).render_as_string(hide_password=False)
    finally:
        # Sessions the test left open are ended first (ours only: DROP ... WITH (FORCE) would
        # also need to end an autovacuum worker, which an unprivileged user may not); plain
        # DROP DATABASE then waits for autovacuum by itself.
        with psycopg.connect(admin, autocommit=True) as connection:
            connection.execute(
                "SELECT pg_terminate_backend(pid, 5000) FROM pg_stat_activity "
                "WHERE datname = %s AND usename = current_user AND pid <> pg_backend_pid()",
                [name],
            )
            connection.execute(f'DROP DATABASE IF EXISTS "{name}"')


def make_settings(folder: Path, database_url: str, **overrides: Any) -> Settings:
    values: dict[str, Any] = {
        "data_dir": folder / "data",
        "database_url": database_url,
        "workers": 0,
        "log_format": "text",
        "job_poll_s": 0.1,
        "job_heartbeat_s": 0.5,
        "shutdown_grace_s": 5.0,
        "instance_name": "test-instance",
        **overrides,
    }
    return Settings(**values)


@pytest.fixture
def database_url(tmp_path: Path) -> Iterator[str]:
    with fresh_database_url(tmp_path) as url:
        yield url


AppFactory = Callable[..., TestClient]


@pytest.fixture
def make_client(tmp_path: Path, database_url: str) -> Iterator[AppFactory]:
    """``make_client(**settings)`` -> a started TestClient; all are stopped at teardown."""
    stack = contextlib.ExitStack()

    def factory(registry: JobRegistry | None = None, **overrides: Any) -> TestClient:
        settings = make_settings(tmp_path, database_url, **overrides)
        client = TestClient(create_app(settings, registry=registry), raise_server_exceptions=False)
        return stack.enter_context(client)

    with stack:
        yield factory


@pytest.fixture
def make_app(tmp_path: Path, database_url: str) -> Callable[..., TestClient]:
    """``make_app(**settings)`` -> an unstarted TestClient on the test's database (use ``with``)."""

    def factory(registry: JobRegistry | None = None, **overrides: Any) -> TestClient:
        settings = make_settings(tmp_path, database_url, **overrides)
        return TestClient(create_app(settings, registry=registry), raise_server_exceptions=False)

    return factory


@pytest.fixture
def client(make_client: AppFactory) -> TestClient:
    """Keyless (127.0.0.1), no worker processes: jobs are accepted but stay queued."""
    return make_client()


def settings_of(client: TestClient) -> Settings:
    settings: Settings = client.app.state.kincal.settings  # type: ignore[attr-defined]
    return settings


def database_of(client: TestClient) -> Database:
    database: Database = client.app.state.kincal.database  # type: ignore[attr-defined]
    return database


def new_key(client: TestClient, tenant: str) -> str:
    return create_api_key(database_of(client), tenant)[1]


# --- recordings --------------------------------------------------------------------------------


@functools.cache
def recording(n: int = 40, seed: int = 2, name: str = "ur10") -> PoseDataset:
    """A small simulated recording (geometry, compliance, camera and marker effects)."""
    description = robot(name)
    scn, rec = scenarios.simulate(description, n_samples=n, seed=seed)
    return scenarios.recording_dataset(rec, scn.chain, rotation=True)


@functools.cache
def recording_bytes(suffix: str = ".csv", n: int = 40, seed: int = 2) -> bytes:
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / f"recording{suffix}"
        write_dataset(recording(n, seed), path)
        return path.read_bytes()


def upload_csv(
    client: TestClient,
    data: bytes | None = None,
    *,
    filename: str = "recording.csv",
    robot_name: str = "ur10",
    headers: dict[str, str] | None = None,
    media: str = "text/csv",
) -> Any:
    return client.post(
        "/api/v1/datasets",
        files={"file": (filename, io.BytesIO(data or recording_bytes()), media)},
        data={"robot": robot_name},
        headers=headers or {},
    )


def assert_problem(response: Any, status: int, *fragments: str) -> dict[str, Any]:
    """An RFC 9457 problem with this status whose detail mentions every fragment."""
    assert response.status_code == status, response.text
    assert response.headers["content-type"].startswith("application/problem+json")
    body = response.json()
    assert body["status"] == status
    assert body["title"] and body["type"] and body["instance"]
    assert body["detail"], body
    for fragment in fragments:
        assert fragment in body["detail"], (fragment, body["detail"])
    assert "Traceback" not in response.text
    return dict(body)


def client_api(client: TestClient, key: str | None = None) -> KincalClient:
    return KincalClient(api_key=key, client=client)


@contextlib.contextmanager
def uvicorn_in_thread(settings: Settings) -> Iterator[str]:
    """The app for ``settings`` under uvicorn on a free loopback port, in a thread of this
    process (for a real browser); its URL."""
    config = uvicorn.Config(
        create_app(settings), host="127.0.0.1", port=0, log_config=None, lifespan="on"
    )
    server = uvicorn.Server(config)
    thread = threading.Thread(target=server.run, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert time.monotonic() < deadline and thread.is_alive(), "server did not start"
        time.sleep(0.05)
    port = server.servers[0].sockets[0].getsockname()[1]
    try:
        yield f"http://127.0.0.1:{port}"
    finally:
        server.should_exit = True
        thread.join(15)
