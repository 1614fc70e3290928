"""Issue 17: every calibration option is reachable, with the same value, from a CLI flag, a
``--config`` TOML file and the HTTP body — one options model, checked against the flags."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from fastapi.testclient import TestClient

from schemas.calibration import CalibrationOptions
from schemas.dataset import write_dataset
from service.api.app import create_app
from service.cli.flags import CALIBRATION_FLAGS
from tests.service.api.conftest import fresh_database_url, make_settings, recording, upload_csv
from tests.service.cli_support import help_text, run

NOISE = [[1e-6 if i == j else 0.0 for j in range(6)] for i in range(6)]

VALUES: dict[str, tuple[list[str], Any]] = {
    "free_parameters": (["--free", "joint_offsets,compliance"], ["joint_offsets", "compliance"]),
    "fixed_parameters": (["--fix", "elbow_joint"], ["elbow_joint"]),
    "compliant_joints": (
        ["--compliant-joints", "shoulder_lift_joint,elbow_joint"],
        ["shoulder_lift_joint", "elbow_joint"],
    ),
    "virtual_axes_at": (["--virtual-axes", "shoulder_pan_joint"], ["shoulder_pan_joint"]),
    "gravity_base_m_s2": (["--gravity", "0,0,-9.8"], [0.0, 0.0, -9.8]),
    "payload_kg": (["--payload-kg", "1.5"], 1.5),
    "payload_com_m": (["--payload-com", "0,0,0.1"], [0.0, 0.0, 0.1]),
    "rotation_weight_m_per_rad": (["--rotation-weight", "0.5"], 0.5),
    "outlier_rule": (["--outlier-rule", "none"], "none"),
    "outlier_level": (["--outlier-level", "0.05"], 0.05),
    "outlier_sigma": (["--outlier-sigma", "3"], 3.0),
    "max_iterations": (["--max-iterations", "80"], 80),
    "tolerance": (["--tolerance", "1e-9"], 1e-9),
    "rank_tolerance": (["--rank-tolerance", "1e-6"], 1e-6),
    "heldout": (["--no-heldout"], False),
    "heldout_method": (["--heldout-method", "exact"], "exact"),
    "seeds": (["--seeds", "3,4"], [3, 4]),
    "train_fraction": (["--train-fraction", "0.8"], 0.8),
    "covariance": (["--covariance", "full"], "full"),
    "covariance_solver": (["--solver", "clarabel"], "clarabel"),
    "covariance_estimator": (["--estimator", "ml"], "ml"),
    "covariance_frames": (["--covariance-frames", "elbow_joint"], ["elbow_joint"]),
    "covariance_axes": (["--covariance-axes", "rotation"], "rotation"),
    "noise_std": (["--noise-std", "1e-4,1e-4,1e-4,1e-3,1e-3,1e-3"], [1e-4] * 3 + [1e-3] * 3),
    "noise_covariance": (["--noise-covariance", "{noise}"], NOISE),
    "measurement": (["--measurement", "components:tz,rx,ry"], "components:tz,rx,ry"),
    "point_distance_m": (["--point-distance", "0.05"], 0.05),
}
"""A non-default value of every option, as calibrate flags and as JSON."""


def _toml(value: Any) -> str:
    return json.dumps(value)  # JSON numbers, strings, booleans and arrays are TOML too


def test_every_option_has_a_flag_in_the_table_and_the_help(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    fields = set(CalibrationOptions.model_fields)
    assert set(VALUES) == fields == set(CALIBRATION_FLAGS)
    code, text, _ = run(["calibrate", "--help"], capsys, monkeypatch)
    assert code == 0
    text = help_text(text)
    for field, flag in CALIBRATION_FLAGS.items():
        assert flag.removeprefix("--") in VALUES[field][0][0], (field, flag)
        assert flag in text and f"[config: {field}]" in text, field


@pytest.fixture(scope="module")
def files(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    folder = tmp_path_factory.mktemp("flags")
    write_dataset(recording(), folder / "data.csv")
    (folder / "noise.json").write_text(json.dumps(NOISE))
    return {"data": folder / "data.csv", "noise": folder / "noise.json", "folder": folder}


def _shown(
    args: list[str], files: dict[str, Path], capsys: pytest.CaptureFixture[str], monkeypatch: Any
) -> dict[str, Any]:
    base = ["calibrate", str(files["data"]), "--robot", "ur10", "-o", str(files["folder"] / "x")]
    code, text, err = run([*base, "--show-options", *args], capsys, monkeypatch)
    assert code == 0, err
    shown: dict[str, Any] = json.loads(text)
    return shown


@pytest.mark.parametrize("field", sorted(VALUES))
def test_each_option_is_reachable_from_a_flag_a_config_file_and_http(
    field: str,
    files: dict[str, Path],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    args, value = VALUES[field]
    args = [a.replace("{noise}", str(files["noise"])) for a in args]
    default = CalibrationOptions().model_dump(mode="json")[field]
    assert value != default
    assert _shown(args, files, capsys, monkeypatch)[field] == value
    config = files["folder"] / f"{field}.toml"
    config.write_text(f"{field} = {_toml(value)}\n")
    assert _shown(["--config", str(config)], files, capsys, monkeypatch)[field] == value
    with (
        fresh_database_url(files["folder"] / field) as url,
        TestClient(create_app(make_settings(files["folder"] / field, url))) as client,
    ):
        dataset = upload_csv(client).json()
        response = client.post(
            "/api/v1/calibrations", json={"dataset_id": dataset["id"], "options": {field: value}}
        )
    assert response.status_code == 202, response.text
    assert response.json()["options"][field] == value


def test_flags_override_the_config_file_and_bad_keys_name_the_options(
    files: dict[str, Path],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    config = files["folder"] / "both.toml"
    config.write_text('covariance_estimator = "ml"\nmax_iterations = 70\n')
    shown = _shown(["--config", str(config), "--estimator", "moment"], files, capsys, monkeypatch)
    assert shown["covariance_estimator"] == "moment" and shown["max_iterations"] == 70
    config.write_text("max_iteration = 70\n")
    base = ["calibrate", str(files["data"]), "--robot", "ur10", "-o", str(files["folder"] / "y")]
    code, _, err = run([*base, "--config", str(config)], capsys, monkeypatch)
    assert code == 2 and err.count("\n") == 1 and "unknown option(s) max_iteration" in err
    config.write_text("max_iterations = 0\n")
    code, _, err = run([*base, "--config", str(config)], capsys, monkeypatch)
    assert code == 2 and "max_iterations (--max-iterations)" in err
    config.write_text("max_iterations = \n")
    code, _, err = run([*base, "--config", str(config)], capsys, monkeypatch)
    assert code == 2 and "is not TOML" in err
