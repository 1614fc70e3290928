"""Devices without a URDF (issue 15): a DH table (YAML) as the robot and industrial_calibration's
YAML recording as the dataset, through ``kincal calibrate``."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from schemas.dataset import read_dataset
from schemas.robots import load_robot
from solver.errors import DatasetError, ModelError
from tests.conftest import REAL_DATA
from tests.service.cli_support import run

POSITIONER = REAL_DATA / "industrial_calibration_2axis_positioner"


def test_positioner_calibrates_through_the_cli_and_improves_heldout(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "result.json"
    code, _, err = run(
        [
            "calibrate",
            POSITIONER / "measurements.yaml",
            "--dh",
            POSITIONER / "positioner_dh.yaml",
            "-o",
            out,
            "--seeds",
            "1,2,3,4,5",
            "--covariance",
            "none",
        ],
        capsys,
        monkeypatch,
    )
    assert code == 0, err
    result = json.loads(out.read_text())
    assert result["dataset"]["n_samples"] == 205
    assert result["robot"]["joint_names"] == ["j1", "j2"]
    before = result["fit"]["before"]["heldout"]["translation_mean_mm"]
    after = result["fit"]["after"]["heldout"]["translation_mean_mm"]
    assert after < 0.95 * before, (before, after)


def test_industrial_yaml_rows_are_sorted_by_time_and_bad_entries_are_named(
    tmp_path: Path,
) -> None:
    robot = load_robot(dh_path=POSITIONER / "positioner_dh.yaml")
    dataset = read_dataset(POSITIONER / "measurements.yaml", ("j1", "j2"))
    assert dataset.time_s is not None and (dataset.time_s[1:] > dataset.time_s[:-1]).all()
    assert robot.base_frame == "base_link" and robot.tip_frame == "tool0"
    bad = tmp_path / "bad.yaml"
    bad.write_text("'17':\n  camera_joints: []\n  target_joints: [0.1]\n  pose: {x: 1}\n")
    with pytest.raises(DatasetError, match=r"entry '17': pose is missing y, z, qx"):
        read_dataset(bad, ("j1",))
    bad.write_text("'17':\n  camera_joints: [0.2]\n  target_joints: [0.1]\n  pose: {x: 1}\n")
    with pytest.raises(DatasetError, match="camera_joints is not empty"):
        read_dataset(bad, ("j1",))


def test_dh_table_errors_name_the_field(tmp_path: Path) -> None:
    table = tmp_path / "t.yaml"
    table.write_text("convention: dh\njoints:\n  - {name: j1, alfa_rad: 1.0}\n")
    with pytest.raises(ModelError, match=r"joints\.0\.alfa_rad: Extra inputs"):
        load_robot(dh_path=table)
    table.write_text("convention: craig\njoints:\n  - {name: j1}\n")
    with pytest.raises(ModelError, match=r"convention: Input should be 'dh' or 'mdh'"):
        load_robot(dh_path=table)
    table.write_text("convention: dh\njoints:\n  - {name: j1, type: prismatic}\n")
    with pytest.raises(ModelError, match="needs lower and upper limits"):
        load_robot(dh_path=table)


def test_http_takes_the_dh_robots_urdf_and_the_yaml_recording(tmp_path: Path) -> None:
    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from tests.service.api.conftest import fresh_database_url, make_settings

    robot = load_robot(dh_path=POSITIONER / "positioner_dh.yaml")
    with (
        fresh_database_url(tmp_path) as url,
        TestClient(create_app(make_settings(tmp_path, url))) as client,
    ):
        created = client.post(
            "/api/v1/robots",
            json={
                "name": "positioner",
                "base_frame": robot.base_frame,
                "tip_frame": robot.tip_frame,
                "urdf": robot.urdf_xml,
            },
        )
        assert created.status_code == 201, created.text
        uploaded = client.post(
            "/api/v1/datasets",
            files={
                "file": (
                    "measurements.yaml",
                    (POSITIONER / "measurements.yaml").read_bytes(),
                    "application/yaml",
                )
            },
            data={"robot": created.json()["id"]},
        )
    assert uploaded.status_code == 201, uploaded.text
    assert uploaded.json()["n_samples"] == 205


def test_dh_urdf_command_writes_the_generated_urdf(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "positioner.urdf"
    code, text, err = run(
        ["dh-urdf", POSITIONER / "positioner_dh.yaml", "-o", out], capsys, monkeypatch
    )
    assert code == 0, err
    assert "base frame base_link, tip frame tool0" in text
    assert out.read_text() == load_robot(dh_path=POSITIONER / "positioner_dh.yaml").urdf_xml
