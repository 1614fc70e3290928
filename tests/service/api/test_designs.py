"""POST /api/v1/designs: synchronous for small candidate sets, a job beyond; problem+json."""

from __future__ import annotations

import time
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from schemas.design import DesignOptions
from service.api import designs
from service.design import run_design
from service.robots import load_robot
from tests.service.api.conftest import assert_problem
from tests.service.api.test_jobs import worker_client  # noqa: F401  (fixture)

BODY: dict[str, Any] = {
    "robot": "kinova",
    "options": {"n_poses": 8, "n_candidates": 150, "seed": 1},
}


def test_small_design_is_answered_in_the_request(client: TestClient) -> None:
    response = client.post("/api/v1/designs", json=BODY)
    assert response.status_code == 200, response.text
    document = response.json()
    assert document["format"] == "kincal.design/1"
    assert len(document["poses"]) == 8
    assert document["criterion"]["value"] <= document["criterion"]["upper_bound"] + 1e-12
    assert all(p["standard_error"] > 0 for p in document["parameters"])


def test_given_candidates_and_same_answer_as_the_cli_pipeline(client: TestClient) -> None:
    candidates = []
    for seed in (1, 2):
        options = {**BODY["options"], "seed": seed}
        first = client.post("/api/v1/designs", json={**BODY, "options": options}).json()
        candidates += [p["joint_positions"] for p in first["poses"]]
    body = {**BODY, "candidates_rad": candidates}
    response = client.post("/api/v1/designs", json=body)
    assert response.status_code == 200, response.text
    document = response.json()
    assert document["candidate_source"] == "given"
    direct = run_design(
        load_robot("kinova"), DesignOptions(**BODY["options"]), candidates=np.array(candidates)
    )
    assert [p["candidate"] for p in document["poses"]] == [p.candidate for p in direct.poses]
    assert document["criterion"]["value"] == pytest.approx(direct.criterion.value, rel=1e-9)


def test_large_design_runs_as_a_job(
    worker_client: TestClient,  # noqa: F811
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    client = worker_client
    monkeypatch.setattr(designs, "SYNC_MAX_CANDIDATES", 100)
    response = client.post("/api/v1/designs", json=BODY)
    assert response.status_code == 202, response.text
    location = response.headers["Location"]
    deadline = time.monotonic() + 120
    while True:
        job = client.get(location).json()
        if job["status"]["state"] in ("succeeded", "failed"):
            break
        assert time.monotonic() < deadline, job
        time.sleep(0.1)
    assert job["status"]["state"] == "succeeded", job
    result = client.get(job["links"]["result"])
    assert result.status_code == 200
    assert len(result.json()["poses"]) == 8


@pytest.mark.parametrize(
    ("body", "status", "fragment"),
    [
        ({**BODY, "options": {"n_poses": 0}}, 422, "n_poses"),
        ({**BODY, "options": {"n_poses": 3}}, 422, "choose at least"),
        ({**BODY, "options": {"criterion": "X"}}, 422, "criterion"),
        ({**BODY, "options": {"box": {"low_m": [1, 1, 1], "high_m": [0, 0, 0]}}}, 422, "box"),
        ({**BODY, "robot": "nope"}, 422, "unknown robot"),
        ({**BODY, "candidates_rad": [[0.0, 1.0]]}, 422, "candidates_rad.0"),
        ({**BODY, "candidates_rad": [[9.0] * 6] * 10}, 422, "outside its limits"),
        (
            {
                **BODY,
                "options": {"n_candidates": 5, "box": {"low_m": [5, 5, 5], "high_m": [6, 6, 6]}},
            },
            422,
            "working volume",
        ),
    ],
)
def test_bad_requests_are_problems(
    client: TestClient, body: dict[str, Any], status: int, fragment: str
) -> None:
    assert_problem(client.post("/api/v1/designs", json=body), status, fragment)
