"""benchmarks/discover_speed.py on a tiny input: it runs ``kincal discover`` in this process and
in two local worker processes, finds the same findings and prints its table, so it cannot
rot."""

from __future__ import annotations

from benchmarks import discover_speed


def test_discover_speed_benchmark_runs_both_settings_and_finds_the_same(capsys) -> None:  # type: ignore[no-untyped-def]
    (row,) = discover_speed.main(["--repeats", "1", "--n", "40", "--no-fr3"])
    assert row["n_samples"] == 40 and row["workers"] == 2
    assert row["same_findings"] is True
    assert row["median_inprocess_s"] > 0 and row["median_processes_s"] > 0
    assert row["without_sizes_s"] > 0
    printed = capsys.readouterr().out
    assert "| simulated Jaco2, 40 poses | 40 |" in printed and "| yes |" in printed
