"""Exports a controller can use (issue 15): every format, reloaded, reproduces kincal's calibrated
forward kinematics to 1e-9 where it can express it, and says what it cannot."""

from __future__ import annotations

import csv
import functools
import io
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
import yaml

from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.dh import parse_dh_robot
from service.app import calibrate as pipeline
from service.app import simulate as scenarios
from service.render import exports, result_json
from service.render.urdf_export import MARKER_LINK, MEASUREMENT_LINK
from solver import lie
from solver.kinematics import ChainParameters, forward_kinematics
from solver.measurement.models import nominal_pose
from solver.model import build_chain, sample_configurations
from tests.conftest import REPO, robot
from tests.service.cli_support import run

N = 40


@functools.cache
def _calibrated(name: str, free: tuple[str, ...] = ("all",)) -> CalibrationResult:
    description = robot(name)
    scn, recording = scenarios.simulate(
        description, n_samples=80, seed=7, effects=("geometry", "compliance", "camera", "marker")
    )
    dataset = scenarios.recording_dataset(recording, scn.chain, rotation=True)
    options = CalibrationOptions(
        heldout=False, outlier_rule="none", covariance="none", free_parameters=list(free)
    )
    return pipeline.calibrate(dataset, description, options)


def _predictions(result: CalibrationResult) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Configurations, kincal's rigid prediction (measurement frame -> marker) and the same
    without the measurement frame and marker (base frame -> tip frame)."""
    chain, params = result_json.result_chain(result)
    q = sample_configurations(chain, N, np.random.default_rng(4))
    rigid = ChainParameters(params.links, np.zeros_like(params.compliance_rad_per_nm))
    measured = forward_kinematics(chain, rigid, q, np.zeros((N, len(chain.compliance_axes))))
    camera = np.array(result.measurement_frame.matrix)
    marker = np.array(result.tool.matrix)
    return q, measured, lie.inverse(camera) @ measured @ lie.inverse(marker)


def _urdf_fk(urdf: str, base: str, tip: str, names: tuple[str, ...], q: np.ndarray) -> np.ndarray:
    chain = build_chain(urdf, base, tip)
    assert chain.joint_names == names
    return nominal_pose(chain, q)


@pytest.mark.parametrize("name", ["ur10", "panda"])
def test_urdf_keeps_the_robots_root_and_reproduces_the_robot_frame_prediction(name: str) -> None:
    result = _calibrated(name)
    q, measured, in_robot = _predictions(result)
    text = exports.export(result, "urdf")
    assert MEASUREMENT_LINK not in text and MARKER_LINK not in text
    original, exported = pin.buildModelFromXML(result.robot.urdf), pin.buildModelFromXML(text)
    assert [f.name for f in exported.frames] == [f.name for f in original.frames]
    names = tuple(result.robot.joint_names)
    got = _urdf_fk(text, result.robot.base_frame, result.robot.tip_frame, names, q)
    assert np.abs(got - in_robot).max() < 1e-9
    with_frames = exports.export(result, "urdf", measurement_frame=True)
    got = _urdf_fk(with_frames, MEASUREMENT_LINK, MARKER_LINK, names, q)
    assert np.abs(got - measured).max() < 1e-9


@pytest.mark.parametrize("convention", ["dh", "mdh"])
@pytest.mark.parametrize("measurement_frame", [False, True])
def test_dh_tables_reproduce_the_prediction(convention: str, measurement_frame: bool) -> None:
    result = _calibrated("ur10")
    q, measured, in_robot = _predictions(result)
    text = exports.export(result, convention, measurement_frame=measurement_frame)  # type: ignore[arg-type]
    assert "not expressed: joint compliance" in text  # the simulated robot is compliant
    table = parse_dh_robot(text, "export.yaml")
    assert table.convention == convention
    got = _urdf_fk(
        table.urdf(), table.base_frame, table.tip_frame, tuple(result.robot.joint_names), q
    )
    assert np.abs(got - (measured if measurement_frame else in_robot)).max() < 1e-9


def _apply_pal(urdf: str, deltas: dict[str, float]) -> str:
    """PAL's overlay: add <joint>_<dx..dyaw> to each joint's origin xyz and rpy as written."""
    root = ET.fromstring(urdf)
    used = set()
    for joint in root.findall("joint"):
        key = str(joint.get("name")).removesuffix("_joint")
        change = [deltas.get(f"{key}_{a}", 0.0) for a in exports.PAL_AXES]
        used |= {f"{key}_{a}" for a in exports.PAL_AXES if f"{key}_{a}" in deltas}
        origin = joint.find("origin")
        if origin is None:
            origin = ET.SubElement(joint, "origin")
        xyz = np.array([float(v) for v in origin.get("xyz", "0 0 0").split()]) + change[:3]
        rpy = np.array([float(v) for v in origin.get("rpy", "0 0 0").split()]) + change[3:]
        origin.set("xyz", " ".join(repr(float(v)) for v in xyz))
        origin.set("rpy", " ".join(repr(float(v)) for v in rpy))
    assert used == set(deltas)
    return ET.tostring(root, encoding="unicode")


@pytest.mark.parametrize("name", ["ur10", "panda"])
def test_pal_master_calibration_on_the_nominal_urdf_reproduces_the_prediction(name: str) -> None:
    result = _calibrated(name)
    q, _, in_robot = _predictions(result)
    text = exports.export(result, "pal-master")
    assert "# not expressed: joint compliance" in text
    deltas = yaml.safe_load(text)["robot_state_publisher"]["geometric_calibration"]
    assert deltas and all(not key.endswith("_joint_dx") for key in deltas)
    overlaid = _apply_pal(result.robot.urdf, deltas)
    names = tuple(result.robot.joint_names)
    got = _urdf_fk(overlaid, result.robot.base_frame, result.robot.tip_frame, names, q)
    assert np.abs(got - in_robot).max() < 1e-9


def _apply_ur(urdf: str, document: dict[str, dict[str, float]]) -> str:
    """``ur_description``'s reading of a kinematics file: each section's x, y, z and roll,
    pitch, yaw become its joint's ``<origin xyz rpy>`` as written (ur_common.xacro)."""
    root = ET.fromstring(urdf)
    joints = {j.get("name"): j for j in root.findall("joint")}
    for section, joint in exports.UR_SECTIONS:
        values = document[section]
        origin = joints[joint].find("origin")
        assert origin is not None
        origin.set("xyz", " ".join(repr(float(values[a])) for a in ("x", "y", "z")))
        origin.set("rpy", " ".join(repr(float(values[a])) for a in ("roll", "pitch", "yaw")))
    return ET.tostring(root, encoding="unicode")


