"""The exported URDF is plain URDF that Pinocchio loads, and reproduces kincal's calibrated FK."""

from __future__ import annotations

import functools

import numpy as np
import pinocchio as pin
import pytest

from schemas.calibration import CalibrationOptions, CalibrationResult
from service.app import calibrate as pipeline
from service.app import simulate as scenarios
from service.render import result_json
from service.render.urdf_export import MARKER_LINK, MEASUREMENT_LINK, export_urdf
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import sample_configurations
from tests.conftest import robot


@functools.cache
def _calibrated(name: str) -> CalibrationResult:
    description = robot(name)
    scn, recording = scenarios.simulate(
        description, n_samples=120, seed=5, effects=("geometry", "compliance", "camera", "marker")
    )
    dataset = scenarios.recording_dataset(recording, scn.chain, rotation=True)
    options = CalibrationOptions(heldout=False, outlier_sigma=None)
    return pipeline.calibrate(dataset, description, options)


@pytest.mark.parametrize("name", ["kinova", "panda", "ur10"])
def test_exported_urdf_reproduces_calibrated_fk(name: str) -> None:
    result = _calibrated(name)
    chain, params = result_json.result_chain(result)
    assert np.any(params.compliance_rad_per_nm != 0.0)  # the test covers a compliant calibration
    model = pin.buildModelFromXML(export_urdf(result, measurement_frame=True))
    data = model.createData()
    q = sample_configurations(chain, 100, np.random.default_rng(1))
    rigid = ChainParameters(params.links, np.zeros_like(params.compliance_rad_per_nm))
    expected = forward_kinematics(chain, rigid, q, np.zeros((100, len(chain.compliance_axes))))
    root, marker = model.getFrameId(MEASUREMENT_LINK), model.getFrameId(MARKER_LINK)
    q_exported = np.tile(pin.neutral(model), (100, 1))
    for column, joint_name in enumerate(chain.joint_names):
        joint = model.joints[model.getJointId(joint_name)]
        if joint.nq == 1:
            q_exported[:, joint.idx_q] = q[:, column]
        else:
            q_exported[:, joint.idx_q : joint.idx_q + 2] = np.c_[
                np.cos(q[:, column]), np.sin(q[:, column])
            ]
    for n in range(100):
        pin.framesForwardKinematics(model, data, q_exported[n])
        pose = (data.oMf[root].inverse() * data.oMf[marker]).homogeneous
        assert np.abs(pose - expected[n]).max() < 1e-9


def test_exported_urdf_records_compliance_and_keeps_everything_else() -> None:
    result = _calibrated("panda")
    text = export_urdf(result, measurement_frame=True)
    for entry in result.compliance:
        assert f"{entry.axis}: {entry.value_rad_per_nm!r} rad/Nm" in text
    original = pin.buildModelFromXML(result.robot.urdf)
    exported = pin.buildModelFromXML(text)
    assert list(exported.names) == list(original.names)  # same joints, fingers included
    assert exported.nframes == original.nframes + 4  # two links + two fixed joints added
