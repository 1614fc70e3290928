"""``kincal discover``: the findings JSON contract, plots next to it, one-line errors."""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest

from schemas.discovery import EFFECTS, FindingsResult
from service import cli, discovery
from tests.conftest import chain


def run(
    args: list[str], capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> tuple[int, str, str]:
    monkeypatch.setattr(sys, "argv", ["kincal", *args])
    code = 0
    try:
        cli.main()
    except SystemExit as exc:
        code = int(exc.code or 0)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture(scope="module")
def findings_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A Jaco2 recording with a hidden 2nd-harmonic gear error on joint 3, discovered."""
    folder = tmp_path_factory.mktemp("discover")
    data = folder / "gear.csv"
    monkeypatch = pytest.MonkeyPatch()
    try:
        effects = [f"--effect={e}" for e in ("geometry", "camera", "marker", "gear_error")]
        output = str(folder / "out" / "findings.json")
        for args in (
            [
                "simulate",
                "--robot",
                "kinova",
                "--n",
                "150",
                "--seed",
                "5",
                "-o",
                str(data),
                *effects,
            ],
            ["discover", str(data), "--robot", "kinova", "--bootstrap", "10", "-o", output],
        ):
            monkeypatch.setattr(sys, "argv", ["kincal", *args])
            with pytest.raises(SystemExit) as exit_info:
                cli.main()
                raise SystemExit(0)
            assert exit_info.value.code in (0, None)
    finally:
        monkeypatch.undo()
    return folder / "out" / "findings.json"


def test_findings_json_has_the_issue_shape(findings_path: Path) -> None:
    document = json.loads(findings_path.read_text())
    assert {"findings", "ambiguous", "unexplained", "heldout"} <= set(document)
    for finding in document["findings"]:
        assert {
            "effect",
            "joint",
            "parameters",
            "stderr",
            "p_value",
            "absorbed_fraction",
            "explanation",
        } <= set(finding)
        assert finding["effect"] in EFFECTS
    for phase in ("before", "after"):
        assert set(document["heldout"][phase]) == {"trans_mm", "rot_deg"}
    FindingsResult.model_validate(document)


def test_discover_names_the_hidden_gear_error_and_improves_heldout(findings_path: Path) -> None:
    result = FindingsResult.model_validate_json(findings_path.read_bytes())
    third = chain("kinova").joint_names[2]
    assert [(f.effect, f.joint, f.variant) for f in result.findings] == [
        ("gear_periodic", third, "h2")
    ]
    assert result.heldout.after.trans_mm < 0.8 * result.heldout.before.trans_mm
    assert result.model.not_carried == [f"gear_periodic (h2) on {third}"]
    assert discovery.calibration_options(result).compliant_joints == []


def test_a_plot_per_finding_is_written_next_to_the_json(findings_path: Path) -> None:
    result = FindingsResult.model_validate_json(findings_path.read_bytes())
    assert result.plots and result.plots == [f.plot for f in result.findings]
    for name in result.plots:
        png = findings_path.parent / name
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize(
    ("extra", "expected"),
    [
        (["--effects", "joint_compliance,warp_drive"], "effects"),
        (["--alpha", "2"], "alpha"),
        (["--compliant-joints", "no_such_joint"], "no_such_joint"),
    ],
)
def test_bad_discover_input_gives_one_line_and_exit_code_2(
    extra: list[str],
    expected: str,
    findings_path: Path,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    data = findings_path.parent.parent / "gear.csv"
    args = ["discover", str(data), "--robot", "kinova", "-o", str(tmp_path / "f.json"), *extra]
    code, _, err = run(args, capsys, monkeypatch)
    assert code == 2
    assert err.count("\n") == 1 and expected in err and err.startswith("kincal: error:")


def test_fr3_negative_compliance_is_reported_not_named() -> None:
    """Real FR3 recording, all loaded joints declared elastic: the springs fit negative (the
    calibration's ">5σ negative compliance"); discovery must say so, not name a physics."""
    from schemas.dataset import read_dataset
    from schemas.discovery import DiscoveryOptions
    from tests.conftest import REAL_DATA, robot

    joints = [f"panda_joint{i}" for i in range(2, 8)]
    options = DiscoveryOptions(compliant_joints=joints, bootstrap=10)
    description = robot("panda")
    model = discovery.chain_for(description, options)
    dataset = read_dataset(
        REAL_DATA / "philnad_fr3_eye_in_hand" / "fr3_poses.csv", model.joint_names
    )
    result = discovery.discover(dataset, description, options)
    declared = {u.joint for u in result.unexplained if u.variable == "declared"}
    assert {"panda_joint2", "panda_joint3"} <= declared
    assert all(f.effect != "joint_compliance" for f in result.findings)
    assert result.heldout.after.trans_mm <= result.heldout.before.trans_mm
