"""``kincal design --check K`` and ``kincal fleet --check`` through the CLI on the real FR3
recording (issue 33), with the calibration of tests/service/test_check_cli.py: the designed
check poses state smaller changes than random poses of the same candidates, and ``kincal
check`` on them states exactly what design printed; a fleet of units checked against their
results gives each unit's verdict, exit 3 when one drifted, and names a unit whose result or
check recording is missing or of another robot (exit 2)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pandas as pd
import pytest

from schemas.check import CheckResult, FleetCheck
from schemas.design import CheckDesign
from service.app.check import stated_sizes_at
from service.cli.common import read_result
from tests.conftest import REAL_DATA, computed_once
from tests.service.cli_support import run
from tests.service.test_check_cli import BAD_ROWS, FR3, split

SIZES_LINE = "detected and located with 90% probability: "


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, pd.DataFrame]:
    return computed_once(tmp_path_factory, "check-fr3", split)


def sizes_line(stdout: str) -> str:
    lines = [line for line in stdout.splitlines() if line.startswith(SIZES_LINE)]
    assert len(lines) == 1, stdout
    return lines[0]


def test_designed_check_poses_state_smaller_changes_than_random_ones(
    calibrated, tmp_path, capsys, monkeypatch
) -> None:
    """10 check poses from the recording's own clean rows (defaults): the largest stated size
    over its scale (the criterion) is smaller than at 10 random rows in at least 4 of 5 draws,
    and kincal check of those rows states the very sizes design printed."""
    data = pd.read_csv(FR3)
    candidates = data[~data["sample_id"].isin(BAD_ROWS)].reset_index(drop=True)
    candidates.to_csv(tmp_path / "candidates.csv", index=False, float_format="%.17g")
    code, stdout, _ = run(
        ["design", "--check", 10, "--result", calibrated[0], "--candidates",
         tmp_path / "candidates.csv", "--out-dir", tmp_path],
        capsys,
        monkeypatch,
    )  # fmt: skip
    assert code == 0
    design = CheckDesign.model_validate_json((tmp_path / "check_design.json").read_bytes())
    template = pd.read_csv(tmp_path / "check_poses.csv")
    assert f"  {tmp_path / 'check_poses.csv'}  the 10 check poses" in stdout
    assert list(template.columns) == design.joint_names and len(template) == 10
    assert design.worst_relative_size < design.random_worst_relative_size
    rows = [pose.candidate for pose in design.poses]
    joints = [f"q{i + 1}" for i in range(7)]
    np.testing.assert_array_equal(template.to_numpy(), candidates.loc[rows, joints].to_numpy())

    result = read_result(calibrated[0])
    scale = {s.name: s.scale for s in design.stated_sizes}
    designed = max(s.relative for s in design.stated_sizes if s.relative is not None)
    worse = 0
    for seed in range(5):
        drawn = np.random.default_rng(seed).choice(len(candidates), 10, replace=False)
        sizes = stated_sizes_at(result, candidates.loc[drawn, joints].to_numpy(), 0.05, 6)
        worse += max(s.size / scale[s.name] for s in sizes) > designed  # type: ignore[operator]
    assert worse >= 4

    check_rows = candidates.loc[rows]
    check_rows.to_csv(tmp_path / "check.csv", index=False, float_format="%.17g")
    code, check_out, _ = run(
        ["check", calibrated[0], tmp_path / "check.csv", "-o", tmp_path / "check.json"],
        capsys,
        monkeypatch,
    )
    check = CheckResult.model_validate_json((tmp_path / "check.json").read_bytes())
    assert not any(p.bad_sample for p in check.poses)
    assert sizes_line(check_out) == sizes_line(stdout)
    assert [(s.name, s.size) for s in check.stated_sizes] == [
        (s.name, s.size) for s in design.stated_sizes
    ]


def test_design_check_needs_a_result_and_three_poses(
    calibrated, tmp_path, capsys, monkeypatch
) -> None:
    code, _, stderr = run(["design", "--check", 10, "--robot", "panda"], capsys, monkeypatch)
    assert code == 2 and "--robot: --check designs check poses of --result" in stderr
    # A flag given at its default value is given all the same.
    code, _, stderr = run(
        ["design", "--check", 10, "--no-allow-repeats", "--poses", 25], capsys, monkeypatch
    )
    assert code == 2 and "--poses, --allow-repeats: --check designs check poses" in stderr
    code, _, stderr = run(["design", "--check", 10], capsys, monkeypatch)
    assert code == 2 and "give --result" in stderr
    code, _, stderr = run(
        ["design", "--check", 2, "--result", calibrated[0], "--out-dir", tmp_path],
        capsys,
        monkeypatch,
    )
    assert code == 2 and "at least 3 poses" in stderr


def fleet(calibrated: tuple[Path, pd.DataFrame], folder: Path) -> tuple[Path, Path]:
    """Two units calibrated alike: arm_a checked on its held-out rows, arm_b on the same rows
    with its joint 3 reading 2 mrad off (as tests/service/test_check_cli.py conceals it)."""
    checks, results = folder / "checks", folder / "results"
    checks.mkdir()
    results.mkdir()
    held = calibrated[1]
    held.to_csv(checks / "arm_a.csv", index=False, float_format="%.17g")
    off = held.copy()
    off["q3"] += 0.002
    off.to_csv(checks / "arm_b.csv", index=False, float_format="%.17g")
    for unit in ("arm_a", "arm_b"):
        shutil.copy(calibrated[0], results / f"{unit}.json")
    return checks, results


def test_a_fleet_check_gives_each_unit_its_verdict(
    calibrated, tmp_path, capsys, monkeypatch
) -> None:
    checks, results = fleet(calibrated, tmp_path)
    out = tmp_path / "fleet_check.json"
    code, stdout, _ = run(["fleet", checks, "--check", results, "-o", out], capsys, monkeypatch)
    assert code == 3
    report = FleetCheck.model_validate_json(out.read_bytes())
    verdicts = {u.unit: u.check.verdict for u in report.units}
    assert verdicts == {"arm_a": "holds", "arm_b": "drifted"}
    assert report.holds == ["arm_a"] and report.drifted == ["arm_b"]
    located = report.units[1].check.located
    assert located is not None and located.name == "panda_joint3 offset"
    lines = stdout.splitlines()
    assert lines[1].split()[:2] == ["arm_a", "holds"]
    assert lines[2].split()[:2] == ["arm_b", "drifted"] and "panda_joint3 offset" in lines[2]
    assert f"  {out}  checks of 2 units" in stdout
    assert lines[-1].startswith("fleet check: 2 units: 1 hold, 1 drifted (arm_b), 0 inconclusive")
    assert "family-wise level 0.05" in lines[-1] and lines[-1].endswith("(exit code 3)")
    assert json.loads(out.read_text())["format"] == "kincal.fleet-check/1"


def test_a_unit_without_its_result_or_of_another_robot_is_named(
    calibrated, tmp_path, capsys, monkeypatch
) -> None:
    checks, results = fleet(calibrated, tmp_path)
    ur10 = REAL_DATA / "figaroh_ur10_experiment" / "calibration.csv"
    shutil.copy(ur10, checks / "arm_c.csv")
    args = ["fleet", checks, "--check", results, "--out-dir", tmp_path]
    code, _, stderr = run(args, capsys, monkeypatch)
    assert code == 2 and len(stderr.strip().splitlines()) == 1
    assert "unit(s) arm_c: a check recording" in stderr and "no calibration result" in stderr
    shutil.copy(calibrated[0], results / "arm_c.json")
    code, _, stderr = run(args, capsys, monkeypatch)
    assert code == 2 and len(stderr.strip().splitlines()) == 1
    assert "unit arm_c: check recording: not a recording of the calibrated robot" in stderr
    (checks / "arm_c.csv").unlink()
    code, _, stderr = run(args, capsys, monkeypatch)
    assert code == 2 and "unit(s) arm_c: a calibration result" in stderr
    assert "no check recording" in stderr


def test_a_fleet_check_refuses_the_flags_of_calibrating_a_fleet(
    tmp_path, capsys, monkeypatch
) -> None:
    args = ["fleet", tmp_path, "--check", tmp_path, "--z-threshold", 3.5, "--robot", "panda"]
    code, _, stderr = run(args, capsys, monkeypatch)
    assert code == 2 and len(stderr.strip().splitlines()) == 1
    assert "--robot, --z-threshold: --check checks each unit against its result" in stderr
