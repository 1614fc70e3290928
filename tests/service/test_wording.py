"""Issue 28: counts and wording agree between the terminal, the result JSON and the HTML report
— on the three cases the issue found (parameters that did not add up, "optimal after 0
iterations" unexplained, a ranking score without its meaning, compliance "not identified" in one
place and "not identifiable" in another), through ``kincal calibrate`` and ``kincal rank`` on
the real FR3 recording."""

from __future__ import annotations

import contextlib
import html
import io
import json
import sys
from pathlib import Path

import pytest

from schemas.calibration import CalibrationResult
from service import cli
from service.render.text import compliance_status, parameter_count, solver_line, verdict_line

FR3 = Path(__file__).resolve().parents[2] / "data/real/philnad_fr3_eye_in_hand/fr3_poses.csv"


def _kincal(args: list[object]) -> tuple[int, str, str]:
    """``kincal *args`` in this process: exit code, stdout, stderr."""
    out, err = io.StringIO(), io.StringIO()
    code = 0
    with (
        pytest.MonkeyPatch.context() as monkeypatch,
        contextlib.redirect_stdout(out),
        contextlib.redirect_stderr(err),
    ):
        monkeypatch.setattr(sys, "argv", ["kincal", *map(str, args)])
        try:
            cli.main()
        except SystemExit as exc:
            code = int(exc.code or 0)
    return code, out.getvalue(), err.getvalue()


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    folder = tmp_path_factory.mktemp("wording")
    report = folder / "report.html"
    code, out, err = _kincal(
        [
            "calibrate",
            FR3,
            "--robot",
            "panda",
            "--no-heldout",
            "--out-dir",
            folder,
            "--report",
            report,
        ]
    )
    assert code == 0, err
    configs = folder / "configs.csv"
    configs.write_text("".join(FR3.read_text().splitlines(keepends=True)[:11]))
    rank_code, rank_out, rank_err = _kincal(["rank", folder / "calibration.json", configs])
    assert rank_code == 0, rank_err
    return {
        "out": out,
        "result": CalibrationResult.model_validate_json((folder / "calibration.json").read_text()),
        "report": html.unescape((folder / "report.html").read_text()),
        "rank_out": rank_out,
        "ranking": json.loads((folder / "ranking.json").read_text()),
    }


def test_the_parameter_count_adds_up_everywhere(calibrated: dict[str, object]) -> None:
    result = calibrated["result"]
    assert isinstance(result, CalibrationResult)
    i = result.identifiability
    assert i.rank + len(i.removed) + len(i.pruned) + len(i.fixed) == i.n_parameters
    line = parameter_count(i)
    assert f"parameters: {i.rank} estimated of {i.n_parameters} ({len(i.removed)} not " in line
    assert line in str(calibrated["out"]) and line in str(calibrated["report"])


def test_the_solver_line_says_whose_iterations_it_counts(calibrated: dict[str, object]) -> None:
    result = calibrated["result"]
    assert isinstance(result, CalibrationResult)
    line = solver_line(result.solver)
    assert "final fit took" in line and "from the warm start's solution" in line
    assert line in str(calibrated["out"]) and line in str(calibrated["report"])


def test_compliance_is_described_in_the_same_words(calibrated: dict[str, object]) -> None:
    result = calibrated["result"]
    assert isinstance(result, CalibrationResult)
    pruned = [c for c in result.compliance if c.pruned]
    assert pruned, "the FR3 has compliances fixed at 0 (negative or not identifiable)"
    for compliance in result.compliance:
        words = compliance_status(compliance)
        assert words in str(calibrated["out"]) and words in str(calibrated["report"])
    assert "not identified in any" not in str(calibrated["out"])


def test_the_verdict_is_one_line_in_the_terminal_and_the_report(
    calibrated: dict[str, object],
) -> None:
    result = calibrated["result"]
    assert isinstance(result, CalibrationResult)
    line = verdict_line(result.verdict)
    assert str(calibrated["out"]).rstrip().splitlines()[-1] == line
    assert line in str(calibrated["report"]) and "Verdict: ok" in str(calibrated["report"])


def test_the_ranking_score_is_explained(calibrated: dict[str, object]) -> None:
    ranking = calibrated["ranking"]
    assert isinstance(ranking, dict)
    text = str(calibrated["rank_out"])
    assert "predicted task-relevant variance" in text and "lower is better" in text
    assert ranking["score_unit"] in text  # "m² (1 rad = 1 m)", the JSON's own unit
    best = ranking["ranking"][0]
    assert f"best: index {best['index']}, score {best['score']:.4g}" in text
    assert text.rstrip().splitlines()[-1].startswith("calibration verdict: ")
