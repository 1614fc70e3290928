"""``kincal discover`` on measurements other than a marker pose (issue 15): a concealed joint
compliance is named with the right joint and size on simulated ball-in-socket rows, three-marker
rows and plane-contact rows (tz, rx, ry), and nothing is named on the same rows without it.

The recordings are simulated independently of discovery's model: ball in socket by damped
Newton on the rigid chain's tool point (``configurations_at_points``) to two sockets 50 mm
apart with 0.05 mm of play, the compliance then hidden in the recorded joint angle (the link
sits at ``q_recorded + c·τ(q)``); markers by the forward kinematics of a chain that carries
the compliance, three markers at their own offsets on the flange.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from solver import lie
from solver.kinematics import ChainParameters, forward_kinematics
from solver.measurement import EyeOnHead, MeasurementRows
from solver.measurement.simulate import configurations_at_points
from solver.model import KinematicChain, build_chain, gravity_loads, sample_configurations
from tests.conftest import robot
from tests.service.cli_support import run

COMPLIANCE_RAD_PER_NM = 3e-5  # on panda_joint2: ~0.7 mrad of deflection at its load scatter
NOISE_M = 5e-5
SOCKETS_M = np.array([[0.45, -0.025, 0.25], [0.45, 0.025, 0.25]])  # 50 mm apart


def _chains() -> tuple[KinematicChain, KinematicChain]:
    """The Panda without compliance and with one on panda_joint2."""
    d = robot("panda")
    rigid = build_chain(d.urdf_xml, d.base_frame, d.tip_frame, compliant_joints=[])
    soft = build_chain(d.urdf_xml, d.base_frame, d.tip_frame, compliant_joints=["panda_joint2"])
    return rigid, soft


def write_socket_folder(folder: Path, compliance: float, seed: int = 3) -> int:
    """hole_0.csv, hole_1.csv (headerless joint angles) of the ball in two sockets; returns
    the number of rows (about 300: starts whose Newton solution stays within the limits)."""
    rigid, soft = _chains()
    rng = np.random.default_rng(seed)
    n = 800
    group = np.arange(n) % 2
    targets = SOCKETS_M[group] + NOISE_M * rng.standard_normal((n, 3))
    start = sample_configurations(rigid, n, rng)
    nominal = ChainParameters.nominal(rigid)
    q = configurations_at_points(rigid, nominal, targets, start)
    reached = forward_kinematics(rigid, nominal, q, np.zeros((n, 0)))[:, :3, 3]
    ok = (np.linalg.norm(reached - targets, axis=1) < 1e-9) & np.all(
        (q >= rigid.lower_limits) & (q <= rigid.upper_limits), axis=1
    )
    recorded = q.copy()
    recorded[:, 1] -= compliance * gravity_loads(soft, q)[:, 0]
    folder.mkdir(parents=True)
    for g in range(2):
        rows = recorded[ok & (group == g)]
        np.savetxt(folder / f"hole_{g}.csv", rows, delimiter=",", fmt="%.12f")
    return int(ok.sum())


def write_marker_file(path: Path, compliance: float, seed: int = 4, gear_rad: float = 0.0) -> None:
    """A FIGAROH-style CSV: joint columns and x1,y1,z1,…,z3 of three markers on the flange,
    in a measurement frame away from the base; with ``gear_rad`` panda_joint4 stands at its
    reading plus ``gear_rad·sin(q)`` (a periodic transmission error hidden in the reading)."""
    _, soft = _chains()
    rng = np.random.default_rng(seed)
    n = 200
    q = sample_configurations(soft, n, rng)
    loads = gravity_loads(soft, q)
    params = ChainParameters(soft.nominal_links.copy(), np.array([compliance]))
    params.links[0] = lie.se3_exp(np.array([1.2, -0.3, 0.4, 0.1, -0.2, 0.3])) @ params.links[0]
    pose = forward_kinematics(soft, params, q, loads)
    offsets = np.array([[0.05, 0.0, 0.02], [-0.03, 0.04, 0.03], [0.0, -0.05, 0.06]])
    points = pose[:, None, :3, 3] + np.einsum("nij,mj->nmi", pose[:, :3, :3], offsets)
    points += NOISE_M * rng.standard_normal(points.shape)
    recorded = q.copy()
    recorded[:, 3] -= gear_rad * np.sin(q[:, 3])
    table = {name: recorded[:, j] for j, name in enumerate(soft.joint_names)}
    for m in range(3):
        for a, axis in enumerate("xyz"):
            table[f"{axis}{m + 1}"] = points[:, m, a]
    pd.DataFrame(table).to_csv(path, index=False)


def _write_noisy_poses(
    path: Path, c: KinematicChain, q: np.ndarray, pose: np.ndarray, rng: np.random.Generator
) -> None:
    """A pose CSV (joint columns, x,y,z, quaternion) of ``pose`` (N, 4, 4) with NOISE_M m / rad
    of noise per component (tip frame)."""
    pose = pose @ lie.se3_exp(NOISE_M * rng.standard_normal((q.shape[0], 6)))
    table = {name: q[:, j] for j, name in enumerate(c.joint_names)}
    table.update({axis: pose[:, a, 3] for a, axis in enumerate("xyz")})
    quaternion = lie.matrix_to_quaternion_xyzw(pose[:, :3, :3])
    table.update({name: quaternion[:, a] for a, name in enumerate(("qx", "qy", "qz", "qw"))})
    pd.DataFrame(table).to_csv(path, index=False)


def write_pose_file(path: Path, compliance: float, seed: int = 6) -> None:
    """A pose CSV (x,y,z, quaternion) of the compliant chain in a measurement frame near the
    robot base, 0.05 mm / 0.05 mrad of noise: a plane contact reads tz, rx, ry of it."""
    _, soft = _chains()
    rng = np.random.default_rng(seed)
    n = 300
    q = sample_configurations(soft, n, rng)
    loads = gravity_loads(soft, q)
    params = ChainParameters(soft.nominal_links.copy(), np.array([compliance]))
    frame = lie.se3_exp(np.array([2e-3, -3e-3, 4e-3, 1e-3, -2e-3, 3e-3]))
    params.links[0] = frame @ params.links[0]
    pose = forward_kinematics(soft, params, q, loads)
    _write_noisy_poses(path, soft, q, pose, rng)


def _discover(
    args: list[object],
    out: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    sizes: bool = True,
) -> dict:
    """``kincal discover`` on ``args``; ``sizes=False``: without the detectable sizes (they
    change nothing discovery names; the rigid runs check them)."""
    flags = [] if sizes else ["--no-detectability"]
    code, _, stderr = run(
        ["discover", *args, "--robot", "panda", "-o", out, "--no-plots", *flags],
        capsys,
        monkeypatch,
    )
    assert code == 0, stderr
    return dict(json.loads(out.read_text()))


def _sized(findings: dict) -> list[dict]:
    """The finite detectable sizes of a findings document (the rows state some)."""
    sizes = [s for s in findings["detectability"]["sizes"] if s["smallest"] is not None]
    assert sizes and all(s["smallest"] > 0.0 for s in sizes)
    return sizes


def _compliance_named(findings: dict) -> float:
    named = [(f["effect"], f["joint"]) for f in findings["findings"]]
    assert named == [("joint_compliance", "panda_joint2")], named
    (value,) = findings["findings"][0]["parameters"].values()
    return float(value)


@pytest.mark.parametrize("compliance", [COMPLIANCE_RAD_PER_NM, 0.0], ids=["compliant", "rigid"])
def test_ball_in_socket_discovery_names_a_concealed_compliance(
    compliance: float,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    n = write_socket_folder(tmp_path / "arm", compliance)
    assert n >= 250
    findings = _discover(
        [tmp_path / "arm", "--point-distance", "0.05"],
        tmp_path / "f.json",
        capsys,
        monkeypatch,
        sizes=compliance == 0.0,
    )
    measurement = findings["measurement"]
    assert measurement["type"] == "point"
    assert measurement["labels"] == ["hole_0", "hole_1"]
    assert abs(measurement["constraint_residuals_m"][0]) < 1e-9  # the known distance holds
    assert any(line.startswith("depth_scale:") for line in measurement["left_out"])
    assert "depth_scale" not in findings["options"]["effects"]
    assert findings["dataset"]["n_samples"] == n
    if compliance == 0.0:
        assert findings["findings"] == [] and findings["ambiguous"] == []
        _sized(findings)
        return
    value = _compliance_named(findings)
    assert abs(value / compliance - 1.0) < 0.2, value
    # the held-out ball-centre scatter drops to the socket play (mean 3-D norm ≈ 1.6 σ)
    assert findings["heldout"]["after"]["trans_mm"] < 1.3 * 1.6 * NOISE_M * 1e3
    heldout = findings["heldout"]
    assert heldout["before"]["trans_mm"] > 1.5 * heldout["after"]["trans_mm"]


@pytest.mark.parametrize("compliance", [COMPLIANCE_RAD_PER_NM, 0.0], ids=["compliant", "rigid"])
def test_three_marker_discovery_names_a_concealed_compliance(
    compliance: float,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    write_marker_file(tmp_path / "markers.csv", compliance)
    findings = _discover(
        [tmp_path / "markers.csv"], tmp_path / "f.json", capsys, monkeypatch, compliance == 0.0
    )
    measurement = findings["measurement"]
    assert measurement["type"] == "markers"
    assert len(measurement["components"]) == 9
    offsets = np.array([measurement["unknowns"][f"marker_1.{a}"] for a in "xyz"])
    assert offsets.shape == (3,)
    if compliance == 0.0:
        assert findings["findings"] == [] and findings["ambiguous"] == []
        _sized(findings)
        return
    value = _compliance_named(findings)
    assert abs(value / compliance - 1.0) < 0.2, value


@pytest.mark.parametrize("compliance", [COMPLIANCE_RAD_PER_NM, 0.0], ids=["compliant", "rigid"])
def test_plane_contact_discovery_names_a_concealed_compliance(
    compliance: float,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    write_pose_file(tmp_path / "poses.csv", compliance)
    findings = _discover(
        [tmp_path / "poses.csv", "--measurement", "components:tz,rx,ry"],
        tmp_path / "f.json",
        capsys,
        monkeypatch,
        sizes=compliance == 0.0,
    )
    assert findings["measurement"]["components"] == ["tz", "rx", "ry"]
    assert findings["measurement"]["frame"] == "measurement frame"
    if compliance == 0.0:
        assert findings["findings"] == [] and findings["ambiguous"] == []
        _sized(findings)
        return
    value = _compliance_named(findings)
    assert abs(value / compliance - 1.0) < 0.2, value


def write_eye_on_head_file(
    path: Path, joint: str, compliance: float, seed: int = 7, backlash_rad: float = 0.0
) -> None:
    """A pose CSV of the tip seen by a sensor riding on the body after panda_joint2 (mounted
    0.23 m and 37° away from that body's frame), 300 rows, 0.05 mm / 0.05 mrad of noise, from
    a chain carrying a compliance on ``joint`` under the full gravity load (the simulator of
    the eye-on-head calibration tests: :meth:`EyeOnHead.predicted_pose`); with
    ``backlash_rad`` the link of ``joint`` stands at its reading + ½·backlash·sign(its load)."""
    d = robot("panda")
    soft = build_chain(d.urdf_xml, d.base_frame, d.tip_frame, compliant_joints=[joint])
    rng = np.random.default_rng(seed)
    n = 300
    q = sample_configurations(soft, n, rng)
    loads = gravity_loads(soft, q)
    params = ChainParameters(soft.nominal_links.copy(), np.array([compliance]))
    mount = lie.se3_exp(np.array([0.05, -0.1, 0.2, 0.3, -0.2, 0.5]))
    params.links[2] = lie.inverse(mount) @ params.links[2]
    rows = MeasurementRows.of(q, loads, np.zeros((n, 4, 4)))
    pose = EyeOnHead(sensor_joint=1).predicted_pose(soft, params, rows)
    recorded = q.copy()
    recorded[:, soft.joint_names.index(joint)] -= 0.5 * backlash_rad * np.sign(loads[:, 0])
    _write_noisy_poses(path, soft, recorded, pose, rng)


BACKLASH_RAD = 3e-4


@pytest.mark.parametrize(
    ("joint", "compliance", "backlash"),
    [
        ("panda_joint4", COMPLIANCE_RAD_PER_NM, 0.0),
        ("panda_joint4", 0.0, BACKLASH_RAD),
        ("panda_joint4", 0.0, 0.0),
        ("panda_joint2", 3e-4, 0.0),
    ],
    ids=["compliance-after-sensor", "backlash-after-sensor", "rigid", "at-sensor"],
)
def test_eye_on_head_discovery_names_a_term_after_the_sensor(
    joint: str,
    compliance: float,
    backlash: float,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Sensor after panda_joint2: a compliance or a load-sign backlash of panda_joint4 is named
    with its size; nothing is named on rigid rows, nor for a tenfold compliance of panda_joint2
    itself, which moves the sensor and the tip alike — that joint's terms are listed as not
    candidates, with the reason, and so is every term of panda_joint1 (decided by their
    columns). The detectable sizes (most of a run's time) are checked on the rigid rows: none is
    stated for a term that is not a candidate."""
    write_eye_on_head_file(tmp_path / "eye.csv", joint, compliance, backlash_rad=backlash)
    rigid = compliance == backlash == 0.0
    findings = _discover(
        [tmp_path / "eye.csv", "--measurement", "eye-on-head:panda_joint2"],
        tmp_path / "f.json",
        capsys,
        monkeypatch,
        sizes=rigid,
    )
    measurement = findings["measurement"]
    assert measurement["type"] == "eye-on-head:panda_joint2"
    unseen = measurement["not_candidates"]
    assert {u["joint"] for u in unseen} == {"panda_joint1", "panda_joint2"}
    by_term = {(u["effect"], u["joint"]): u for u in unseen}
    before = by_term[("joint_compliance", "panda_joint2")]
    assert before["remaining_fraction"] < 1e-12
    assert "moves the sensor and the tip alike" in before["reason"]
    assert ("gear_periodic", "panda_joint1") in by_term and (
        "joint_scale",
        "panda_joint2",
    ) in by_term
    if rigid:
        sized = {(s["effect"], s["joint"]) for s in findings["detectability"]["sizes"]}
        assert ("joint_compliance", "panda_joint3") in sized and not sized & set(by_term)
    if joint == "panda_joint2" or rigid:
        assert findings["findings"] == [] and findings["ambiguous"] == [], findings["findings"]
        return
    named = [(f["effect"], f["joint"], f["variant"]) for f in findings["findings"]]
    effect, truth = ("joint_compliance", compliance) if compliance else ("backlash", backlash)
    assert named == [(effect, "panda_joint4", "" if compliance else "load")], named
    (value,) = findings["findings"][0]["parameters"].values()
    assert abs(value / truth - 1.0) < 0.2, value


def test_eye_on_head_discovery_refuses_a_joint_off_the_chain(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    write_eye_on_head_file(tmp_path / "eye.csv", "panda_joint4", 0.0)
    code, _, stderr = run(
        [
            *("discover", tmp_path / "eye.csv", "--robot", "panda"),
            *("--measurement", "eye-on-head:panda_joint7", "-o", tmp_path / "f.json"),
        ],
        capsys,
        monkeypatch,
    )
    assert code == 2
    assert "eye-on-head:panda_joint7: not a joint of the chain before its last" in stderr


def test_http_discovery_refuses_measurements_of_a_folder_or_every_marker(tmp_path: Path) -> None:
    """The service discovers on one uploaded dataset: 'point' gets a 422 problem naming
    ``kincal discover``; 'eye-on-head' with a joint off the chain a 422 naming the joints."""
    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from tests.service.api.conftest import fresh_database_url, make_settings, upload_csv

    with (
        fresh_database_url(tmp_path) as url,
        TestClient(create_app(make_settings(tmp_path, url))) as client,
    ):
        dataset = upload_csv(client).json()
        responses = [
            client.post(
                "/api/v1/discoveries",
                json={"dataset_id": dataset["id"], "options": {"measurement": measurement}},
            )
            for measurement in ("point", "eye-on-head:tool0")
        ]
    expected = ("kincal discover", "not a joint of the chain before its last")
    for response, text in zip(responses, expected, strict=True):
        assert response.status_code == 422, response.text
        assert response.headers["content-type"].startswith("application/problem+json")
        assert text in response.json()["detail"]
