"""schemathesis against a real ``kincal serve`` (uvicorn on 127.0.0.1, API keys on).

test_fuzz.py fuzzes the app in-process, where no HTTP parser, socket or uvicorn setting is in
the way. Here every operation of /openapi.json is called over real HTTP, so what uvicorn and
the middleware do with generated paths, headers and bodies is checked too: no 5xx, and every
answer (problem documents included) matches the schema of its operation.
"""

from __future__ import annotations

import os
import signal
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import pytest
import schemathesis
from hypothesis import HealthCheck, settings
from hypothesis import strategies as st

from service.api.client import KincalClient
from service.security import create_api_key
from service.storage.db import Database
from tests.service.api.conftest import fresh_database_url, recording_bytes
from tests.service.api.test_crash_recovery import Server
from tests.service.api.test_fuzz import SCHEMA_CHECKS, _openapi_document, steered_bodies

# Its own schema object: the hook below steers bodies to this module's live server. Fuzzing
# phase only: the coverage phase's boundary cases go to the same application in process
# (test_fuzz.py); here they would cost seconds at every collection for the process boundary
# that a few requests per operation already cross.
LIVE_SCHEMA = schemathesis.openapi.from_dict(_openapi_document())
LIVE_SCHEMA.config.phases.coverage.enabled = False


@dataclass
class Live:
    url: str
    api_key: str
    dataset_id: str
    calibration_id: str


LIVE: list[Live] = []


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Live]:
    folder: Path = tmp_path_factory.mktemp("fuzz-live")
    with fresh_database_url(folder) as url:
        env = {
            **os.environ,
            "KINCAL_DATA_DIR": str(folder / "data"),
            "KINCAL_DATABASE_URL": url,
            "KINCAL_ALLOW_KEYLESS_LOCALHOST": "false",
            "KINCAL_MAX_REQUEST_BYTES": str(256 * 1024),
        }
        server = Server(env, folder / "server.log")
        try:
            server.wait_live()
            database = Database(url)  # migrated by the server at start-up
            try:
                key = create_api_key(database, "fuzz")[1]
            finally:
                database.dispose()
            api = KincalClient(server.url, api_key=key)
            csv = folder / "recording.csv"
            csv.write_bytes(recording_bytes(".csv", 40, 3))
            dataset = api.upload_dataset(csv, robot="ur10")
            calibration = api.start_calibration(dataset["id"])
            api.wait(calibration["id"], poll_s=0.05)
            LIVE.append(Live(server.url, key, dataset["id"], calibration["id"]))
            yield LIVE[-1]
        finally:
            LIVE.clear()
            code = server.stop(signal.SIGTERM)
        log = (folder / "server.log").read_text()
        assert code in (0, -signal.SIGTERM), log
        assert "Traceback" not in log, log


@LIVE_SCHEMA.hook
def flatmap_body(context: Any, body: Any) -> st.SearchStrategy[Any]:
    """Half of the bodies name the live server's dataset / calibration, to get past the 404s."""
    if not LIVE:
        return st.just(body)
    server = LIVE[-1]
    return steered_bodies(body, server.dataset_id, server.calibration_id, plausible_rankings=False)


@LIVE_SCHEMA.parametrize()
@settings(max_examples=6, deadline=None, suppress_health_check=list(HealthCheck))
def test_live_server_operations_never_5xx_and_match_their_schema(case: Any, live: Live) -> None:
    case.headers = {**(case.headers or {}), "X-API-Key": live.api_key}
    response = case.call(base_url=live.url, timeout=30)
    case.validate_response(response, checks=SCHEMA_CHECKS)


def test_live_server_answers_requests_without_a_key_with_401(live: Live) -> None:
    response = httpx.get(f"{live.url}/api/v1/datasets", timeout=10)
    assert response.status_code == 401
    assert response.headers["content-type"].startswith("application/problem+json")
