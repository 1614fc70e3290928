"""Issue 13: the HTTP status of a calibration carries its verdict, and the URDF of a failed
calibration is withheld unless forced — through the routes, with a real worker."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from schemas.calibration import CalibrationOptions
from schemas.robots import example_robot_data_dir
from service.api.app import create_app
from tests.service.api.conftest import (
    assert_problem,
    client_api,
    fresh_database_url,
    make_settings,
    upload_csv,
)

TIAGO_WITH_RPY = (
    Path(__file__).resolve().parents[3]
    / "data/real/figaroh_tiago_mocap/vicon/relative_encoder"
    / "vicon_calibration_fc10_gripper3_base1_withrpy.csv"
)


@pytest.fixture(scope="module")
def worker_client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[TestClient]:
    folder = tmp_path_factory.mktemp("verdict")
    with fresh_database_url(folder) as url:
        settings = make_settings(folder, url, workers=1)
        with TestClient(create_app(settings), raise_server_exceptions=False) as client:
            yield client


def test_failed_verdict_is_in_the_status_and_withholds_the_urdf(
    worker_client: TestClient,
) -> None:
    """The TIAGo Vicon file with roll-pitch-yaw (orientations the arm cannot explain, held-out
    worse than before): GET of the job and its list entry say failed with the causes; the
    URDF is refused (409 naming them) unless ?force=true."""
    urdf = example_robot_data_dir() / "robots/tiago_description/robots/tiago.urdf"
    body = {
        "name": "tiago",
        "base_frame": "base_footprint",
        "tip_frame": "arm_7_link",
        "urdf": urdf.read_text(),
    }
    robot = worker_client.post("/api/v1/robots", json=body)
    assert robot.status_code == 201, robot.text
    dataset = upload_csv(
        worker_client,
        TIAGO_WITH_RPY.read_bytes(),
        filename=TIAGO_WITH_RPY.name,
        robot_name=robot.json()["id"],
    )
    assert dataset.status_code == 201, dataset.text
    api = client_api(worker_client)
    calibration = api.start_calibration(dataset.json()["id"], CalibrationOptions(seeds=[1, 2, 3]))
    assert calibration["verdict"] is None  # not finished yet
    api.wait(calibration["id"], poll_s=0.05)

    status = api.status(calibration["id"])
    assert status["status"]["state"] == "succeeded"
    verdict = status["verdict"]
    assert verdict["status"] == "failed"
    failed = {r["code"] for r in verdict["reasons"] if r["severity"] == "failed"}
    assert "orientation_misfit" in failed
    assert all(r["message"] and r["fix"] for r in verdict["reasons"])
    assert verdict == api.result(calibration["id"]).verdict.model_dump(mode="json")  # type: ignore[union-attr]
    listed = worker_client.get("/api/v1/calibrations").json()["data"]
    assert [c["verdict"] for c in listed if c["id"] == calibration["id"]] == [verdict]

    location = f"/api/v1/calibrations/{calibration['id']}/urdf"
    assert_problem(worker_client.get(location), 409, "verdict is failed", "?force=true")
    assert "<robot" in api.urdf(calibration["id"], force=True)


def test_a_sound_calibration_has_its_verdict_and_urdf(worker_client: TestClient) -> None:
    api = client_api(worker_client)
    dataset = upload_csv(worker_client).json()  # 40 simulated UR10 poses
    calibration = api.start_calibration(dataset["id"], CalibrationOptions(seeds=[1, 2]))
    api.wait(calibration["id"], poll_s=0.05)
    verdict = api.status(calibration["id"])["verdict"]
    assert verdict is not None and verdict["status"] in {"ok", "warning"}
    assert "<robot" in api.urdf(calibration["id"])
