"""Arbitrary requests never produce a 5xx: every answer is a success or a problem document."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import quote

import pytest
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from service.api import create_app
from tests.service.api.conftest import fresh_database_url, make_settings

JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=12), inner, max_size=4)
    ),
    max_leaves=12,
)
PATHS = st.sampled_from(
    [
        "/api/v1/datasets",
        "/api/v1/calibrations",
        "/api/v1/robots",
        "/api/v1/datasets/{id}",
        "/api/v1/calibrations/{id}",
        "/api/v1/calibrations/{id}/result",
        "/api/v1/calibrations/{id}/cancel",
        "/api/v1/robots/{id}",
    ]
)


@pytest.fixture(scope="module")
def fuzz_client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    folder: Path = tmp_path_factory.mktemp("fuzz")
    with fresh_database_url(folder) as url:
        app = create_app(make_settings(folder, url, max_request_bytes=64 * 1024))
        with TestClient(app, raise_server_exceptions=False) as client:
            yield client


def _check(response: Any) -> None:
    assert response.status_code < 500, response.text
    if response.status_code >= 400:
        assert response.headers["content-type"].startswith("application/problem+json")
        assert response.json()["status"] == response.status_code


@settings(max_examples=60, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    method=st.sampled_from(["GET", "POST", "DELETE", "PUT"]),
    path=PATHS,
    ident=st.text(min_size=1, max_size=40).filter(lambda s: "/" not in s and s not in (".", "..")),
    body=JSON,
    query=st.dictionaries(
        st.sampled_from(["offset", "limit", "x"]), st.text(max_size=8), max_size=2
    ),
)
def test_random_json_requests_never_give_a_5xx(
    fuzz_client: TestClient, method: str, path: str, ident: str, body: Any, query: dict[str, str]
) -> None:
    url = path.replace("{id}", quote(ident, safe=""))
    _check(fuzz_client.request(method, url, json=body, params=query))


@settings(max_examples=40, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    robot=st.sampled_from(["ur10", "panda"]) | st.text(max_size=20),
    content=st.binary(max_size=2000),
    filename=st.sampled_from(["a.csv", "a.json", "a.parquet", "a.txt", ""]),
    extra=st.dictionaries(
        st.sampled_from(["base_frame", "tip_frame", "name"]), st.text(max_size=10)
    ),
)
def test_random_uploads_never_give_a_5xx(
    fuzz_client: TestClient, robot: str, content: bytes, filename: str, extra: dict[str, str]
) -> None:
    response = fuzz_client.post(
        "/api/v1/datasets",
        files={"file": (filename, content, "application/octet-stream")},
        data={"robot": robot, **extra},
    )
    _check(response)
