"""Arbitrary requests never produce a 5xx: every answer is a success or a problem document."""

from __future__ import annotations

import importlib
import math
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

import pytest
import schemathesis
from fastapi.testclient import TestClient
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from schemathesis.checks import not_a_server_error
from schemathesis.python import asgi
from schemathesis.specs.openapi.checks import (
    content_type_conformance,
    response_schema_conformance,
    status_code_conformance,
)

from schemas.ranking import RankingResult
from service.api import create_app
from service.jobs.worker import JobContext
from service.storage import repository
from tests.service.api.conftest import fresh_database_url, make_settings, upload_csv

JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=12), inner, max_size=4)
    ),
    max_leaves=12,
)
PATHS = st.sampled_from(
    [
        "/api/v1/rankings",
        "/api/v1/discoveries",
        "/api/v1/discoveries/{id}",
        "/api/v1/discoveries/{id}/report",
        "/api/v1/datasets",
        "/api/v1/calibrations",
        "/api/v1/robots",
        "/api/v1/datasets/{id}",
        "/api/v1/calibrations/{id}",
        "/api/v1/calibrations/{id}/result",
        "/api/v1/calibrations/{id}/cancel",
        "/api/v1/calibrations/{id}/checks",
        "/api/v1/calibrations/{id}/checks/report",
        "/api/v1/calibrations/{id}/checks/{id}",
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


# --- schemathesis: every operation of /openapi.json, answers checked against the schema -------


def run_queued_job_inline(state: Any, job_id: str) -> None:
    """Run a queued job's function in this process, as a worker would (the fuzzed app has no
    worker processes, so what the fuzzer queues stays queued)."""
    with state.database.session() as session:
        job = repository.claim_next_job(session, "fuzz-inline", ["calibration"])
        assert job is not None and job.id == job_id
        params, tenant = dict(job.params), job.tenant_id
    module, _, function = state.registry["calibration"].target.partition(":")
    ctx = JobContext(job_id, tenant, params, state.files, lambda message: None)
    getattr(importlib.import_module(module), function)(ctx)
    with state.database.session() as session:
        finished = repository.finish_job(
            session, job_id, "fuzz-inline", repository.SUCCEEDED, artifacts=ctx.artifacts
        )
        assert finished is not None


def _openapi_document() -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as folder:
        app = create_app(make_settings(Path(folder), f"sqlite:///{folder}/openapi.db"))
        return app.openapi()


# Loaded at import (schemathesis parametrizes at collection); the requests go to the app of the
# ``fuzzed`` fixture, which has a dataset and a succeeded calibration to steer bodies to.
SCHEMA = schemathesis.openapi.from_dict(_openapi_document())


@dataclass
class Fuzzed:
    client: TestClient
    session: Any  # a requests.Session that calls the same ASGI app in-process
    dataset_id: str
    calibration_id: str


FUZZED: list[Fuzzed] = []


@pytest.fixture(scope="module")
def fuzzed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Fuzzed]:
    folder: Path = tmp_path_factory.mktemp("schemathesis")
    with fresh_database_url(folder) as url:
        app = create_app(make_settings(folder, url, max_request_bytes=256 * 1024))
        with TestClient(app, raise_server_exceptions=False) as client:
            dataset_id = upload_csv(client).json()["id"]
            created = client.post(
                "/api/v1/calibrations",
                json={"dataset_id": dataset_id, "options": {"heldout": False}},
            ).json()
            run_queued_job_inline(app.state.kincal, created["id"])
            body = {"calibration_id": created["id"], "joint_positions_rad": [[0.1] * 6]}
            assert client.post("/api/v1/rankings", json=body).status_code == 200
            # Not entered as a context manager: the TestClient above runs the app's lifespan.
            FUZZED.append(Fuzzed(client, asgi.get_client(app), dataset_id, created["id"]))
            yield FUZZED[-1]
            FUZZED.clear()


UR10_JOINTS = (
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
)


def _six(values: list[Any]) -> list[Any]:
    return (list(values) + [0.0] * 6)[:6]


def _one_kind_of_candidates(body: dict[str, Any]) -> dict[str, Any]:
    """A ranking body the JSON schema cannot promise to be valid made plausible: exactly one
    kind of candidates, rows of the UR10's six joints (the generated values kept)."""
    steered = {k: v for k, v in body.items() if k not in ("configurations", "target")}
    rows = body.get("joint_positions_rad")
    named = body.get("configurations")
    if isinstance(rows, list) and rows and all(isinstance(r, list) for r in rows):
        steered["joint_positions_rad"] = [_six(r) for r in rows]
    elif isinstance(named, list) and named and all(isinstance(c, dict) for c in named):
        steered.pop("joint_positions_rad", None)
        steered["configurations"] = [
            dict(zip(UR10_JOINTS, _six(list(c.values())), strict=True)) for c in named
        ]
    elif isinstance(body.get("target"), dict):
        steered.pop("joint_positions_rad", None)
        # IK costs ~20 ms per candidate: keep the search small
        steered |= {"target": body["target"], "n_candidates": 2, "n_free_rotations": 2}
    return steered


SCHEMA_CHECKS = [
    not_a_server_error,
    status_code_conformance,
    content_type_conformance,
    response_schema_conformance,
]
"""What every fuzzed answer must pass: no 5xx, a documented status, content type and body."""


def steered_bodies(
    body: Any, dataset_id: str, calibration_id: str, *, plausible_rankings: bool
) -> st.SearchStrategy[Any]:
    """The generated body or, half of the time, the same body naming the seeded dataset /
    calibration (and, if ``plausible_rankings``, ranking bodies made plausible), so that the
    fuzzer gets past the 404s into validation and the work."""
    if not isinstance(body, dict):
        return st.just(body)
    steered = dict(body)
    if "calibration_id" in body:
        steered = _one_kind_of_candidates(body) if plausible_rankings else steered
        steered["calibration_id"] = calibration_id
    if "dataset_id" in body:
        steered["dataset_id"] = dataset_id
    return st.sampled_from([body, steered])


@SCHEMA.hook
def flatmap_body(context: Any, body: Any) -> st.SearchStrategy[Any]:
    if not FUZZED:
        return st.just(body)
    seeded = FUZZED[-1]
    return steered_bodies(body, seeded.dataset_id, seeded.calibration_id, plausible_rankings=True)


@SCHEMA.hook
def flatmap_path_parameters(context: Any, path_parameters: Any) -> st.SearchStrategy[Any]:
    """A check's routes half of the time on the seeded calibration, so that the fuzzer gets
    past the 404 to the dataset and the refusals (it has no predictive covariance: 409)."""
    operation = context.operation
    if (
        not FUZZED
        or operation is None
        or "/checks" not in operation.path
        or not isinstance(path_parameters, dict)
        or "calibration_id" not in path_parameters
    ):
        return st.just(path_parameters)
    steered = {**path_parameters, "calibration_id": FUZZED[-1].calibration_id}
    return st.sampled_from([path_parameters, steered])


@SCHEMA.parametrize()
@settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
def test_openapi_operations_never_5xx_and_match_their_schema(case: Any, fuzzed: Fuzzed) -> None:
    response = case.call(session=fuzzed.session, base_url=f"http://{asgi.HOST}")
    case.validate_response(response, checks=SCHEMA_CHECKS)


# --- rankings: well-formed bodies with extreme values reach the maths, never a 5xx or a NaN ----

HUGE = st.floats(min_value=-1e300, max_value=1e300, allow_nan=False)
NON_NEGATIVE = st.floats(min_value=0.0, max_value=1e300, allow_nan=False)
WEIGHTS = st.one_of(
    st.builds(
        lambda d, scale: {"kind": "pose", "diagonal": d, "rotation_scale_m_per_rad": scale},
        st.lists(NON_NEGATIVE, min_size=6, max_size=6),
        st.floats(min_value=1e-300, max_value=1e300),
    ),
    st.builds(
        lambda m: {"kind": "pose", "matrix": m},
        st.lists(st.lists(HUGE, min_size=6, max_size=6), min_size=6, max_size=6),
    ),
    st.builds(
        lambda p, w: {"kind": "task_point", "point_m": p, "axis_weights": w},
        st.lists(HUGE, min_size=3, max_size=3),
        st.lists(NON_NEGATIVE, min_size=3, max_size=3),
    ),
)


@settings(
    max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(
    rows=st.lists(
        st.lists(st.floats(min_value=-1e4, max_value=1e4), min_size=6, max_size=6),
        min_size=1,
        max_size=12,
    ),
    named=st.booleans(),
    payload=st.none() | st.floats(min_value=0.0, max_value=1e5),
    weights=WEIGHTS,
    include_noise=st.booleans(),
    top=st.none() | st.integers(min_value=1, max_value=20),
)
def test_well_formed_rankings_with_extreme_values_answer_200_or_422(
    fuzzed: Fuzzed,
    rows: list[list[float]],
    named: bool,
    payload: float | None,
    weights: dict[str, Any],
    include_noise: bool,
    top: int | None,
) -> None:
    body: dict[str, Any] = {
        "calibration_id": fuzzed.calibration_id,
        "payload_kg": payload,
        "options": {"weights": weights, "include_noise": include_noise, "top": top},
    }
    if named:
        body["configurations"] = [dict(zip(UR10_JOINTS, row, strict=True)) for row in rows]
    else:
        body["joint_positions_rad"] = rows
    response = fuzzed.client.post("/api/v1/rankings", json=body)
    _check(response)
    assert response.status_code in (200, 422), response.text
    if response.status_code == 200:
        ranking = RankingResult.model_validate_json(response.content)
        scores = [entry.score for entry in ranking.ranking]
        assert all(math.isfinite(v) for v in scores) and scores == sorted(scores)
        assert len(scores) == min(len(rows), top or len(rows))