def test_ur_kinematics_on_the_nominal_urdf_reproduces_the_prediction() -> None:
    result = _calibrated("ur10")
    q, _, in_robot = _predictions(result)
    text = exports.export(result, "ur-kinematics")
    assert "# not expressed: joint compliance" in text
    kinematics = yaml.safe_load(text)["kinematics"]
    assert list(kinematics) == [section for section, _ in exports.UR_SECTIONS] + ["hash"]
    assert kinematics["hash"].startswith("kincal_")
    got = _urdf_fk(
        _apply_ur(result.robot.urdf, kinematics),
        result.robot.base_frame,
        result.robot.tip_frame,
        tuple(result.robot.joint_names),
        q,
    )
    assert np.abs(got - in_robot).max() < 1e-9
    other = yaml.safe_load(exports.export(_calibrated("ur10", ("joint_offsets",)), "ur-kinematics"))
    assert other["kinematics"]["hash"] != kinematics["hash"]  # it names the calibration


def test_ur_kinematics_refuses_an_arm_that_is_not_a_ur() -> None:
    from solver.errors import KincalError

    with pytest.raises(KincalError, match=r"ur-kinematics needs a Universal Robots arm.*panda_"):
        exports.export(_calibrated("panda"), "ur-kinematics")


def test_the_real_ur10e_calibration_as_the_ur_kinematics_file_reproduces_kincal(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """The shipped UR10e recording (its ur_description URDF) through ``kincal calibrate`` and
    ``kincal export --format ur-kinematics``: the file, read as ur_description reads it into
    that URDF, gives kincal's calibrated forward kinematics to 1e-9."""
    folder = REPO / "data/real/figaroh_ur10_experiment"
    result_path, out = tmp_path / "ur10e.json", tmp_path / "ur10e_kinematics.yaml"
    calibrate = ["calibrate", folder / "calibration.csv", "--urdf", folder / "ur10e_robot.urdf"]
    calibrate += ["--base", "base_link", "--tip", "wrist_3_link", "--no-heldout"]
    code, _, err = run([*calibrate, "-o", result_path], capsys, monkeypatch)
    assert code in (0, 3), err
    export = ["export", result_path, "--format", "ur-kinematics", "-o", out, "--force"]
    code, text, err = run(export, capsys, monkeypatch)
    assert code == 0, err
    assert f"{out}  ur-kinematics export" in text
    result = CalibrationResult.model_validate_json(result_path.read_bytes())
    q, _, in_robot = _predictions(result)
    names = tuple(result.robot.joint_names)
    overlaid = _apply_ur(result.robot.urdf, yaml.safe_load(out.read_text())["kinematics"])
    got = _urdf_fk(overlaid, "base_link", "wrist_3_link", names, q)
    assert np.abs(got - in_robot).max() < 1e-9
    nominal = _urdf_fk(result.robot.urdf, "base_link", "wrist_3_link", names, q)
    assert np.abs(nominal - in_robot).max() > 1e-4  # the calibration moved the joints


def test_offsets_are_exact_for_a_joint_offset_calibration_and_say_so_otherwise() -> None:
    result = _calibrated("ur10", ("joint_offsets",))
    q, measured, _ = _predictions(result)
    document = yaml.safe_load(exports.export(result, "offsets-yaml"))
    assert document["exact"] is True
    offsets = np.array([row["offset"] for row in document["offsets"]])
    assert np.abs(offsets).max() > 1e-4  # the simulated geometry error moved them
    chain = build_chain(result.robot.urdf, result.robot.base_frame, result.robot.tip_frame)
    camera = np.array(document["measurement_frame"]["matrix"])
    marker = np.array(document["marker"]["matrix"])
    got = camera @ nominal_pose(chain, q + offsets) @ marker
    assert np.abs(got - measured).max() < 1e-9
    rows = list(csv.DictReader(io.StringIO(exports.export(result, "offsets-csv"))))
    assert [float(r["offset"]) for r in rows] == offsets.tolist()
    assert [r["joint"] for r in rows] == result.robot.joint_names
    full = yaml.safe_load(exports.export(_calibrated("ur10"), "offsets-yaml"))
    assert full["exact"] is False
    assert any(line.startswith("link geometry") for line in full["not_expressed"])


def test_export_cli_writes_each_format_and_refuses_unknown_ones(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    result_path = tmp_path / "result.json"
    result_path.write_text(_calibrated("ur10").model_dump_json())
    for format in exports.FORMATS:
        out = tmp_path / f"out{exports.SUFFIX[format]}"
        code, text, err = run(
            ["export", result_path, "--format", format, "-o", out], capsys, monkeypatch
        )
        assert code == 0, err
        assert f"wrote:\n  {out}  {format} export" in text
        # the file is what the reloading tests above checked
        assert out.read_text() == exports.export(_calibrated("ur10"), format)
        assert "not expressed: joint compliance" in err
    code, _, err = run(
        ["export", result_path, "--format", "sdf", "-o", tmp_path / "x"], capsys, monkeypatch
    )
    assert code == 2 and "--format 'sdf': choose one of urdf, offsets-yaml" in err


def test_a_result_correcting_joint_readings_is_refused_in_every_format() -> None:
    from schemas.calibration import ModelCorrection, ModelCorrections
    from solver.errors import KincalError

    correction = ModelCorrection(
        effect="joint_scale",
        joint="elbow_joint",
        variant="linear",
        description="a joint scale error of elbow_joint",
        parameters={"scale": 1e-3},
        applied_in_prediction=True,
    )
    result = _calibrated("ur10").model_copy(
        update={
            "model_corrections": ModelCorrections(
                gravity_base_m_s2=(0.0, 0.0, -9.81),
                payload_kg=0.0,
                corrections=[correction],
                not_carried=[],
            )
        }
    )
    for format in exports.FORMATS:
        with pytest.raises(KincalError, match=f"cannot export {format}: the calibration corrects"):
            exports.export(result, format)
