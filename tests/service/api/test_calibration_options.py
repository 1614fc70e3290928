"""Issue 17: every invalid value of every calibration option is a 422 at POST time, naming the
option, before any job exists — those the schema checks and those only the robot can check
(joint names), through the one check of the calibration entry point."""

from __future__ import annotations

import json
from typing import Any

import pytest
from fastapi.testclient import TestClient

from schemas.calibration import CalibrationOptions
from service.cli.flags import CALIBRATION_FLAGS
from tests.service.api.conftest import assert_problem, upload_csv

URL = "/api/v1/calibrations"
ASYMMETRIC = [[1e-6 if i == j else 0.0 for j in range(6)] for i in range(6)]
ASYMMETRIC[0][1] = 1e-7

INVALID: dict[str, list[Any]] = {
    "free_parameters": [["torso"], [], "joint_offsets", ["elbow_joint.qx"]],
    "fixed_parameters": [["elbow"], "compliance", [3]],
    "compliant_joints": [["no_such_joint"], "shoulder_pan_joint", [3]],
    "virtual_axes_at": [["knee"], "elbow_joint"],
    "gravity_base_m_s2": [[0.0, -9.81], [0, 0, "down"], [0, 0, float("nan")]],
    "payload_kg": [-1.0, "heavy", float("inf")],
    "payload_com_m": [[0.0, 0.0], [0, 0, float("-inf")]],
    "rotation_weight_m_per_rad": [0.0, -1.0],
    "outlier_rule": ["2sigma", None],
    "outlier_level": [0.0, 1.0, -0.1],
    "outlier_sigma": [-1.0, "two"],
    "max_iterations": [0, 1001, 2.5],
    "tolerance": [0.0, 1.0, -1e-3],
    "rank_tolerance": [0.0, 1.0],
    "heldout": ["maybe", 2],
    "heldout_method": ["approximate", None, 1],
    "seeds": [[], [-1], ["a"], 3],
    "train_fraction": [0.0, 1.0, 1.5],
    "covariance": ["triangular", None],
    "covariance_solver": ["adam"],
    "covariance_estimator": ["bayes"],
    "covariance_frames": [["elbow"], ["elbow_joint", "elbow_joint"], "elbow_joint", []],
    "covariance_axes": ["twist"],
    "noise_std": [[1e-4, 1e-4], [0, 0, 0, -1e-3, 0, 0]],
    "noise_covariance": [[[1e-6]], ASYMMETRIC, [[0.0] * 6] * 5],
    "measurement": ["sockets", "components:tz,roll", "eye-on-head:knee", "point", "markers"],
    "point_distance_m": [0.0, -0.05, "far"],
}
"""At least one invalid value per option (a new option must be added here)."""

COMBINATIONS = [
    ({"covariance": "full", "covariance_solver": "nnls"}, "covariance_solver"),
    ({"noise_std": [1e-4] * 6, "noise_covariance": ASYMMETRIC}, "not both"),
    ({"free_parameters": ["base"], "fixed_parameters": ["base", "tool"]}, "nothing to calibrate"),
]


def test_every_option_has_invalid_values_here_and_a_cli_flag() -> None:
    assert set(INVALID) == set(CalibrationOptions.model_fields)
    assert set(CALIBRATION_FLAGS) == set(CalibrationOptions.model_fields)


@pytest.fixture(scope="module")
def accepted(tmp_path_factory: pytest.TempPathFactory) -> Any:
    from service.api.app import create_app
    from tests.service.api.conftest import fresh_database_url, make_settings

    folder = tmp_path_factory.mktemp("options")
    with (
        fresh_database_url(folder) as url,
        TestClient(create_app(make_settings(folder, url))) as client,
    ):
        dataset = upload_csv(client).json()
        yield client, dataset["id"]


def _post(client: TestClient, dataset_id: str, options: dict[str, Any]) -> Any:
    body = json.dumps({"dataset_id": dataset_id, "options": options}, allow_nan=True)
    return client.post(URL, content=body, headers={"content-type": "application/json"})


@pytest.mark.parametrize(
    ("field", "value"),
    [(field, value) for field, values in INVALID.items() for value in values],
)
def test_every_invalid_option_is_a_422_before_a_job_exists(
    accepted: tuple[TestClient, str], field: str, value: Any
) -> None:
    client, dataset_id = accepted
    problem = assert_problem(_post(client, dataset_id, {field: value}), 422, field)
    assert "Traceback" not in problem["detail"]
    assert client.get(URL).json()["count"] == 0


@pytest.mark.parametrize(("options", "fragment"), COMBINATIONS)
def test_invalid_combinations_are_a_422_naming_them(
    accepted: tuple[TestClient, str], options: dict[str, Any], fragment: str
) -> None:
    client, dataset_id = accepted
    assert_problem(_post(client, dataset_id, options), 422, fragment)
    assert client.get(URL).json()["count"] == 0
