"""``benchmarks/cli_latency.py`` runs (one repeat): whole ``kincal`` processes for the help, for
a recording that is not there and for the FR3 recording in millimetres and in degrees, each
with the exit code and the word the issue asks for (the benchmark stops otherwise). Its times
are printed, never asserted."""

from __future__ import annotations

from benchmarks import cli_latency


def test_the_latency_benchmark_runs_every_case_with_its_exit_code_and_message() -> None:
    rows = cli_latency.main(repeats=1)
    assert [row[0] for row in rows] == [
        "kincal --help",
        "kincal calibrate --help",
        "calibrate, file not found",
        "calibrate, positions in mm",
        "calibrate, joints in degrees",
    ]
    assert all(row[1] > 0 and row[4] > 0 for row in rows)
