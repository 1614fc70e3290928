"""Runnable examples and benchmarks are smoke-tested on small inputs so they cannot rot."""

from __future__ import annotations

from pathlib import Path

from benchmarks import evaluate_real
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
    }
    text = "\n".join(lines)
    assert "Cal. Ours Trans." in text and "15 of 15 injected outliers removed" in text


def test_real_data_benchmark_prints_the_readme_table(tmp_path: Path) -> None:
    table = evaluate_real.main(seeds=2, figures=tmp_path)
    assert table.count("\n") == 3 and "2 of 2" in table
    assert len(list(tmp_path.glob("*_residuals.png"))) == 2
