"""benchmarks/discover_speed.py on the smallest shipped recording: it runs ``kincal discover`` in
this process and in two local worker processes, finds the same findings and renders its table,
so it cannot rot."""

from __future__ import annotations

from pathlib import Path

from benchmarks import discover_speed

UR10E = discover_speed.DATA / "figaroh_ur10_experiment"
FLAGS = ["--urdf", str(UR10E / "ur10e_robot.urdf"), "--base", "base_link", "--tip", "wrist_3_link"]


def test_discover_speed_benchmark_runs_both_settings_and_finds_the_same(tmp_path: Path) -> None:
    recording = [str(UR10E / "calibration.csv"), *FLAGS]
    row = discover_speed.measure("UR10e", recording, 1, 2, tmp_path, without_sizes=False)
    assert row["n_samples"] == 23 and row["workers"] == 2
    assert row["same_findings"] is True
    assert row["median_inprocess_s"] > 0 and row["median_processes_s"] > 0
    table = discover_speed.render([row])
    assert "| UR10e | 23 |" in table and "(2 workers)" in table and "| – | yes |" in table
