"""POST /api/v1/rankings: the same ranking as ``kincal rank`` (one pipeline), by rows, by
named configurations and by target pose; 404 / 409 / 413 / 422 problems for everything else."""

from __future__ import annotations

import json
import random
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
import pytest
from fastapi.testclient import TestClient

from schemas.calibration import CalibrationResult
from schemas.ranking import RankingOptions, RankingResult, TargetPose, TargetRankingRequest
from service import cli
from service.api import create_app
from service.api.client import KincalAPIError, KincalClient
from service.app import rank as ranking
from service.render import result_json
from solver import lie
from solver.model import sample_configurations
from tests.service.api.conftest import (
    AppFactory,
    assert_problem,
    client_api,
    fresh_database_url,
    make_settings,
    new_key,
    upload_csv,
)

URL = "/api/v1/rankings"


class Calibrated:
    """One app with a worker, a calibration with covariances and one without (tenant 'local'),
    and a key of another tenant."""

    def __init__(self, client: TestClient) -> None:
        self.client = client
        self.api = client_api(client)
        dataset = upload_csv(client).json()
        with_cov = self.api.start_calibration(dataset["id"], {"heldout": False})
        without = self.api.start_calibration(
            dataset["id"], {"heldout": False, "covariance": "none"}
        )
        self.api.wait(with_cov["id"], poll_s=0.05)
        self.api.wait(without["id"], poll_s=0.05)
        self.id = with_cov["id"]
        self.no_covariance_id = without["id"]
        self.result = self.api.result(self.id)
        self.chain, _ = result_json.result_chain(self.result)
        self.other_tenant_key = new_key(client, "other-lab")

    def configurations(self, n: int, seed: int = 5) -> np.ndarray:
        return sample_configurations(self.chain, n, np.random.default_rng(seed), 0.8)


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Calibrated]:
    folder = tmp_path_factory.mktemp("rankings")
    with fresh_database_url(folder) as url:
        settings = make_settings(folder, url, workers=1)
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            yield Calibrated(client)


def _cli_rank(
    result: CalibrationResult, args: list[str], folder: Path, monkeypatch: pytest.MonkeyPatch
) -> RankingResult:
    result_path = folder / "result.json"
    result_path.write_text(result.model_dump_json(), encoding="utf-8")
    output = folder / "ranking.json"
    monkeypatch.setattr(sys, "argv", ["kincal", "rank", str(result_path), *args, "-o", str(output)])
    with pytest.raises(SystemExit) as exit_info:
        cli.main()
        raise SystemExit(0)
    assert exit_info.value.code in (0, None)
    return RankingResult.model_validate_json(output.read_text(encoding="utf-8"))


# --- the same ranking as the CLI and the pipeline ----------------------------------------------


