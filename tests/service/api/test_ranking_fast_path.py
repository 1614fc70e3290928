"""POST /api/v1/rankings through :class:`service.api.ranking_fast_path.RankingFastPath`: the
planners' common case is answered without FastAPI's routing, with the route's exact bytes; every
other request (bad input, unknown keys or calibrations, other media types, chunked or large
bodies) gets exactly the route's answer. Compared side by side with an app without the fast path
on the same database and data folder."""

from __future__ import annotations

import json
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest
from fastapi import FastAPI
from fastapi.testclient import TestClient
from hypothesis import given, settings
from hypothesis import strategies as st

from service.api import create_app
from service.api.ranking_fast_path import RankingFastPath
from service.render import result_json
from solver.model import sample_configurations
from tests.service.api.conftest import (
    client_api,
    fresh_database_url,
    make_settings,
    new_key,
    upload_csv,
)

URL = "/api/v1/rankings"
REQUEST_ID = {"X-Request-Id": "fast-path-test"}  # problems carry it: the same in both apps


class Twins:
    """Two apps on one database and data folder: ``fast`` as served, ``route`` without the
    fast path. A calibration with covariances (tenant 'local', keyless) and an API key."""

    def __init__(self, fast: TestClient, route: TestClient) -> None:
        self.fast, self.route = fast, route
        api = client_api(fast)
        dataset = upload_csv(fast).json()
        calibration = api.start_calibration(dataset["id"], {"heldout": False})
        api.wait(calibration["id"], poll_s=0.05)
        self.id = calibration["id"]
        self.chain, _ = result_json.result_chain(api.result(self.id))
        self.key = new_key(fast, "planners")

    def configurations(self, n: int, seed: int = 3) -> list[list[float]]:
        q = sample_configurations(self.chain, n, np.random.default_rng(seed), 0.8)
        return list(q.tolist())

    def fast_path(self) -> RankingFastPath:
        return fast_path_of(self.fast.app)  # type: ignore[arg-type]

    def both(self, content: bytes, headers: dict[str, str]) -> tuple[Any, Any, int]:
        """The fast app's response, the route-only app's, and whether the fast path answered
        (the route-only app is asked first, so both have the calibration cached)."""
        route = self.route.post(URL, content=content, headers={**REQUEST_ID, **headers})
        before = self.fast_path().answered
        fast = self.fast.post(URL, content=content, headers={**REQUEST_ID, **headers})
        return fast, route, self.fast_path().answered - before


def fast_path_of(app: FastAPI) -> RankingFastPath:
    layer: Any = app.middleware_stack
    while not isinstance(layer, RankingFastPath):
        layer = layer.app
    return layer


def without_fast_path(app: FastAPI) -> FastAPI:
    app.user_middleware = [m for m in app.user_middleware if m.cls is not RankingFastPath]
    return app


@pytest.fixture(scope="module")
def twins(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Twins]:
    folder = tmp_path_factory.mktemp("fast-path")
    with fresh_database_url(folder) as url:
        fast_app = create_app(make_settings(folder, url, workers=1))
        route_app = without_fast_path(create_app(make_settings(folder, url)))
        with (
            TestClient(fast_app, raise_server_exceptions=False) as fast,
            TestClient(route_app, raise_server_exceptions=False) as route,
        ):
            yield Twins(fast, route)


def assert_same_answer(fast: Any, route: Any) -> None:
    assert fast.status_code == route.status_code, (fast.text, route.text)
    assert fast.content == route.content
    drop = {"x-request-id"}
    assert [(k, v) for k, v in fast.headers.items() if k not in drop] == [
        (k, v) for k, v in route.headers.items() if k not in drop
    ]


def body(twins: Twins, **fields: Any) -> bytes:
    return json.dumps({"calibration_id": twins.id, **fields}).encode()


JSON = {"content-type": "application/json"}


@pytest.mark.parametrize(
    ("n", "named", "fields"),
    [
        (100, False, {}),
        (1, False, {}),
        (7, False, {"payload_kg": 1.25}),
        (5, False, {"payload_kg": [0.0, 0.5, 1.0, 1.5, 2.0]}),
        (
            9,
            False,
            {"options": {"top": 3, "weights": {"kind": "task_point", "point_m": [0, 0, 0.1]}}},
        ),
        (6, False, {"options": {"uncertainty": "total"}}),
        (4, True, {}),
    ],
    ids=["100 rows", "1 row", "payload", "payload per row", "options", "total", "named"],
)
def test_the_common_case_is_answered_by_the_fast_path_with_the_routes_bytes(
    twins: Twins, n: int, named: bool, fields: dict[str, Any]
) -> None:
    q = twins.configurations(n)
    candidates: dict[str, Any] = {"joint_positions_rad": q}
    if named:
        names = twins.chain.joint_names
        candidates = {"configurations": [dict(zip(names, row, strict=True)) for row in q]}
    content = body(twins, **candidates, **fields)
    twins.fast.post(URL, content=content, headers=JSON)  # the calibration cached
    fast, route, answered = twins.both(content, JSON)
    assert fast.status_code == 200
    assert_same_answer(fast, route)
    assert answered == 1


