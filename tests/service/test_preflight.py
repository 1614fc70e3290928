"""Issue 28: unit mistakes and malformed recordings are refused before any fit, with one line
naming the fix — the same checks (:mod:`service.app.preflight`) through ``kincal calibrate``,
``discover``, ``fleet``, ``predict`` and the HTTP upload. On the real FR3 recording, altered
the way users get it wrong. (How long a refusal takes, whole process, is measured by
``benchmarks/cli_latency.py``, not asserted here.)"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from fastapi.testclient import TestClient

from schemas.robots import example_robot_data_dir, load_robot
from service.api.app import create_app
from service.app.preflight import check_recording
from solver.errors import DatasetError
from solver.model import KinematicChain, build_chain
from tests.service.api.conftest import fresh_database_url, make_settings
from tests.service.cli_support import run

REAL = Path(__file__).resolve().parents[2] / "data" / "real"
FR3 = REAL / "philnad_fr3_eye_in_hand" / "fr3_poses.csv"
JOINTS = [f"q{i}" for i in range(1, 8)]


def _altered(tmp_path: Path, name: str, change: object) -> Path:
    table = pd.read_csv(FR3)
    changed = change(table)  # type: ignore[operator]
    table = table if changed is None else changed
    path = tmp_path / name
    table.to_csv(path, index=False)
    return path


def _millimetres(table: pd.DataFrame) -> None:
    table[["x", "y", "z"]] *= 1000.0


def _degrees(table: pd.DataFrame) -> None:
    table[JOINTS] *= 180.0 / math.pi


def _refused(
    args: list[object], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> str:
    code, out, err = run(args, capsys, monkeypatch)
    assert code == 2, out + err
    assert err.startswith("kincal: error: ") and err.count("\n") == 1, err
    return err


def test_millimetres_are_refused_by_calibrate_naming_the_unit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    mm = _altered(tmp_path, "mm.csv", _millimetres)
    err = _refused(
        ["calibrate", mm, "--robot", "panda", "--out-dir", tmp_path / "out"], capsys, monkeypatch
    )
    assert "mm.csv" in err and "millimetres" in err and "divide by 1000" in err
    assert not (tmp_path / "out").exists()


def test_degrees_are_refused_by_calibrate_naming_the_unit(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    deg = _altered(tmp_path, "deg.csv", _degrees)
    err = _refused(
        ["calibrate", deg, "--robot", "panda", "--out-dir", tmp_path / "out"], capsys, monkeypatch
    )
    assert "degrees" in err and "π/180" in err and "panda_joint" in err
    assert not (tmp_path / "out").exists()


def test_a_constant_joint_is_refused_unless_fixed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def hold(table: pd.DataFrame) -> None:
        table["q7"] = 0.25

    held = _altered(tmp_path, "held.csv", hold)
    err = _refused(["calibrate", held, "--robot", "panda"], capsys, monkeypatch)
    assert "panda_joint7" in err and "same value" in err and "--fix panda_joint7" in err
    chain = _panda()
    check_recording(held, chain, fixed_joints=["panda_joint7"])  # accepted when fixed


def test_repeated_rows_are_refused_naming_them(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def repeat(table: pd.DataFrame) -> None:
        table.loc[len(table)] = table.loc[4]
        table.loc[len(table) - 1, "sample_id"] = 10_000

    twice = _altered(tmp_path, "twice.csv", repeat)
    err = _refused(["calibrate", twice, "--robot", "panda"], capsys, monkeypatch)
    assert "data rows 5 and 115 are identical" in err and "remove the repeated rows" in err


def test_joint_values_outside_the_limits_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    def swap(table: pd.DataFrame) -> None:  # columns in the wrong order: q4 is never positive
        table[["q3", "q4"]] = table[["q4", "q3"]].to_numpy()

    swapped = _altered(tmp_path, "swapped.csv", swap)
    err = _refused(["calibrate", swapped, "--robot", "panda"], capsys, monkeypatch)
    assert "column panda_joint4" in err and "outside the joint's limits" in err
    assert "chain order" in err


def test_too_few_rows_for_the_parameters_are_refused(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    few = _altered(tmp_path, "few.csv", lambda t: t.head(5))
    err = _refused(["calibrate", few, "--robot", "panda"], capsys, monkeypatch)
    assert "5 samples give 30 equations" in err and "--free joint_offsets" in err


def test_predict_refuses_configurations_in_degrees(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    result = tmp_path / "fr3.json"
    code, _, err = run(
        [
            "calibrate",
            FR3,
            "--robot",
            "panda",
            "--no-heldout",
            "--covariance",
            "none",
            "-o",
            result,
        ],
        capsys,
        monkeypatch,
    )
    assert code == 0, err
    deg = _altered(tmp_path, "configs.csv", _degrees)
    err = _refused(["predict", result, deg], capsys, monkeypatch)
    assert "degrees" in err


def test_discover_and_fleet_refuse_before_fitting(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    mm = _altered(tmp_path, "mm.csv", _millimetres)
    err = _refused(["discover", mm, "--robot", "panda"], capsys, monkeypatch)
    assert "millimetres" in err
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    (fleet / "arm_a.csv").write_bytes(FR3.read_bytes())
    _altered(fleet, "arm_b.csv", _degrees)
    err = _refused(
        ["fleet", fleet, "--robot", "panda", "--out-dir", tmp_path / "f"], capsys, monkeypatch
    )
    assert "robot arm_b" in err and "degrees" in err
    assert not (tmp_path / "f").exists()


def test_the_http_upload_refuses_millimetres_and_degrees(tmp_path: Path) -> None:
    with (
        fresh_database_url(tmp_path) as url,
        TestClient(create_app(make_settings(tmp_path, url))) as client,
    ):
        for name, change, word in (
            ("mm.csv", _millimetres, "millimetres"),
            ("deg.csv", _degrees, "degrees"),
        ):
            path = _altered(tmp_path, name, change)
            response = client.post(
                "/api/v1/datasets",
                data={"robot": "panda"},
                files={"file": (name, path.read_bytes(), "text/csv")},
            )
            assert response.status_code == 422, response.text
            assert response.headers["content-type"].startswith("application/problem+json")
            assert word in response.json()["detail"]


def _panda() -> KinematicChain:
    robot = load_robot("panda")
    return build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)


ERD = example_robot_data_dir()
TIAGO = load_robot(
    urdf_path=ERD / "robots/tiago_description/robots/tiago.urdf",
    base_frame="base_footprint",
    tip_frame="arm_tool_link",
)


@pytest.mark.parametrize(
    ("recording", "robot"),
    [
        (FR3, load_robot("panda")),
        (
            REAL / "figaroh_ur10_experiment/calibration.csv",
            load_robot(
                urdf_path=REAL / "figaroh_ur10_experiment/ur10e_robot.urdf",
                base_frame="base_link",
                tip_frame="wrist_3_link",
            ),
        ),
        (
            REAL / "figaroh_talos_left_arm_contact/talos_left_arm_02_10_contact.csv",
            load_robot(
                urdf_path=ERD / "robots/talos_data/robots/talos_full_v2.urdf",
                base_frame="base_link",
                tip_frame="gripper_left_base_link",
            ),
        ),
        (
            REAL / "industrial_calibration_2axis_positioner/measurements.yaml",
            load_robot(dh_path=REAL / "industrial_calibration_2axis_positioner/positioner_dh.yaml"),
        ),
        *[
            (path, TIAGO)
            for path in sorted((REAL / "figaroh_tiago_mocap/vicon/relative_encoder").glob("*.csv"))
        ],
        *[(path, load_robot("panda")) for path in sorted(REAL.glob("platonics_ball_socket/p*"))],
    ],
    ids=lambda value: getattr(value, "name", None),
)
def test_every_shipped_recording_passes_the_checks(recording: Path, robot: object) -> None:
    chain = build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)  # type: ignore[attr-defined]
    view = check_recording(recording, chain)
    assert view.n_rows == len(view.joint_positions) > 0


def test_the_tiago_absolute_encoder_files_are_refused_for_their_constant_torso() -> None:
    """Their torso_lift_joint reads 0 in every row (PROVENANCE.md): use relative_encoder/."""
    chain = build_chain(TIAGO.urdf_xml, TIAGO.base_frame, TIAGO.tip_frame)
    for path in sorted((REAL / "figaroh_tiago_mocap/vicon/absolute_encoder").glob("*.csv")):
        with pytest.raises(DatasetError, match="column torso_lift_joint holds the same value"):
            check_recording(path, chain)


def test_the_checks_read_a_large_recording_by_its_head(tmp_path: Path) -> None:
    """A file beyond the head's rows is checked on its head and counted whole."""
    table = pd.read_csv(FR3)
    rng = np.random.default_rng(0)
    big = table.sample(70_000, replace=True, random_state=0).reset_index(drop=True)
    big[JOINTS] += rng.normal(0, 1e-6, size=(len(big), 7))  # no repeated rows
    big["sample_id"] = np.arange(len(big))
    path = tmp_path / "big.csv"
    big.to_csv(path, index=False)
    view = check_recording(path, _panda())
    assert view.n_rows == 70_000 and len(view.joint_positions) == 65_536
