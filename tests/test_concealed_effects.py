"""benchmarks/discovery_study.py runs on tiny settings and prints its table (cannot rot)."""

from __future__ import annotations

from benchmarks import discovery_study


def test_discovery_study_prints_a_row_per_scenario() -> None:
    lines: list[str] = []
    text, rows = discovery_study.main(
        seeds=1, n=120, workers=1, names=["null", "backlash"], bootstrap=5, echo=lines.append
    )
    assert text.count("\n") == 3 and text.startswith("| Scenario |")
    assert rows["null"]["detected"] == 1.0 and rows["null"]["false_runs"] == 0.0
    assert rows["backlash"]["detected"] == 1.0 and rows["backlash"]["heldout_ratio"] < 1.1
    assert "2 discoveries" in lines[-1]
