"""Runnable examples and benchmarks are smoke-tested on small inputs so they cannot rot."""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd

from benchmarks import evaluate_real
from schemas.calibration import CalibrationResult
from schemas.ranking import RankingOptions, RankingResult
from service import ranking as ranking_pipeline
from service.demo import run_demo


def test_demo_runs_and_calibration_beats_nominal(tmp_path: Path) -> None:
    lines: list[str] = []
    numbers = run_demo(tmp_path, echo=lines.append)
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


def test_real_data_benchmark_prints_the_readme_table(tmp_path: Path) -> None:
    table = evaluate_real.main(seeds=2, figures=tmp_path)
    assert table.count("\n") == 3 and "2 of 2" in table
    assert len(list(tmp_path.glob("*_residuals.png"))) == 2
