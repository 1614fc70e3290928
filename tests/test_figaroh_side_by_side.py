"""benchmarks/figaroh_side_by_side.py: its table and acceptance column, and (when a FIGAROH
interpreter is given) kincal and FIGAROH on the same splits of the UR10e recording."""

from __future__ import annotations

import dataclasses
import os

import pytest

from benchmarks import figaroh_side_by_side as side
from schemas.calibration import CalibrationOptions
from solver.kinematics import parameter_names


def test_table_reports_mean_and_standard_error_and_the_acceptance() -> None:
    row = side.SideBySide(
        "R", 10, 9, [1.0, 2.0, 3.0], [1.0, 1.1, 1.2], [1.0, 1.0, 1.3], 0.01, 1.0, [0.5] * 3, 30
    )
    text = side.table([row])
    assert "| R | 10 (9) | 2.00 ± 0.58 | 1.10 ± 0.06 | 1.10 ± 0.10 | no / yes |" in text
    assert "| 0.010 | 0.50 | 50× | 1.0 | – |" in text
    checked = side.table([dataclasses.replace(row, same_parameters_mm=[1.0, 1.0, 1.3])])
    assert checked.endswith("| 1.0 | 1.10 ± 0.10 |")


def test_figaroh_parameter_names_map_to_kincal_columns() -> None:
    """FIGAROH's base frame is kincal's first link, its marker the tip link, ``d_<c>_<joint>``
    the joint's placement."""
    (tiago,) = [r for r in side.RECORDINGS if r.name == "TIAGo"]
    chain = side.pipeline.check_calibration(side.robot_of(tiago), CalibrationOptions()).chain
    names = ["base_px", "base_phiz", "d_phiy_arm_1_joint", "d_pz_arm_7_joint", "pEEy_1"]
    columns = side.figaroh_columns(chain, names)
    assert [parameter_names(chain)[c] for c in columns] == [
        "torso_lift_joint.tx",
        "torso_lift_joint.rz",
        "arm_1_joint.ry",
        "arm_7_joint.tz",
        "arm_tool_link.ty",
    ]


@pytest.mark.skipif(
    "KINCAL_FIGAROH_PYTHON" not in os.environ,
    reason="FIGAROH is not a kincal dependency: set KINCAL_FIGAROH_PYTHON to its interpreter",
)
def test_figaroh_and_kincal_on_the_same_splits_of_a_real_recording() -> None:
    (ur10e,) = [r for r in side.RECORDINGS if r.name == "UR10e"]
    row = side.compare(ur10e, 2, os.environ["KINCAL_FIGAROH_PYTHON"])
    assert len(row.kincal_mm) == len(row.same_model_mm) == len(row.figaroh_mm) == 2
    assert all(0.5 < v < 20.0 for v in row.kincal_mm + row.same_model_mm + row.figaroh_mm)
    # same rows, same parameters, no physical-range rule: FIGAROH's numbers (docs/figaroh.md)
    assert row.same_parameters_mm is not None
    for kincal, figaroh in zip(row.same_parameters_mm, row.figaroh_mm, strict=True):
        assert abs(kincal - figaroh) < 0.02, (row.same_parameters_mm, row.figaroh_mm)
