"""benchmarks/scale.py runs on tiny settings: table, JSON, plot, fleet (cannot rot)."""

from __future__ import annotations

import json
from pathlib import Path

from benchmarks import default_calibrate, scale


def test_scale_benchmark_prints_its_table_and_finds_the_worn_robot(tmp_path: Path) -> None:
    lines: list[str] = []
    text, runs, fleets = scale.main(
        [600, 1200],
        ["inprocess"],
        out=tmp_path / "out",
        plot_path=tmp_path / "scale.png",
        fleet_robots=8,
        fleet_poses=200,
        chunk_rows=500,
        echo=lines.append,
    )
    assert [(r.backend, r.n) for r in runs] == [("inprocess", 600), ("inprocess", 1200)]
    assert all(r.passes >= 5 and r.stage_s["deterministic"] > 0 for r in runs)
    assert all(abs(r.compliance_rad_per_nm[2] - 8e-4) < 1e-4 for r in runs)
    rows = [line.split() for line in text.splitlines()]
    assert ["inprocess", "1200"] in [row[:2] for row in rows] and "fleet" in text
    assert (tmp_path / "scale.png").stat().st_size > 10_000
    saved = json.loads((tmp_path / "out" / "scale.json").read_text())
    assert len(saved["runs"]) == 2 and len(saved["fleets"]) == 1
    (fleet,) = fleets
    assert fleet.n_robots == 8 and "SN0007:compliance.j2s6s200_joint_3" in fleet.flagged
    assert all(r.other_cpu_s >= 0.0 and r.load_average[0] >= 0.0 for r in runs)
    assert "other CPU s" in text


def test_idle_wait_reports_how_busy_the_machine_is() -> None:
    busy = scale.wait_until_idle(1.0, 0.0, window_s=0.2)
    assert 0.0 <= busy <= 1.25  # whole clock ticks: a short window can round above 1


def test_default_calibrate_benchmark_prints_its_table(tmp_path: Path) -> None:
    """benchmarks/default_calibrate.py on a tiny recording: both rows, stages, verdicts."""
    text = default_calibrate.main((800,), repeats=1, out=tmp_path)
    rows = [line for line in text.splitlines() if line.startswith("| 800 |")]
    assert len(rows) == 2
    assert "| (none) |" in rows[0] and "ran on" not in rows[0] and "inprocess" in rows[1]
    assert "reml optimal" in rows[0] and "heldout" in rows[0]
