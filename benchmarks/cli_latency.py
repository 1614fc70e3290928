"""How long a newcomer waits (issue 28), whole process, wall time: ``kincal --help``,
``kincal calibrate --help`` and the refusal of a recording that is not there (target ≤ 0.5 s,
issue 29), and the refusal of the FR3 recording converted to millimetres and to degrees
(target < 2 s, exit code 2, the unit named in the message).

Median and range of ``--repeats`` runs each, and the median CPU time (user + system of the
process and its children): on a machine loaded by other work the wall time grows with the
load average (printed), the CPU time much less — on a quiet machine wall ≈ CPU. Tests assert on
behaviour, never on these times.

Usage: ``python -m benchmarks.cli_latency [--repeats 7]``.
"""

from __future__ import annotations

import argparse
import math
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

RECORDING = Path(__file__).resolve().parents[1] / "data/real/philnad_fr3_eye_in_hand/fr3_poses.csv"
JOINTS = [f"q{i}" for i in range(1, 8)]
KINCAL = str(Path(sys.executable).with_name("kincal"))


@dataclass(frozen=True)
class Case:
    name: str
    args: list[str]
    exit_code: int
    says: str
    target_s: float


def cases(folder: Path) -> list[Case]:
    table = pd.read_csv(RECORDING)
    millimetres = table.copy()
    millimetres[["x", "y", "z"]] *= 1000.0
    degrees = table.copy()
    degrees[JOINTS] *= 180.0 / math.pi
    millimetres.to_csv(folder / "fr3_mm.csv", index=False)
    degrees.to_csv(folder / "fr3_deg.csv", index=False)
    refuse = ["--robot", "panda", "--out-dir", str(folder / "out")]
    return [
        Case("kincal --help", ["--help"], 0, "calibrate", 0.5),
        Case("kincal calibrate --help", ["calibrate", "--help"], 0, "Outliers", 0.5),
        Case(
            "calibrate, file not found",
            ["calibrate", str(folder / "fr3_missing.csv"), *refuse],
            2,
            "file not found",
            0.5,
        ),
        Case(
            "calibrate, positions in mm",
            ["calibrate", str(folder / "fr3_mm.csv"), *refuse],
            2,
            "millimetres",
            2.0,
        ),
        Case(
            "calibrate, joints in degrees",
            ["calibrate", str(folder / "fr3_deg.csv"), *refuse],
            2,
            "degrees",
            2.0,
        ),
    ]


def _cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def measure(case: Case, repeats: int) -> tuple[list[float], list[float]]:
    """Wall and CPU seconds of each run."""
    times, cpu = [], []
    for _ in range(repeats):
        started, cpu_started = time.perf_counter(), _cpu_s()
        done = subprocess.run([KINCAL, *case.args], capture_output=True, text=True)
        times.append(time.perf_counter() - started)
        cpu.append(_cpu_s() - cpu_started)
        if done.returncode != case.exit_code or case.says not in done.stdout + done.stderr:
            raise SystemExit(
                f"{case.name}: exit {done.returncode}, expected {case.exit_code} and "
                f"{case.says!r}\n{done.stdout}\n{done.stderr}"
            )
    return times, cpu


def main(repeats: int = 7) -> list[tuple[str, float, float, float, float, float]]:
    rows = []
    with tempfile.TemporaryDirectory() as folder:
        measure(cases(Path(folder))[0], 1)  # warm the file cache once
        for case in cases(Path(folder)):
            times, cpu = measure(case, repeats)
            median, cpu_s = statistics.median(times), statistics.median(cpu)
            rows.append((case.name, median, min(times), max(times), cpu_s, case.target_s))
    load = os.getloadavg()[0]
    print(
        f"whole process, wall time, {repeats} runs each; load average {load:.1f} on "
        f"{os.cpu_count()} CPUs"
    )
    print(f"{'command':<32} {'median s':>9} {'min s':>7} {'max s':>7} {'CPU s':>7} {'target s':>9}")
    for name, median, low, high, cpu_s, target in rows:
        print(f"{name:<32} {median:>9.2f} {low:>7.2f} {high:>7.2f} {cpu_s:>7.2f} {target:>9.1f}")
    return rows


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=7)
    main(parser.parse_args().repeats)
