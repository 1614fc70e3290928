"""POST /api/v1/designs: synchronous for small candidate sets, a job beyond; problem+json."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from fastapi.testclient import TestClient

from schemas.design import DesignOptions
from schemas.robots import load_robot
from service.api import designs
from service.app.design import run_design
from tests.service.api.conftest import (
    assert_problem,
    client_api,
    new_key,
    recording_bytes,
    upload_csv,
)
from tests.service.api.test_jobs import worker_client  # noqa: F401  (fixture)
from tests.service.cli_support import run

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
    job = _wait(client, response.headers["Location"])
    assert job["status"]["state"] == "succeeded", job
    result = client.get(job["links"]["result"])
    assert result.status_code == 200
    assert len(result.json()["poses"]) == 8


def _wait(client: TestClient, location: str) -> dict[str, Any]:
    deadline = time.monotonic() + 120
    while True:
        job: dict[str, Any] = client.get(location).json()
        if job["status"]["state"] in ("succeeded", "failed"):
            return job
        assert time.monotonic() < deadline, job
        time.sleep(0.1)


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


# --- sequential designs: calibration_id -------------------------------------------------------


class Calibrated:
    """A calibrated recording (tenant 'local'), its result and recording as files, and a key
    of another tenant."""

    def __init__(self, client: TestClient, folder: Path) -> None:
        self.client = client
        api = client_api(client)
        dataset = upload_csv(client).json()
        job = api.start_calibration(dataset["id"], {"heldout": False})
        api.wait(job["id"], poll_s=0.05)
        self.id = job["id"]
        self.result_path = folder / "result.json"
        self.result_path.write_text(api.result(self.id).model_dump_json(), encoding="utf-8")
        self.recording_path = folder / "recording.csv"
        self.recording_path.write_bytes(recording_bytes())
        self.other_tenant_key = new_key(client, "other-lab")

    def design(self, options: dict[str, Any], **body: Any) -> dict[str, Any]:
        request = {"calibration_id": self.id, "options": options, **body}
        response = self.client.post("/api/v1/designs", json=request)
        assert response.status_code == 200, response.text
        return response.json()  # type: ignore[no-any-return]


@pytest.fixture(scope="module")
def calibrated(
    worker_client: TestClient,  # noqa: F811
    tmp_path_factory: pytest.TempPathFactory,
) -> Calibrated:
    return Calibrated(worker_client, tmp_path_factory.mktemp("sequential"))


SEQUENTIAL = {"n_poses": 5, "n_candidates": 150, "seed": 1}


def test_sequential_design_is_the_clis(
    calibrated: Calibrated,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """calibration_id gives the poses ``kincal design --result --recording`` gives for that
    calibration's result and recording, with the same criterion."""
    document = calibrated.design(SEQUENTIAL)
    output = tmp_path / "next.json"
    code, _, stderr = run(
        [
            "design", "--result", calibrated.result_path, "--recording",
            calibrated.recording_path, "--poses", "5", "--n-candidates", "150", "--seed", "1",
            "-o", output,
        ],
        capsys,
        monkeypatch,
    )  # fmt: skip
    assert code == 0, stderr
    cli = json.loads(output.read_text())
    assert document["sequential"]["recorded_poses"] == cli["sequential"]["recorded_poses"] == 40
    assert [p["candidate"] for p in document["poses"]] == [p["candidate"] for p in cli["poses"]]
    assert document["criterion"]["value"] == pytest.approx(cli["criterion"]["value"], rel=1e-9)
    assert document["parameters"] == cli["parameters"]


