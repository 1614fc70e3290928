"""Measurement models through the user's path (issue 15): ball-in-socket folders and the
4-marker TIAGo file calibrate with ``kincal calibrate`` and their held-out error drops; bad
input is refused with the fix."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from benchmarks import platonics
from schemas.robots import example_robot_data_dir
from tests.conftest import REAL_DATA
from tests.service.cli_support import run

SOCKETS = REAL_DATA / "platonics_ball_socket"
TIAGO_QUALISYS = REAL_DATA / "figaroh_tiago_mocap/qualysis/qualysis_base_hand_calibration.csv"


def _tiago_urdf() -> Path:
    return example_robot_data_dir() / "robots/tiago_description/robots/tiago.urdf"


def test_panda_ball_in_socket_calibrates_with_defaults(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A platonics Panda folder (a placement folder with two sockets, headerless joint files)
    is detected as 'point' and calibrates with exit 0; the held-out ball-centre scatter drops
    more than 5x."""
    out = tmp_path / "result.json"
    report = tmp_path / "report.html"
    args = ["calibrate", SOCKETS / "panda_right", "--robot", "panda", "--report", report]
    code, stdout, stderr = run([*args, "-o", out], capsys, monkeypatch)
    assert code == 0, stderr
    page = report.read_text()
    assert "point (residual in the robot base frame)" in page
    assert "removed by the model rule (level 0.01)" in page
    result = json.loads(out.read_text())
    measurement = result["measurement"]
    assert measurement["type"] == "point"
    assert measurement["labels"] == ["world_frame/hole_0", "world_frame/hole_1"]
    assert [u["name"] for u in measurement["unknowns"]][:3] == [
        "point_0.x",
        "point_0.y",
        "point_0.z",
    ]
    # the random perturbations' covariances (Eq. 12 on the socket residuals, base frame)
    covariance = result["covariance"]
    assert covariance is not None and covariance["estimator"] == "reml"
    assert [f["name"] for f in covariance["frames"]] == result["robot"]["joint_names"]
    assert covariance["solver"]["status"] == "optimal", covariance["solver"]
    assert not any("not estimated" in note for note in measurement["notes"])
    # the predictive parts in the socket residual's space (3-D, robot base frame): Cov(θ̂)
    # over the chain parameters and the sockets, the model error, the held-out coverage
    predictive = result["predictive"]
    assert predictive is not None
    assert "point_0.x" in predictive["parameter_covariance"]["parameters"]
    assert predictive["model_error"]["frame"] == "robot base frame"
    assert predictive["model_error"]["axes"] == ["x", "y", "z"]
    found = predictive["coverage"]
    assert found["dimension"] == 3 and found["n_splits"] == 10
    assert "predictive coverage on" in stdout
    # kincal predict takes it: the total tip covariance with the tip's parameter part, and
    # says that the model-error part (socket residual space) is not applicable to the tip
    configs = tmp_path / "configs.csv"
    joints = np.loadtxt(SOCKETS / "panda_right/world_frame/hole_0.csv", delimiter=",")[:2]
    header = ",".join(result["robot"]["joint_names"])
    np.savetxt(configs, joints, delimiter=",", header=header, comments="")
    predicted = tmp_path / "predicted.csv"
    code, _, stderr = run(["predict", out, configs, "-o", predicted], capsys, monkeypatch)
    assert code == 0, stderr
    assert "model-error part is estimated in its own residual space" in stderr
    assert "cov_55" in predicted.read_text().splitlines()[0]
    parts = {}
    for part in ("total", "random-effects", "parameters", "model-error"):
        path = tmp_path / f"{part}.csv"
        code, _, stderr = run(
            ["predict", out, configs, "-o", path, "--part", part], capsys, monkeypatch
        )
        assert code == 0, stderr
        table = np.genfromtxt(path, delimiter=",", names=True)
        parts[part] = np.array([[table[f"cov_{i}{i}"] for i in range(3)]])
    assert np.all(parts["parameters"] > 0)  # J_θ Cov(θ̂) J_θᵀ of the tip's position
    assert np.all(parts["model-error"] == 0)
    np.testing.assert_allclose(
        parts["total"], parts["random-effects"] + parts["parameters"], rtol=1e-9
    )
    before = result["fit"]["before"]["heldout"]["translation_mean_mm"]
    after = result["fit"]["after"]["heldout"]["translation_mean_mm"]
    assert after < before / 5, (before, after)
    assert "held-out" in stdout


