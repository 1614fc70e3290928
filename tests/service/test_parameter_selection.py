"""Choosing what to calibrate (issue 15): free / fixed parameters by class and by name through
``kincal calibrate --free/--fix``; fixed parameters stay at their starting value and get no
standard error; unknown names are refused with the valid ones listed."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from schemas.dataset import PoseDataset, write_dataset
from solver import lie
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import build_chain, sample_configurations
from tests.conftest import robot
from tests.service.cli_support import run

NOISE_M, NOISE_RAD = 2e-5, 2e-5


@pytest.fixture(scope="module")
def offsets_recording(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    """UR10 whose only errors are joint offsets (plus an unknown camera and marker)."""
    description = robot("ur10")
    chain = build_chain(description.urdf_xml, description.base_frame, description.tip_frame)
    rng = np.random.default_rng(11)
    offsets = rng.normal(0.0, 0.01, chain.n_joints)
    twists = np.zeros((chain.n_links, 6))
    for j in range(1, chain.n_joints):  # joint 1's offset is the camera's yaw: not separable
        twists[j] = offsets[j] * chain.joint_screws[j]
    params = ChainParameters.nominal(chain).with_link_corrections(twists)
    camera = lie.se3_exp(np.array([0.3, -0.2, 1.0, 0.2, -0.1, 0.5]))
    marker = lie.se3_exp(np.array([0.01, 0.02, 0.05, 0.1, 0.0, -0.2]))
    links = params.links.copy()
    links[0] = camera @ links[0]
    links[-1] = links[-1] @ marker
    truth = ChainParameters(links, params.compliance_rad_per_nm)
    q = sample_configurations(chain, 60, rng, range_fraction=0.6)
    pose = forward_kinematics(chain, truth, q, np.zeros((60, len(chain.compliance_axes))))
    noise = np.concatenate(
        [rng.normal(0, NOISE_M, (60, 3)), rng.normal(0, NOISE_RAD, (60, 3))], axis=1
    )
    pose = pose @ lie.se3_exp(noise)
    folder = tmp_path_factory.mktemp("selection")
    data = folder / "offsets.csv"
    write_dataset(
        PoseDataset(
            chain.joint_names, q, pose[:, :3, 3], lie.matrix_to_quaternion_xyzw(pose[:, :3, :3])
        ),
        data,
    )
    return {"chain": chain, "offsets": offsets, "data": data, "folder": folder}


def _calibrate(
    recording: dict[str, Any], args: list[str], capsys: Any, monkeypatch: Any
) -> dict[str, Any]:
    out = recording["folder"] / f"r{abs(hash(tuple(args)))}.json"
    base = ["calibrate", recording["data"], "--robot", "ur10", "-o", out, "--rigid"]
    code, _, err = run([*base, "--covariance", "none", "--no-heldout", *args], capsys, monkeypatch)
    assert code in (0, 3), err
    result: dict[str, Any] = json.loads(Path(out).read_text())
    return result


def test_joint_offsets_only_recovers_the_offsets_within_three_standard_errors(
    offsets_recording: dict[str, Any],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    chain = offsets_recording["chain"]
    result = _calibrate(offsets_recording, ["--free", "joint_offsets"], capsys, monkeypatch)
    fixed = set(result["identifiability"]["fixed"])
    links = {link["link"]: link for link in result["links"]}
    # the first joint's offset is the camera's, the last one's the marker's: not separable
    components = ("tx", "ty", "tz", "rx", "ry", "rz")
    last_axis = components[int(np.argmax(np.abs(chain.joint_screws[-1])))]
    assert f"{chain.joint_names[-1]}.{last_axis}" in result["identifiability"]["removed"]
    for j in range(1, chain.n_joints - 1):
        name = chain.joint_names[j]
        link = links[name]
        nominal = chain.nominal_links[j]
        twist = lie.se3_log(lie.inverse(nominal) @ np.array(link["placement"]))
        screw = chain.joint_screws[j]
        axis = int(np.argmax(np.abs(screw)))
        estimate = float(twist @ screw)
        stderr = (link["stderr_translation_m"] + link["stderr_rotation_rad"])[axis]
        assert stderr is not None and stderr > 0.0
        assert abs(estimate - offsets_recording["offsets"][j]) < 3.0 * stderr, name
        # every other component is fixed: exactly nominal, no standard error
        others = [c for c in range(6) if c != axis]
        assert np.abs(twist[others]).max() < 1e-12
        assert {f"{name}.{components[c]}" for c in others} <= fixed
        assert all(
            (link["stderr_translation_m"] + link["stderr_rotation_rad"])[c] is None for c in others
        )
    # the same data with every parameter free fits no better than the truth's noise allows
    assert result["fit"]["after"]["train"]["translation_rms_mm"] < 3 * np.sqrt(3) * NOISE_M * 1e3


def test_a_fixed_link_stays_nominal_and_compliance_can_be_fixed(
    offsets_recording: dict[str, Any],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    chain = offsets_recording["chain"]
    result = _calibrate(
        offsets_recording, ["--fix", "elbow_joint,wrist_1_joint.t*"], capsys, monkeypatch
    )
    links = {link["link"]: link for link in result["links"]}
    elbow = chain.joint_names.index("elbow_joint")
    assert np.allclose(links["elbow_joint"]["placement"], chain.nominal_links[elbow], atol=0.0)
    assert links["elbow_joint"]["stderr_rotation_rad"] == [None, None, None]
    wrist = links["wrist_1_joint"]
    assert wrist["stderr_translation_m"] == [None, None, None]
    assert any(v is not None for v in wrist["stderr_rotation_rad"])
    fixed = result["identifiability"]["fixed"]
    assert "elbow_joint.rz" in fixed and "wrist_1_joint.tx" in fixed
    assert not set(fixed) & set(result["identifiability"]["removed"])


def test_unknown_names_are_refused_listing_the_valid_ones(
    offsets_recording: dict[str, Any],
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    base = ["calibrate", offsets_recording["data"], "--robot", "ur10", "-o", "/dev/null"]
    code, _, err = run([*base, "--fix", "torso"], capsys, monkeypatch)
    assert code == 2 and err.count("\n") == 1
    assert "fixed_parameters: 'torso' names no parameter" in err
    assert "joint_offsets" in err and "elbow_joint" in err
    code, _, err = run([*base, "--free", "base", "--fix", "base,tool"], capsys, monkeypatch)
    assert code == 2 and "leave nothing to calibrate" in err


def test_http_refuses_unknown_names_with_a_problem(tmp_path: Path) -> None:
    from fastapi.testclient import TestClient

    from service.api.app import create_app
    from tests.service.api.conftest import (
        assert_problem,
        fresh_database_url,
        make_settings,
        upload_csv,
    )

    with (
        fresh_database_url(tmp_path) as url,
        TestClient(create_app(make_settings(tmp_path, url))) as client,
    ):
        dataset = upload_csv(client).json()
        response = client.post(
            "/api/v1/calibrations",
            json={"dataset_id": dataset["id"], "options": {"fixed_parameters": ["torso"]}},
        )
        assert_problem(response, 422, "fixed_parameters: 'torso' names no parameter", "elbow")
        accepted = client.post(
            "/api/v1/calibrations",
            json={"dataset_id": dataset["id"], "options": {"free_parameters": ["joint_offsets"]}},
        )
    assert accepted.status_code == 202, accepted.text
