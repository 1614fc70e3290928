"""The ``kincal`` command line: round trips, and one clear line + exit code 2 on bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from schemas.calibration import CalibrationResult
from service.render import result_json
from solver import lie
from tests.service.cli_support import run


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small simulated UR10 recording written by ``kincal simulate``."""
    path = tmp_path_factory.mktemp("cli") / "ur10.csv"
    subprocess.run(
        [
            sys.executable,
            "-c",
            "from service.cli import main; main()",
            "simulate",
            "--robot",
            "ur10",
            "--n",
            "60",
            "--seed",
            "2",
            "-o",
            str(path),
            "--truth",
            str(path.with_suffix(".json")),
        ],
        check=True,
        capture_output=True,
    )
    return path


def test_console_script_is_installed() -> None:
    out = subprocess.run(
        [Path(sys.executable).with_name("kincal"), "--help"],
        capture_output=True,
        text=True,
        check=True,
    )
    for command in ("simulate", "calibrate", "predict", "demo"):
        assert command in out.stdout


def test_simulate_writes_contract_and_truth(recording: Path) -> None:
    frame = pd.read_csv(recording)
    assert list(frame.columns[1:7]) == [
        "shoulder_pan_joint",
        "shoulder_lift_joint",
        "elbow_joint",
        "wrist_1_joint",
        "wrist_2_joint",
        "wrist_3_joint",
    ]
    assert {"x", "y", "z", "qx", "qy", "qz", "qw", "sample_id", "t"} <= set(frame.columns)
    truth = json.loads(recording.with_suffix(".json").read_text())
    assert truth["compliance_rad_per_nm"]["shoulder_lift_joint"] == 5e-4