def test_known_socket_distance_is_met(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "result.json"
    config = tmp_path / "options.toml"
    config.write_text('measurement = "point"\npoint_distance_m = 0.05\nseeds = [1, 2, 3]\n')
    code, _, stderr = run(
        ["calibrate", SOCKETS / "panda_right", "--robot", "panda", "--config", config, "-o", out],
        capsys,
        monkeypatch,
    )
    assert code == 0, stderr
    result = json.loads(out.read_text())
    (gap,) = result["measurement"]["constraint_residuals_m"]
    assert abs(gap) < 1e-3  # 50 mm met to within a millimetre (one equation among 180)
    assert result["fit"]["after"]["heldout"]["translation_mean_mm"] < 0.5


def test_tiago_qualisys_file_calibrates_all_its_markers_with_their_covariances(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The Qualisys file's four markers (marker 4 repeats marker 3's columns: read once, with a
    note) in one fit, exit 0, held-out better than before; asked for explicitly, the
    covariances of Eq. 12 with the markers' position noise (blockdiag(Σ_n, …), tip frame),
    and ``kincal predict`` reads them."""
    out = tmp_path / "result.json"
    args = ["calibrate", TIAGO_QUALISYS, "--urdf", _tiago_urdf(), "--base", "base_footprint"]
    args += ["--tip", "arm_7_link", "--covariance", "diag", "--seeds", "1,2,3"]  # 3 splits: quicker
    code, stdout, stderr = run([*args, "-o", out], capsys, monkeypatch)
    assert code == 0, stderr
    result = json.loads(out.read_text())
    measurement = result["measurement"]
    assert measurement["type"] == "markers"
    assert measurement["labels"] == ["marker 1", "marker 2", "marker 3"]
    assert "marker 4 repeats marker 3 in every row: read once" in measurement["notes"]
    assert len(measurement["unknowns"]) == 9
    assert measurement["components"][:4] == ["m1.x", "m1.y", "m1.z", "m2.x"]
    before = result["fit"]["before"]["heldout"]["translation_mean_mm"]
    after = result["fit"]["after"]["heldout"]["translation_mean_mm"]
    assert after < before
    covariance = result["covariance"]
    assert covariance is not None and covariance["structure"] == "diag"
    assert [f["name"] for f in covariance["frames"]] == result["robot"]["joint_names"]
    noise = covariance["noise"]  # one position noise of every marker: no rotation axes
    assert noise["std"][3:] == [0.0, 0.0, 0.0], noise
    assert all(s is not None and 0.0 <= s < 1e-3 for s in noise["std"][:3]), noise
    assert not any("not estimated" in note for note in measurement["notes"])
    assert "random perturbations" in stdout
    configs = tmp_path / "configs.csv"
    header = ",".join(result["robot"]["joint_names"])
    np.savetxt(
        configs,
        np.zeros((2, len(result["robot"]["joint_names"]))),
        delimiter=",",
        header=header,
        comments="",
    )
    code, _, stderr = run(["predict", out, configs, "-o", tmp_path / "p.csv"], capsys, monkeypatch)
    assert code == 0, stderr


@pytest.mark.parametrize("estimator", ["reml", "ml"])
def test_tiago_qualisys_covariance_likelihood_fit_converges(
    estimator: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The likelihood fit of the Qualisys file's covariances (33 rows of a 9-D marker residual,
    51 diagonal entries of rank 44) ends "optimal" under its own stopping rule, from both starts,
    and no fit of the run (the model rule's outlier screening refits too) notes another status.
    With the scoring metric's proximal weight taken relative to the largest equilibrated
    curvature (that of a marker-noise variance near its floor) both estimators stopped at the
    200-step limit from both starts, REML's NLL at −4307.78 still falling (optimum −4307.80)."""
    out = tmp_path / "result.json"
    args = ["calibrate", TIAGO_QUALISYS, "--urdf", _tiago_urdf(), "--base", "base_footprint"]
    args += ["--tip", "arm_7_link", "--covariance", "diag", "--estimator", estimator]
    code, _, stderr = run([*args, "--no-heldout", "-o", out], capsys, monkeypatch)
    assert code == 0, stderr
    result = json.loads(out.read_text())
    solver = result["covariance"]["solver"]
    assert solver["status"] == "optimal", solver
    assert "(optimal))" in solver["message"], solver  # the other start's end
    notes = [*result["measurement"]["notes"], *result["covariance"]["identifiability"]["warnings"]]
    assert not [note for note in notes if "ended with status" in note], notes


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--measurement", "sockets"], "unknown measurement 'sockets'"),
        (["--measurement", "components:tz,roll"], "tz,rx,ry"),
        (["--measurement", "eye-on-head:neck"], "not a joint of the chain"),
        (["--point-distance", "-1"], "point_distance_m"),
    ],
)
def test_bad_measurement_options_name_the_fix(
    flags: list[str],
    message: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    args = ["calibrate", SOCKETS / "panda_right", "--robot", "panda", "-o", tmp_path / "r.json"]
    code, _, stderr = run([*args, *flags], capsys, monkeypatch)
    assert code == 2
    assert message in stderr
    assert "Traceback" not in stderr


def test_bad_hole_file_is_named_with_the_fix(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    folder = tmp_path / "arm" / "front"
    folder.mkdir(parents=True)
    shutil.copy(SOCKETS / "panda_right/world_frame/hole_0.csv", folder / "hole_0.csv")
    (folder / "hole_1.csv").write_text("0.1,0.2,0.3\n0.1,0.2,0.3\n")
    code, _, stderr = run(
        ["calibrate", tmp_path / "arm", "--robot", "panda", "-o", tmp_path / "r.json"],
        capsys,
        monkeypatch,
    )
    assert code == 2
    assert "front/hole_1.csv: 3 columns but the chain has 7 joints" in stderr


def test_platonics_benchmark_smoke() -> None:
    line, numbers = platonics.row("panda_right", seeds=2)
    assert line.startswith("| panda_right |")
    assert numbers["after_mm"] < numbers["before_mm"]


def test_http_refuses_a_folder_measurement_with_problem_json(tmp_path: Path) -> None:
    """The service calibrates one uploaded file: 'point' and 'markers' get a 422 saying so."""
    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from tests.service.api.conftest import fresh_database_url, make_settings, upload_csv

    with (
        fresh_database_url(tmp_path) as url,
        TestClient(create_app(make_settings(tmp_path, url))) as client,
    ):
        dataset = upload_csv(client).json()
        response = client.post(
            "/api/v1/calibrations",
            json={"dataset_id": dataset["id"], "options": {"measurement": "point"}},
        )
    assert response.status_code == 422
    assert response.headers["content-type"].startswith("application/problem+json")
    assert "kincal calibrate" in response.json()["detail"]


FR3 = REAL_DATA / "philnad_fr3_eye_in_hand/fr3_poses.csv"


def test_position_measurement_ignores_the_recorded_orientations(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """--measurement position on a full-pose file equals the same file without its
    quaternion columns (to 1e-9)."""
    import pandas as pd

    stripped = tmp_path / "positions.csv"
    pd.read_csv(FR3).drop(columns=["qx", "qy", "qz", "qw"]).to_csv(stripped, index=False)
    base = ["--robot", "panda", "--covariance", "none", "--seeds", "1,2"]
    out_a, out_b = tmp_path / "a.json", tmp_path / "b.json"
    code, _, err = run(
        ["calibrate", FR3, *base, "--measurement", "position", "-o", out_a], capsys, monkeypatch
    )
    assert code == 0, err
    code, _, err = run(["calibrate", stripped, *base, "-o", out_b], capsys, monkeypatch)
    assert code == 0, err
    a, b = json.loads(out_a.read_text()), json.loads(out_b.read_text())
    assert not a["dataset"]["measures_rotation"] and not b["dataset"]["measures_rotation"]
    for link_a, link_b in zip(a["links"], b["links"], strict=True):
        np.testing.assert_allclose(link_a["placement"], link_b["placement"], atol=1e-9)
    heldout_a, heldout_b = a["fit"]["after"]["heldout"], b["fit"]["after"]["heldout"]
    assert heldout_a["rotation_mean_deg"] is None
    assert heldout_a["translation_mean_mm"] == pytest.approx(heldout_b["translation_mean_mm"])
    code, _, err = run(
        ["calibrate", stripped, *base, "--measurement", "pose", "-o", out_b], capsys, monkeypatch
    )
    assert code == 2 and "--measurement position" in err


def test_design_plans_the_configs_measurement(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A calibrate config naming the measurement makes the design plan it: ball in socket
    without recorded socket candidates is refused naming --candidates."""
    config = tmp_path / "options.toml"
    config.write_text('measurement = "point"\n')
    code, _, stderr = run(
        ["design", "--robot", "kinova", "--config", config, "-o", tmp_path / "d.json"],
        capsys,
        monkeypatch,
    )
    assert code == 2
    assert "measurement 'point'" in stderr and "--candidates" in stderr


@pytest.mark.parametrize(
    ("measurement", "model_name"),
    [("components:tz,rx,ry", "plane contact"), ("eye-on-head:panda_joint2", "eye-on-head")],
)
def test_pose_like_measurements_calibrate_through_the_cli_to_the_noise_floor(
    measurement: str,
    model_name: str,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A simulated plane contact (z, roll, pitch of the tool in the plane's frame) and a
    sensor riding after joint 2 (the tip in its moving frame), written as pose CSVs:
    ``kincal calibrate --measurement ...`` exits 0 and its held-out error is at the noise."""
    import pandas as pd

    from solver import lie
    from solver.model import sample_configurations
    from tests.conftest import chain
    from tests.solver.test_measurement import MODELS, NOISE, _base, _rows

    c = chain("panda")
    model = MODELS[model_name]
    rng = np.random.default_rng(3)
    truth = _base(c, model)
    truth = model.apply(
        c, truth, 5e-4 * rng.standard_normal(6 * c.n_links), np.arange(6 * c.n_links)
    )
    rows = _rows(c, model, truth, sample_configurations(c, 200, rng), rng)
    quaternion = lie.matrix_to_quaternion_xyzw(rows.measured[:, :3, :3])
    table = pd.DataFrame(rows.joint_positions, columns=list(c.joint_names))
    table[["x", "y", "z"]] = rows.measured[:, :3, 3]
    table[["qx", "qy", "qz", "qw"]] = quaternion
    data = tmp_path / "contact.csv"
    table.to_csv(data, index=False)
    out = tmp_path / "result.json"
    args = ["calibrate", data, "--robot", "panda", "--measurement", measurement]
    code, _, stderr = run([*args, "--rigid", "-o", out], capsys, monkeypatch)
    assert code == 0, stderr
    result = json.loads(out.read_text())
    assert result["measurement"]["type"] == measurement
    after = result["fit"]["after"]["heldout"]
    before = result["fit"]["before"]["heldout"]
    translation_rows = len(model.translation_rows)
    # mean norm of the translation rows of 0.1 mm noise: at most 1.2x its expected value
    expected_mm = 1e3 * NOISE * {1: np.sqrt(2 / np.pi), 3: np.sqrt(8 / np.pi)}[translation_rows]
    assert after["translation_mean_mm"] <= 1.2 * expected_mm, (after, expected_mm)
    assert after["translation_mean_mm"] < before["translation_mean_mm"]
    covariance = result["covariance"]
    if model_name == "eye-on-head":  # Eq. 12 as for poses; the frames up to the sensor cancel
        assert covariance is not None
        frames = {f["name"]: f for f in covariance["frames"]}
        for hidden in ("panda_joint1", "panda_joint2"):  # not seen at all: std null, why
            assert frames[hidden]["std"] == [None] * 6, frames[hidden]
            assert all("no effect" in why for why in frames[hidden]["not_identifiable"])
        assert any(s is not None for s in frames["panda_joint4"]["std"])
    else:  # the chosen components' noise only, in the plane's frame
        assert covariance is not None
        assert covariance["noise"]["std"][0] == covariance["noise"]["std"][1] == 0.0
        assert covariance["noise"]["std"][5] == 0.0
        assert not any("not estimated" in note for note in result["measurement"]["notes"])
    # the predictive parts in the type's residual space, every part from training rows: the
    # held-out rows of 0.1 mm / 1 mrad noise inside the predicted 95 % ellipsoid (measured:
    # plane contact 99 %, mean d² 2.53 of 3; eye-on-head 97 %, 5.56 of 6)
    predictive = result["predictive"]
    assert predictive["model_error"]["frame"] == result["measurement"]["frame"]
    found = predictive["coverage"]
    assert found["dimension"] == model.dim and found["n_heldout"] == 200
    inside = {level["level"]: level["observed"] for level in found["levels"]}
    assert inside[0.95] >= 0.90, found
    assert abs(found["mean_mahalanobis_sq"] / model.dim - 1.0) < 0.25, found
    configs = tmp_path / "configs.csv"
    table[list(c.joint_names)].head(3).to_csv(configs, index=False)
    code, _, stderr = run(["predict", out, configs, "-o", tmp_path / "p.csv"], capsys, monkeypatch)
    assert code == 0, stderr
    # the model error applies to the tip pose only where the residual is the tip pose
    assert ("not applicable" in stderr) == (model_name != "eye-on-head"), stderr


TIAGO_VICON = (
    REAL_DATA
    / "figaroh_tiago_mocap/vicon/relative_encoder/vicon_calibration_fc10_gripper3_base1.csv"
)


def test_tiago_vicon_relative_base_joint_offsets_calibrate(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The Vicon gripper3/base1 file (21 rows, gripper marker in the frame of a base marker)
    calibrates through ``kincal calibrate --measurement relative-base --free joint_offsets``
    with exit 0 and a held-out improvement: the selection reaches the measurement-model fit
    (it used to be ignored there, leaving 33 parameters for 63 equations: few_equations)."""
    out = tmp_path / "result.json"
    args = ["calibrate", TIAGO_VICON, "--urdf", _tiago_urdf(), "--base", "base_footprint"]
    args += ["--tip", "arm_tool_link", "--measurement", "relative-base"]
    code, _, stderr = run([*args, "--free", "joint_offsets", "-o", out], capsys, monkeypatch)
    assert code == 0, stderr
    result = json.loads(out.read_text())
    identifiability = result["identifiability"]
    assert identifiability["rank"] <= 6 + 3 + 8, identifiability  # 2 frames, 8 offsets
    assert "arm_3_joint.tx" in identifiability["fixed"]
    assert "arm_3_joint.tx" not in identifiability["removed"]
    assert not any(name.endswith(".rz") for name in identifiability["fixed"])
    before = result["fit"]["before"]["heldout"]["translation_mean_mm"]
    after = result["fit"]["after"]["heldout"]["translation_mean_mm"]
    assert after < 0.5 * before, (before, after)
    # the default covariance calibration runs for this measurement too (it used to be dropped
    # without a word): every chain joint's frame and the noise, 3-D position residuals
    covariance = result["covariance"]
    assert covariance is not None and covariance["estimator"] == "reml"
    assert [f["name"] for f in covariance["frames"]] == result["robot"]["joint_names"]
    assert covariance["n_samples"] == result["outliers"]["n_used"]
    # 63 equations cannot fix the ~44 covariance entries well enough to judge rows by: the
    # model rule's Σ_E step is skipped and says why (with it, 2 rows went and the held-out
    # error rose from 10.1 to 10.8 mm)
    assert result["outliers"]["n_used"] == 21
    (step,) = [n for n in result["measurement"]["notes"] if "Σ_E step" in n]
    assert "skipped" in step and "too uncertain" in step


def test_fleet_of_ball_in_socket_pandas(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """``kincal fleet`` over platonics Panda folders (the known 50 mm socket distance in the
    TOML config) calibrates each folder as one robot and reports each one's parameters."""
    fleet = tmp_path / "fleet"
    fleet.mkdir()
    for name in ("panda_left", "panda_right"):
        (fleet / name).symlink_to(SOCKETS / name, target_is_directory=True)
    config = tmp_path / "fleet.toml"
    config.write_text('measurement = "point"\npoint_distance_m = 0.05\n')
    out = tmp_path / "fleet.json"
    args = ["fleet", fleet, "--robot", "panda", "--config", config, "-o", out]
    code, stdout, stderr = run(args, capsys, monkeypatch)
    assert code == 0, stderr
    assert "2 calibrated, 0 failed" in stdout
    report = json.loads(out.read_text())
    assert [r["serial"] for r in report["robots"]] == ["panda_left", "panda_right"]
    assert all(r["rms_after_mm"] < 1.0 for r in report["robots"])
