"""Runnable examples and benchmarks are smoke-tested on small inputs so they cannot rot."""

from __future__ import annotations

import json
import re
import shutil
from pathlib import Path

import pandas as pd
import pytest

from benchmarks import evaluate_real
from schemas.calibration import CalibrationResult
from schemas.ranking import RankingOptions, RankingResult
from service.app import rank as ranking_pipeline
from service.cli.demo import run_demo
from tests.conftest import (
    assert_documents_close,
    assert_quoted_output,
    comparable_result,
    computed_once,
)
from tests.service.cli_support import run_ok


def _run_demo(folder: Path) -> tuple[Path, dict[str, float], list[str]]:
    lines: list[str] = []
    numbers = run_demo(folder, echo=lines.append)
    return folder, numbers, lines


@pytest.fixture(scope="module")
def demo(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, float], list[str]]:
    """The demo, run once for both xdist workers (its tests may land on both)."""
    return computed_once(tmp_path_factory, "demo", _run_demo)


def test_demo_runs_and_calibration_beats_nominal(
    demo: tuple[Path, dict[str, float], list[str]],
) -> None:
    tmp_path, numbers, lines = demo
    assert numbers["heldout_after_mm"] < 0.5 * numbers["heldout_before_mm"]
    assert {p.name for p in tmp_path.iterdir()} == {
        "jaco2_recording.csv",
        "truth.json",
        "result.json",
        "jaco2_calibrated.urdf",
        "residuals.png",
        "report.html",
        "ranking.json",
        "candidates.csv",
        "service",
    }
    text = "\n".join(lines)
    assert "Cal. Ours Trans." in text and "15 of 15 injected outliers removed" in text

    # it went through the service: upload, a job with progress, a report, a ranking over HTTP
    assert "uploaded 154 samples over HTTP" in text
    progress = [line for line in lines if line.startswith("  [")]
    assert any("running: heldout" in line for line in progress)
    assert "succeeded: done" in progress[-1]
    assert (tmp_path / "service" / "kincal.db").is_file()
    assert f"report: {(tmp_path / 'report.html').resolve()}" in text
    assert "data:image/png;base64," in (tmp_path / "report.html").read_text()

    result = CalibrationResult.model_validate_json((tmp_path / "result.json").read_text())
    ranking = RankingResult.model_validate_json((tmp_path / "ranking.json").read_text())
    assert "ranked 20 candidate configurations over HTTP" in text
    assert numbers["best_score_m2"] < numbers["worst_score_m2"]
    candidates = pd.read_csv(tmp_path / "candidates.csv")
    assert list(candidates.columns) == ranking.joint_names and len(candidates) == 20
    direct = ranking_pipeline.rank_configurations(result, candidates.to_numpy(), RankingOptions())
    assert ranking == direct  # the HTTP ranking is the pipeline's (and so `kincal rank`'s)
    best = ranking.ranking[0]
    assert any(re.match(rf"^ +1 +{best.index} +{best.score * 1e6:.4f} ", line) for line in lines)


def test_the_demo_output_docs_demo_md_quotes_is_what_the_demo_prints(
    demo: tuple[Path, dict[str, float], list[str]],
) -> None:
    """Every line of docs/demo.md's example output is a line the demo prints
    (:func:`tests.conftest.assert_quoted_output`)."""
    _, _, lines = demo
    page = (Path(__file__).parents[1] / "docs" / "demo.md").read_text(encoding="utf-8")
    (block,) = re.findall(r"```\n(.*?)```", page, re.S)
    assert_quoted_output(block, "\n".join(lines))


def test_cli_http_fleet_and_demo_calibrate_alike(
    demo: tuple[Path, dict[str, float], list[str]],
    tmp_path: Path,
) -> None:
    """Issue 17: the demo's calibration (an HTTP job of the embedded service), ``kincal
    calibrate`` and ``kincal fleet`` of the same recording with the same options go through
    the one entry point and agree to 1e-9."""
    folder, _, _ = demo
    data = folder / "jaco2_recording.csv"
    demo_result = CalibrationResult.model_validate_json((folder / "result.json").read_text())
    flex = demo_result.options.virtual_axes_at
    assert flex  # the demo models the base plate's flex
    cli_out = tmp_path / "cli.json"
    run_ok(
        ["calibrate", data, "--robot", "kinova", "--virtual-axes", ",".join(flex), "-o", cli_out]
    )
    fleet_dir = tmp_path / "fleet"
    fleet_dir.mkdir()
    shutil.copy(data, fleet_dir / "SN0001.csv")
    config = tmp_path / "demo.toml"
    config.write_text(f"virtual_axes_at = {json.dumps(flex)}\n")
    fleet = ["fleet", fleet_dir, "--robot", "kinova", "--config", config, "--heldout"]
    run_ok([*fleet, "--results-dir", tmp_path / "robots", "-o", tmp_path / "fleet.json"])
    want = comparable_result(demo_result)
    for path in (cli_out, tmp_path / "robots" / "SN0001.json"):
        got = CalibrationResult.model_validate_json(path.read_text())
        assert_documents_close(comparable_result(got), want)


def test_real_data_benchmark_prints_the_readme_table(tmp_path: Path) -> None:
    """benchmarks/evaluate_real.py end to end on two recordings, a pose file with its residual
    figure and the DH-table positioner (every shipped recording is calibrated by
    tests/test_shipped_recordings_solve.py; the UR10e row is checked against the README's
    results file by tests/test_quoted_numbers.py)."""
    names = [
        "UR10e (FIGAROH UR10 experiment)",
        "2-axis positioner, DH table (industrial_calibration)",
    ]
    rows = evaluate_real.main(seeds=2, figures=tmp_path, names=names)
    table = evaluate_real.render(rows)
    assert table.count("\n") == 1 + len(names) and "2 of 2" in table
    assert "| 0 | ok |" in table or "| 0 | warning |" in table
    figures = [name for name in names if evaluate_real.RECORDINGS[name].figure]
    assert len(figures) == 1 and len(list(tmp_path.glob("*_residuals.png"))) == 1