def test_calibrate_then_predict_round_trip(
    recording: Path, tmp_path: Path, capsys, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    result_path, poses_path, urdf_path = (
        tmp_path / "r.json",
        tmp_path / "p.csv",
        tmp_path / "c.urdf",
    )
    code, out, err = run(
        [
            "calibrate",
            str(recording),
            "--robot",
            "ur10",
            "-o",
            str(result_path),
            "--export-urdf",
            str(urdf_path),
            "--no-heldout",
        ],
        capsys,
        monkeypatch,
    )
    assert code == 0, err
    assert "Levenberg-Marquardt: optimal" in out and urdf_path.exists()
    result = CalibrationResult.model_validate_json(result_path.read_text())
    assert result.format == "kincal.calibration/1"
    code, _, err = run(
        ["predict", str(result_path), str(recording), "-o", str(poses_path)], capsys, monkeypatch
    )
    assert code == 0, err
    predicted = pd.read_csv(poses_path)
    data = pd.read_csv(recording)
    q = data[result.robot.joint_names].to_numpy()
    expected = result_json.predict_poses(result, q)
    assert np.allclose(predicted[["x", "y", "z"]].to_numpy(), expected[:, :3, 3], atol=1e-12)
    rotation = lie.pose_matrix(
        np.zeros((len(q), 3)), predicted[["qx", "qy", "qz", "qw"]].to_numpy()
    )
    assert np.allclose(rotation[:, :3, :3], expected[:, :3, :3], atol=1e-12)
    # predictions land on the (noisy) measurements: the calibration is good
    assert (
        np.abs(predicted[["x", "y", "z"]].to_numpy() - data[["x", "y", "z"]].to_numpy()).mean()
        < 1e-3
    )


def test_a_simulated_recording_of_positions_calibrates_and_reads_back_under_either_field(
    tmp_path: Path, capsys, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    """``kincal simulate --no-rotation`` writes no quaternion columns; its result says
    ``measures_rotation: false``; a result written before issue 35 (``position_only: true``)
    predicts the same poses."""
    data, result_path = tmp_path / "positions.csv", tmp_path / "r.json"
    simulate = ["simulate", "--robot", "ur10", "--n", "40", "--no-rotation", "-o", data]
    code, _, err = run(simulate, capsys, monkeypatch)
    assert code == 0, err
    assert not {"qx", "qy", "qz", "qw"} & set(pd.read_csv(data).columns)
    calibrate = ["calibrate", data, "--robot", "ur10", "--no-heldout", "--covariance", "none"]
    code, _, err = run([*calibrate, "-o", result_path], capsys, monkeypatch)
    assert code == 0, err
    document = json.loads(result_path.read_text())
    assert document["dataset"]["measures_rotation"] is False
    assert "position_only" not in document["dataset"]
    old = tmp_path / "old.json"
    document["dataset"]["position_only"] = not document["dataset"].pop("measures_rotation")
    old.write_text(json.dumps(document))
    predictions = []
    for result in (result_path, old):
        poses = tmp_path / f"{result.stem}_poses.csv"
        code, _, err = run(["predict", result, data, "-o", poses], capsys, monkeypatch)
        assert code == 0, err
        predictions.append(pd.read_csv(poses))
    pd.testing.assert_frame_equal(*predictions)
    assert not CalibrationResult.model_validate(document).dataset.measures_rotation
    # a legacy flag that is not true or false is refused, never coerced into its negation
    document["dataset"]["position_only"] = "true"
    old.write_text(json.dumps(document))
    code, _, err = run(["predict", old, data, "-o", tmp_path / "x.csv"], capsys, monkeypatch)
    assert code == 2 and "position_only must be true or false, got 'true'" in err


def _bad(recording: Path, tmp_path: Path, edit) -> Path:  # type: ignore[no-untyped-def]
    frame = pd.read_csv(recording)
    out = tmp_path / "bad.csv"
    edited = edit(frame)
    if isinstance(edited, str):
        out.write_text(edited)
    else:
        edited.to_csv(out, index=False)
    return out


def _set(frame: pd.DataFrame, row: int, column: str, value: object) -> pd.DataFrame:
    frame[column] = frame[column].astype(object)
    frame.loc[row, column] = value
    return frame


UR10_JOINTS = [
    "shoulder_pan_joint",
    "shoulder_lift_joint",
    "elbow_joint",
    "wrist_1_joint",
    "wrist_2_joint",
    "wrist_3_joint",
]

BAD_DATA = {
    "nan": (lambda f: _set(f, 4, "elbow_joint", np.nan), "data row 5, column elbow_joint"),
    "inf": (lambda f: _set(f, 2, "x", np.inf), "data row 3, column x"),
    "non_unit_quaternion": (lambda f: _set(f, 6, "qw", 3.0), "data row 7"),
    "unknown_joint": (lambda f: f.assign(wrist_4_joint=0.0), "unknown column(s) wrist_4_joint"),
    "missing_joint": (
        lambda f: f.drop(columns=["elbow_joint"]),
        "missing joint column(s) elbow_joint",
    ),
    "wrong_column_count": (
        lambda f: f.rename(columns={n: f"q{i + 1}" for i, n in enumerate(UR10_JOINTS)}).drop(
            columns=["q6"]
        ),
        "missing q6",
    ),
    "duplicate_columns": (
        lambda f: f.to_csv(index=False).replace("elbow_joint", "shoulder_lift_joint", 1),
        "duplicate column",
    ),
    "too_few_samples": (lambda f: f.head(4), "fewer samples than identifiable parameters"),
    "non_numeric": (lambda f: _set(f, 9, "y", "abc"), "data row 10, column y"),
}


@pytest.mark.parametrize("case", sorted(BAD_DATA))
def test_bad_dataset_gives_one_line_and_exit_2(
    case: str, recording: Path, tmp_path: Path, capsys, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    edit, expected = BAD_DATA[case]
    path = _bad(recording, tmp_path, edit)
    code, _, err = run(
        ["calibrate", str(path), "--robot", "ur10", "-o", str(tmp_path / "r.json")],
        capsys,
        monkeypatch,
    )
    assert code == 2
    assert err.count("\n") == 1 and err.startswith("kincal: error: ")
    assert expected in err
    assert "Traceback" not in err


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--robot", "abb"], "unknown robot 'abb'; built-in robots: kinova, panda, ur10"),
        (
            ["--urdf", "{urdf}", "--base", "base_link", "--tip", "nope"],
            "tip frame 'nope' is not in the URDF",
        ),
        (
            ["--urdf", "/no/such.urdf", "--base", "a", "--tip", "b"],
            "cannot read URDF /no/such.urdf",
        ),
        (
            ["--robot", "ur10", "--compliant-joints", "nope"],
            "compliant_joints: joint 'nope' is not on the chain",
        ),
        (["--robot", "ur10", "--gravity", "1,2"], "--gravity takes 3 comma-separated numbers"),
        (["--robot", "ur10", "--rotation-weight", "0"], "option rotation_weight_m_per_rad"),
    ],
)
def test_bad_robot_or_option_gives_one_line_and_exit_2(
    args: list[str], expected: str, recording: Path, tmp_path: Path, capsys, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    from schemas.robots import example_robot_data_dir

    urdf = example_robot_data_dir() / "robots/ur_description/urdf/ur10_robot.urdf"
    args = [a.replace("{urdf}", str(urdf)) for a in args]
    code, _, err = run(
        ["calibrate", str(recording), "-o", str(tmp_path / "r.json"), *args], capsys, monkeypatch
    )
    assert code == 2
    assert err.count("\n") == 1 and expected in err


@pytest.mark.parametrize(
    ("name", "content", "expected"),
    [
        ("missing.csv", None, "missing.csv"),
        ("data.txt", "a,b\n1,2\n", "'.txt'"),
        ("garbage.parquet", "not parquet", "garbage.parquet"),
        ("broken.json", '{"samples": [', "broken.json"),
    ],
)
def test_unreadable_file_gives_one_line_and_exit_2(
    name: str, content: str | None, expected: str, tmp_path: Path, capsys, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    path = tmp_path / name
    if content is not None:
        path.write_text(content)
    code, _, err = run(
        ["calibrate", str(path), "--robot", "ur10", "-o", str(tmp_path / "r.json")],
        capsys,
        monkeypatch,
    )
    assert code == 2 and err.count("\n") == 1 and expected in err


def test_predict_rejects_a_file_that_is_not_a_result(
    recording: Path, tmp_path: Path, capsys, monkeypatch
) -> None:  # type: ignore[no-untyped-def]
    bogus = tmp_path / "r.json"
    bogus.write_text('{"format": "something else"}')
    code, _, err = run(
        ["predict", str(bogus), str(recording), "-o", str(tmp_path / "p.csv")], capsys, monkeypatch
    )
    assert code == 2 and "is not a kincal calibration result" in err and err.count("\n") == 1


def test_usage_error_exits_2(capsys, monkeypatch) -> None:  # type: ignore[no-untyped-def]
    code, _, err = run(["calibrate"], capsys, monkeypatch)
    assert code == 2 and "Missing argument" in err


@pytest.mark.parametrize("value", ["1" + "0" * 400, "1e308"])
def test_huge_numbers_in_a_json_recording_are_exit_2_naming_the_cell(
    recording: Path,
    tmp_path: Path,
    value: str,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A 400-digit integer was 'internal error', exit 1; 1e308 failed deep in the solver."""
    rows = pd.read_csv(recording).to_dict(orient="records")
    text = json.dumps(rows).replace(f"{rows[3]['elbow_joint']!r}", value, 1)
    bad = tmp_path / "bad.json"
    bad.write_text(text)
    code, _, err = run(
        ["calibrate", bad, "--robot", "ur10", "-o", tmp_path / "r.json"], capsys, monkeypatch
    )
    assert code == 2, err
    assert code == 2 and "bad.json" in err and "data row 4, column elbow_joint" in err
    assert "-10000 to 10000 rad" in err


def test_help_lists_each_command_with_its_whole_summary() -> None:
    """Click cut summaries at the first full stop ("(paper Eq.") or at 45 characters."""
    out = subprocess.run(
        [sys.executable, "-c", "from service.cli import main; main()", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    panel = out.split("Commands")[1]
    listing = " ".join(panel.translate({ord(c): " " for c in "│╭╮╰╯─"}).split())
    assert "..." not in listing
    for fragment in ("(paper Eq. 8–10)", "best first (Eq. 22–23).", "show the held-out gain."):
        assert fragment in listing


def test_serve_help_lists_every_setting_of_the_service() -> None:
    from service.settings import Settings

    out = subprocess.run(
        [sys.executable, "-c", "from service.cli import main; main()", "serve", "--help"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    for name in Settings.model_fields:
        assert f"KINCAL_{name.upper()} [" in out, name
    assert "Most <joint> elements in an uploaded URDF" in out