def test_sequential_design_adds_to_the_recording(calibrated: Calibrated) -> None:
    """The next poses are chosen for what the recording already holds (criterion I: the
    parameter part of the predicted pose variance over the task configurations, in m² + rad²,
    which unlike the criterion's value does not depend on the candidates' equilibration):
    the recording plus them predicts a lower variance than the recording alone and than the
    recording plus any of 10 random draws of as many of the same candidates (each scored by
    giving it as the candidate set)."""
    options = {**SEQUENTIAL, "criterion": "I"}
    document = calibrated.design(options)
    variance = document["mean_pose_variance_m2"]
    assert document["criterion"]["value"] <= document["criterion"]["upper_bound"] + 1e-12
    before = document["sequential"]["mean_pose_variance_before_m2"]
    assert before is not None and variance < before
    everything = calibrated.design({**options, "n_poses": SEQUENTIAL["n_candidates"]})
    pool = [p["joint_positions"] for p in everything["poses"]]  # the 150 candidates
    chosen = [pool[p["candidate"]] for p in document["poses"]]
    assert chosen == [p["joint_positions"] for p in document["poses"]]

    def with_recording(rows: list[list[float]]) -> float:
        forced = calibrated.design({**options, "n_poses": len(rows)}, candidates_rad=rows)
        return float(forced["mean_pose_variance_m2"])

    assert with_recording(chosen) == pytest.approx(variance, rel=1e-9)
    rng = np.random.default_rng(0)
    draws = [rng.choice(len(pool), 5, replace=False) for _ in range(10)]
    assert variance < min(with_recording([pool[i] for i in draw]) for draw in draws)


def test_large_sequential_design_runs_as_a_job(
    calibrated: Calibrated, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Candidates plus recorded configurations decide: 100 candidates + 40 recorded > 120."""
    monkeypatch.setattr(designs, "SYNC_MAX_CANDIDATES", 120)
    body = {"calibration_id": calibrated.id, "options": {**SEQUENTIAL, "n_candidates": 100}}
    response = calibrated.client.post("/api/v1/designs", json=body)
    assert response.status_code == 202, response.text
    job = _wait(calibrated.client, response.headers["Location"])
    assert job["status"]["state"] == "succeeded", job
    result = calibrated.client.get(job["links"]["result"]).json()
    assert result["sequential"]["recorded_poses"] == 40
    assert len(result["poses"]) == 5


def test_sequential_bad_requests(calibrated: Calibrated) -> None:
    """Each refusal names the field and what to do; another tenant's calibration is 404."""
    client, url = calibrated.client, "/api/v1/designs"
    body = {"calibration_id": calibrated.id, "options": SEQUENTIAL}
    for field, extra in (
        ("robot", {"robot": "ur10"}),
        ("tip_frame", {"tip_frame": "tool0"}),
        ("options.calibration", {"options": {**SEQUENTIAL, "calibration": {"heldout": True}}}),
    ):
        problem = assert_problem(client.post(url, json={**body, **extra}), 422, field, "leave")
        assert problem["errors"][0]["location"] == f"body.{field}"
    assert_problem(client.post(url, json={"options": SEQUENTIAL}), 422, "robot", "calibration_id")
    unknown = {**body, "calibration_id": "cal_nope"}
    assert_problem(client.post(url, json=unknown), 404, "calibration_id", "cal_nope")
    headers = {"X-API-Key": calibrated.other_tenant_key}
    assert_problem(client.post(url, json=body, headers=headers), 404, calibrated.id)
    wrong = {**body, "candidates_rad": [[0.0, 1.0]]}
    assert_problem(client.post(url, json=wrong), 422, "candidates_rad.0", "6")


def test_sequential_design_of_an_unfinished_calibration_is_409(client: TestClient) -> None:
    """No worker here: the calibration stays queued."""
    dataset = upload_csv(client).json()
    job = client_api(client).start_calibration(dataset["id"], {"heldout": False})
    body = {"calibration_id": job["id"], "options": SEQUENTIAL}
    problem = assert_problem(client.post("/api/v1/designs", json=body), 409, "queued", "poll")
    assert problem["type"].endswith("not-ready")


def test_sequential_design_after_its_dataset_was_deleted_is_409(calibrated: Calibrated) -> None:
    """The recording is part of a sequential design: once deleted, the problem says so."""
    client = calibrated.client
    api = client_api(client)
    dataset = upload_csv(client, recording_bytes(seed=3)).json()
    job = api.start_calibration(dataset["id"], {"heldout": False, "covariance": "none"})
    api.wait(job["id"], poll_s=0.05)
    assert client.delete(f"/api/v1/datasets/{dataset['id']}").status_code == 204
    body = {"calibration_id": job["id"], "options": SEQUENTIAL}
    problem = assert_problem(client.post("/api/v1/designs", json=body), 409, "dataset", "upload")
    assert problem["type"].endswith("no-dataset")