def test_ranking_by_joint_positions_equals_kincal_rank(
    calibrated: Calibrated, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    q = calibrated.configurations(40)
    over_http = calibrated.api.rank(calibrated.id, q.tolist())
    configs = tmp_path / "configs.csv"
    frame = pd.DataFrame(q, columns=list(calibrated.chain.joint_names))
    frame.to_csv(configs, index=False, float_format="%.17g")
    from_cli = _cli_rank(calibrated.result, [str(configs)], tmp_path, monkeypatch)

    assert over_http == from_cli  # every score, the order, the calibration reference
    assert over_http.n_configurations == 40 and len(over_http.ranking) == 40
    scores = [entry.score for entry in over_http.ranking]
    assert scores == sorted(scores) and len(set(scores)) > 1
    assert over_http.best_index == over_http.ranking[0].index
    assert over_http.calibration.covariance_structure == "diag"


def test_weights_top_and_payload_are_passed_through_like_the_cli(
    calibrated: Calibrated, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    q = calibrated.configurations(25, seed=8)
    options = {"weights": {"kind": "task_point", "point_m": [0.0, 0.0, 0.05]}, "top": 5}
    over_http = calibrated.api.rank(calibrated.id, q.tolist(), options=options, payload_kg=1.5)
    configs = tmp_path / "configs.csv"
    pd.DataFrame(q, columns=list(calibrated.chain.joint_names)).to_csv(
        configs, index=False, float_format="%.17g"
    )
    args = [str(configs), "--task-point", "0,0,0.05", "--top", "5", "--payload-kg", "1.5"]
    assert over_http == _cli_rank(calibrated.result, args, tmp_path, monkeypatch)
    assert len(over_http.ranking) == 5 and over_http.score_unit == "m²"

    default = calibrated.api.rank(calibrated.id, q.tolist(), options={"top": 5})
    assert [e.score for e in default.ranking] != [e.score for e in over_http.ranking]


def test_total_uncertainty_is_scored_like_kincal_rank_and_adds_its_parts(
    calibrated: Calibrated, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Issue 13: options.uncertainty 'total' scores Σ_E + J_θ Cov(θ̂) J_θᵀ + the model-error
    part; each entry's score is the sum of its parts, the random-effects part is the default
    ranking's score, and the answer equals ``kincal rank --uncertainty total``."""
    q = calibrated.configurations(30, seed=12)
    total = calibrated.api.rank(calibrated.id, q.tolist(), options={"uncertainty": "total"})
    default = calibrated.api.rank(calibrated.id, q.tolist())
    configs = tmp_path / "configs.csv"
    pd.DataFrame(q, columns=list(calibrated.chain.joint_names)).to_csv(
        configs, index=False, float_format="%.17g"
    )
    args = [str(configs), "--uncertainty", "total"]
    assert total == _cli_rank(calibrated.result, args, tmp_path, monkeypatch)
    assert total.uncertainty == "total" and default.uncertainty == "random_effects"
    paper = {e.index: e.score for e in default.ranking}
    assert all(e.score_parts is None for e in default.ranking)
    for entry in total.ranking:
        parts = entry.score_parts
        assert parts is not None and set(parts) == {"random_effects", "parameters", "model_error"}
        assert parts["random_effects"] == pytest.approx(paper[entry.index], rel=1e-12)
        assert parts["parameters"] > 0.0 and parts["model_error"] >= 0.0
        assert entry.score == pytest.approx(sum(parts.values()), rel=1e-12)
    scores = [e.score for e in total.ranking]
    assert scores == sorted(scores)


def test_weights_kind_may_be_left_out(calibrated: Calibrated) -> None:
    q = calibrated.configurations(8, seed=10).tolist()
    for weights, kind in (
        ({"diagonal": [1.0, 1.0, 0.0, 0.0, 0.0, 0.0]}, "pose"),
        ({"point_m": [0.0, 0.0, 0.05]}, "task_point"),
    ):
        implicit = calibrated.api.rank(calibrated.id, q, options={"weights": weights})
        explicit = calibrated.api.rank(
            calibrated.id, q, options={"weights": {"kind": kind, **weights}}
        )
        assert implicit == explicit and implicit.weights.kind == kind


def test_payload_per_configuration(calibrated: Calibrated) -> None:
    q = calibrated.configurations(6, seed=9)
    payload = [0.0, 0.5, 1.0, 2.0, 3.0, 4.0]
    over_http = calibrated.api.rank(calibrated.id, q.tolist(), payload_kg=payload)
    direct = ranking.rank_configurations(
        calibrated.result, q, RankingOptions(), payload_kg=np.array(payload)
    )
    assert over_http.ranking == direct.ranking


@pytest.mark.parametrize(
    ("options", "payload"),
    [
        ({}, None),
        ({"top": 3, "include_noise": True}, 1.5),
        ({"weights": {"kind": "task_point", "point_m": [0.0, 0.01, 0.05]}}, "per row"),
        ({"weights": {"matrix": np.eye(6).tolist(), "rotation_scale_m_per_rad": 0.2}}, None),
    ],
)
def test_served_bytes_are_the_ranking_models_json(
    calibrated: Calibrated, options: dict[str, Any], payload: Any
) -> None:
    """The hot path serialises plain dicts (no model per entry): the same bytes as the
    validated RankingResult's JSON, the documented response schema."""
    q = calibrated.configurations(30, seed=12)
    payload_kg = np.linspace(0.0, 2.0, 30) if payload == "per row" else payload
    ranking_options = RankingOptions.model_validate(options)
    served = ranking.rank_configurations_json(
        calibrated.result, q, ranking_options, payload_kg=payload_kg, require_finite=True
    )
    model = ranking.rank_configurations(
        calibrated.result, q, ranking_options, payload_kg=payload_kg
    )
    assert served == model.model_dump_json().encode()
    body = {"calibration_id": calibrated.id, "joint_positions_rad": q.tolist(), "options": options}
    if payload is not None:
        body["payload_kg"] = payload_kg.tolist() if payload == "per row" else payload_kg
    response = calibrated.client.post(URL, json=body)
    assert response.status_code == 200 and response.content == served


def test_non_finite_scores_are_refused_only_when_asked(calibrated: Calibrated) -> None:
    q = calibrated.configurations(4, seed=13)
    huge = RankingOptions.model_validate({"weights": {"diagonal": [1e300] * 6}})
    with pytest.raises(ranking.NonFiniteScoreError) as refused:
        ranking.rank_configurations_json(calibrated.result, q, huge, require_finite=True)
    assert refused.value.index in range(4)
    kept = ranking.rank_configurations(calibrated.result, q, huge)
    assert not np.isfinite(kept.ranking[-1].score)


def test_ranking_by_named_configurations_equals_ranking_by_rows(calibrated: Calibrated) -> None:
    q = calibrated.configurations(12, seed=6)
    names = list(calibrated.chain.joint_names)
    shuffled = random.Random(1).sample(names, len(names))
    named = [{name: float(row[names.index(name)]) for name in shuffled} for row in q]
    by_name = calibrated.api.rank(calibrated.id, configurations=named)
    by_rows = calibrated.api.rank(calibrated.id, q.tolist())
    assert by_name == by_rows
    assert by_name.joint_names == names


def test_ranking_ik_candidates_of_a_target_pose_equals_the_pipeline(
    calibrated: Calibrated, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    reachable = calibrated.configurations(1, seed=11)
    pose = result_json.predict_poses(calibrated.result, reachable)[0]  # measurement frame
    position = pose[:3, 3].tolist()
    quaternion = lie.matrix_to_quaternion_xyzw(pose[:3, :3]).tolist()
    target = TargetPose(position_m=position, quaternion_xyzw=quaternion)

    over_http = calibrated.api.rank(calibrated.id, target=target, n_candidates=6, seed=3)
    direct = ranking.rank_target(
        calibrated.result, TargetRankingRequest(target=target, n_candidates=6, seed=3)
    )
    assert over_http == direct
    assert over_http.target == target and over_http.free_axis is not None
    assert 1 <= len(over_http.ranking) <= 6
    for entry in over_http.ranking:
        assert entry.joint_positions_rad is not None and len(entry.joint_positions_rad) == 6
        assert entry.ik_translation_error_m is not None and entry.ik_translation_error_m < 1e-6
    scores = [entry.score for entry in over_http.ranking]
    assert scores == sorted(scores)

    target_flag = ",".join(str(v) for v in (*position, *quaternion))
    args = ["--target", target_flag, "--n-candidates", "6", "--seed", "3"]
    assert over_http == _cli_rank(calibrated.result, args, tmp_path, monkeypatch)


def test_a_cached_ranking_needs_no_database(
    calibrated: Calibrated, monkeypatch: pytest.MonkeyPatch
) -> None:
    q = calibrated.configurations(3).tolist()
    first = calibrated.api.rank(calibrated.id, q)
    state = calibrated.client.app.state.kincal  # type: ignore[attr-defined]

    def no_database(*args: object) -> None:
        raise AssertionError("a cached ranking must not query the database")

    monkeypatch.setattr(state.database, "sessions", no_database)
    monkeypatch.setattr(state.database, "session", no_database)
    assert calibrated.api.rank(calibrated.id, q) == first


# --- tenants, ids and states -------------------------------------------------------------------


def test_unknown_or_another_tenants_calibration_is_404(calibrated: Calibrated) -> None:
    row = [calibrated.configurations(1)[0].tolist()]
    body = {"calibration_id": "cal_does_not_exist", "joint_positions_rad": row}
    assert_problem(calibrated.client.post(URL, json=body), 404, "cal_does_not_exist")

    calibrated.api.rank(calibrated.id, row)  # cached for its owner now
    other = KincalClient(api_key=calibrated.other_tenant_key, client=calibrated.client)
    with pytest.raises(KincalAPIError) as error:
        other.rank(calibrated.id, row)
    assert error.value.status == 404 and calibrated.id in error.value.problem["detail"]
    assert "ur10" not in json.dumps(error.value.problem)  # nothing about the calibration leaks
    headers = {"X-API-Key": calibrated.other_tenant_key}
    body = {"calibration_id": calibrated.id, "joint_positions_rad": row}
    assert_problem(calibrated.client.post(URL, json=body, headers=headers), 404, calibrated.id)
    assert_problem(
        calibrated.client.post(URL, json=body, headers={"X-API-Key": "kc_wrong"}), 401, "X-API-Key"
    )


def test_calibration_without_covariances_is_409(calibrated: Calibrated) -> None:
    body = {
        "calibration_id": calibrated.no_covariance_id,
        "joint_positions_rad": [calibrated.configurations(1)[0].tolist()],
    }
    problem = assert_problem(calibrated.client.post(URL, json=body), 409, "covariance")
    assert "'diag' or 'full'" in problem["detail"]


def test_calibration_not_finished_is_409(client: TestClient) -> None:
    dataset = upload_csv(client).json()
    queued = client.post("/api/v1/calibrations", json={"dataset_id": dataset["id"]}).json()
    body = {"calibration_id": queued["id"], "joint_positions_rad": [[0.0] * 6]}
    assert_problem(client.post(URL, json=body), 409, "queued", "poll")


# --- limits and malformed candidates -----------------------------------------------------------


def test_too_many_candidates_is_413(make_client: AppFactory) -> None:
    client = make_client(max_ranking_candidates=5)
    body = {"calibration_id": "cal_any", "joint_positions_rad": [[0.0] * 6] * 6}
    assert_problem(client.post(URL, json=body), 413, "6 candidate configurations", "limit of 5")
    named = {"calibration_id": "cal_any", "configurations": [{"j": 0.0}] * 6}
    assert_problem(client.post(URL, json=named), 413, "limit of 5")
    assert client.get("/healthz").status_code == 200


NAN_BODY = b'{"calibration_id": "%s", "joint_positions_rad": [[0, 0, NaN, 0, 0, 0]]}'


@pytest.mark.parametrize(
    ("change", "fragments"),
    [
        ({"joint_positions_rad": [[0.1] * 5]}, ["joint_positions_rad.0", "has 5", "has 6"]),
        (
            {"joint_positions_rad": [[0.1] * 6, [0.1] * 7]},
            ["joint_positions_rad.1", "row 1 has 7", "shoulder_pan_joint"],
        ),
        ({"joint_positions_rad": []}, ["joint_positions_rad"]),
        ({"joint_positions_rad": [[1e6] * 6]}, ["joint_positions_rad.0.0", "10000"]),
        ({"configurations": [{"elbow": 0.0}]}, ["configurations.0", "unknown joint(s) elbow"]),
        (
            {"configurations": [{"shoulder_pan_joint": 0.0}]},
            ["configurations.0", "missing joint(s)", "wrist_3_joint"],
        ),
        ({}, ["exactly one of joint_positions_rad, configurations or target"]),
        (
            {"joint_positions_rad": [[0.0] * 6], "configurations": [{"a": 0.0}]},
            ["exactly one", "got joint_positions_rad, configurations"],
        ),
        (
            {"joint_positions_rad": [[0.0] * 6] * 3, "payload_kg": [1.0, 2.0]},
            ["payload_kg", "2 values for 3"],
        ),
        ({"joint_positions_rad": [[0.0] * 6], "payload_kg": -1}, ["payload_kg"]),
        (
            {"target": {"position_m": [0.5, 0, 0.5], "quaternion_xyzw": [0, 0, 0, 2]}},
            ["target", "unit norm"],
        ),
        (
            {"target": {"position_m": [50.0, 0, 0], "quaternion_xyzw": [0, 0, 0, 1]}},
            ["target", "reaches the target"],
        ),
        (
            {
                "target": {"position_m": [0.5, 0, 0.5], "quaternion_xyzw": [0, 0, 0, 1]},
                "n_candidates": 65,
            },
            ["n_candidates", "64"],
        ),
        (
            {"joint_positions_rad": [[0.0] * 6], "options": {"weights": {"diagonal": [1] * 5}}},
            ["options.weights"],
        ),
        (
            {
                "joint_positions_rad": [[0.3] * 6],
                "options": {"weights": {"kind": "pose", "diagonal": [1e300] * 6}},
            },
            ["not a finite number", "options.weights"],
        ),
        ({"joint_positions_rad": [[0.0] * 6], "unknown_field": 1}, ["unknown_field"]),
    ],
)
def test_bad_candidates_are_422_naming_the_field(
    calibrated: Calibrated, change: dict[str, Any], fragments: list[str]
) -> None:
    body = {"calibration_id": calibrated.id, **change}
    assert_problem(calibrated.client.post(URL, json=body), 422, *fragments)


def test_nan_and_infinity_are_422(calibrated: Calibrated) -> None:
    for literal in (b"NaN", b"Infinity", b"-Infinity"):
        content = NAN_BODY.replace(b"NaN", literal) % calibrated.id.encode()
        response = calibrated.client.post(
            URL, content=content, headers={"content-type": "application/json"}
        )
        assert_problem(response, 422, "joint_positions_rad.0.2", "finite")
    assert calibrated.client.get("/healthz").status_code == 200


def test_body_that_is_not_json_is_a_problem(calibrated: Calibrated) -> None:
    post = calibrated.client.post
    assert_problem(post(URL, content=b"{not json"), 422, "body", "Invalid JSON")
    assert_problem(post(URL, content=b"\xff\xfe"), 422, "body", "Invalid JSON")
    text = {"content-type": "text/plain"}
    assert_problem(post(URL, content=b"{}", headers=text), 415, "application/json")
    documented = calibrated.client.get("/openapi.json").json()["paths"][URL]["post"]
    schema = documented["requestBody"]["content"]["application/json"]["schema"]
    assert "$ref" not in json.dumps(schema) and "joint_positions_rad" in schema["properties"]
    assert {"404", "409", "413", "415", "422"} <= set(documented["responses"])


def test_a_slow_ik_search_does_not_stall_other_rankings(calibrated: Calibrated) -> None:
    """Target rankings run in a thread: a row ranking answers while one is searching."""
    import threading

    target = {"position_m": [0.5, 0.2, 0.6], "quaternion_xyzw": [0, 0, 0, 1]}
    body = {"calibration_id": calibrated.id, "target": target, "n_candidates": 64}
    done: list[float] = []

    def search() -> None:
        calibrated.client.post(URL, json=body)
        done.append(time.monotonic())

    q = calibrated.configurations(10).tolist()
    calibrated.api.rank(calibrated.id, q)  # warm
    thread = threading.Thread(target=search)
    thread.start()
    time.sleep(0.05)
    answered = []
    while thread.is_alive() and len(answered) < 5:
        calibrated.api.rank(calibrated.id, q)
        answered.append(time.monotonic())
    thread.join()
    assert answered and done and answered[0] < done[0]