def test_with_a_key_the_first_request_verifies_it_and_the_next_is_fast(twins: Twins) -> None:
    key = new_key(twins.fast, "another-planner")
    content = body(twins, joint_positions_rad=twins.configurations(3))
    headers = {**JSON, "X-API-Key": key}
    before = twins.fast_path().answered
    first = twins.fast.post(URL, content=content, headers=headers)  # key not cached: the route
    assert twins.fast_path().answered == before
    assert first.status_code == 404  # another tenant's calibration: the route's problem
    fast, route, answered = twins.both(content, headers)
    assert_same_answer(fast, route)
    assert answered == 0  # a problem is never the fast path's


def test_fast_answers_are_counted_and_logged_under_the_route(
    twins: Twins, caplog: pytest.LogCaptureFixture
) -> None:
    content = body(twins, joint_positions_rad=twins.configurations(2))
    twins.fast.post(URL, content=content, headers=JSON)

    def count() -> float:
        text = twins.fast.get("/metrics").text
        label = 'kincal_http_requests_total{method="POST",route="/api/v1/rankings",status="200"}'
        return float(next(line for line in text.splitlines() if line.startswith(label)).split()[-1])

    before, answered = count(), twins.fast_path().answered
    with caplog.at_level("INFO", logger="kincal.http"):
        response = twins.fast.post(URL, content=content, headers={**JSON, **REQUEST_ID})
    assert response.status_code == 200 and twins.fast_path().answered == answered + 1
    assert response.headers["x-request-id"] == REQUEST_ID["X-Request-Id"]
    assert count() == before + 1
    [line] = [r for r in caplog.records if r.getMessage() == "POST /api/v1/rankings 200"]
    assert line.route == URL  # type: ignore[attr-defined]


def test_chunked_and_large_bodies_go_to_the_route_unchanged(twins: Twins) -> None:
    content = body(twins, joint_positions_rad=twins.configurations(5))
    twins.fast.post(URL, content=content, headers=JSON)  # cached
    before = twins.fast_path().answered
    chunked = twins.fast.post(URL, content=iter([content[:10], content[10:]]), headers=JSON)
    assert chunked.status_code == 200 and twins.fast_path().answered == before
    assert chunked.content == twins.fast.post(URL, content=content, headers=JSON).content
    large = body(twins, joint_positions_rad=twins.configurations(600))  # > 64 KB
    fast, route, answered = twins.both(large, JSON)
    assert fast.status_code == 200 and answered == 0
    assert_same_answer(fast, route)


# --- anything else: exactly the route's answer -------------------------------------------------

_numbers = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False, width=64),
    st.integers(min_value=-(10**20), max_value=10**20),
    st.sampled_from([1e308, -1e308, 1e-320, 0.0, -0.0]),
)
_junk: st.SearchStrategy[Any] = st.one_of(
    st.none(), st.booleans(), st.text(max_size=5), _numbers, st.just([])
)


def _rows(k: int) -> st.SearchStrategy[list[list[Any]]]:
    row = st.one_of(
        st.lists(_numbers, min_size=k, max_size=k),
        st.lists(_numbers, min_size=0, max_size=k + 2),
        st.lists(_junk, min_size=k, max_size=k),
    )
    return st.lists(row, min_size=0, max_size=4)


@st.composite
def requests(draw: st.DrawFn, twins: Twins) -> tuple[bytes, dict[str, str]]:
    k = twins.chain.n_joints
    document: dict[str, Any] = {
        "calibration_id": draw(st.sampled_from([twins.id, "cal_unknown", "", 7])),
        "joint_positions_rad": draw(st.one_of(_rows(k), _junk)),
    }
    if draw(st.booleans()):
        document["payload_kg"] = draw(st.one_of(_numbers, st.lists(_numbers, max_size=3), _junk))
    if draw(st.booleans()):
        document["options"] = draw(
            st.sampled_from(
                [{"top": 0}, {"top": 2}, {"weights": {"kind": "nope"}}, {"uncertainty": "total"}]
            )
        )
    if draw(st.integers(0, 4)) == 0:  # an IK search: slower, so rarer
        document["target"] = {"position_m": [0.5, 0.2, 0.6], "quaternion_xyzw": [0, 0, 0, 1]}
    if draw(st.booleans()):
        document[draw(st.sampled_from(["extra", "configurations"]))] = draw(_junk)
    content = json.dumps(document).encode()
    if draw(st.booleans()):
        content = content[: draw(st.integers(0, len(content)))]  # truncated JSON
    headers = draw(
        st.sampled_from(
            [
                JSON,
                {},
                {"content-type": "text/plain"},
                {"content-type": "application/json; charset=utf-8"},
                {**JSON, "X-API-Key": "kc_wrong"},
                {**JSON, "X-API-Key": twins.key},
                {**JSON, "X-API-Key": ""},
            ]
        )
    )
    return content, headers


@settings(max_examples=60, deadline=None)
@given(data=st.data())
def test_every_request_gets_the_routes_answer(twins: Twins, data: st.DataObject) -> None:
    content, headers = data.draw(requests(twins))
    fast, route, answered = twins.both(content, headers)
    assert_same_answer(fast, route)
    if answered:
        assert fast.status_code == 200
    common = headers.get("content-type") in (None, "application/json") and not headers.get(
        "X-API-Key"
    )
    if common and fast.status_code == 200 and b'"target":null' in fast.content:
        assert answered == 1
