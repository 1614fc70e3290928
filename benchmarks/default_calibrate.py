"""``kincal calibrate`` with no flags on large recordings: wall time as a user sees it (issue 17).

Simulates Kinova Jaco2 recordings of N poses (the scale benchmark's robot: compliant joints,
random perturbations in every joint frame, sensor noise, 1 % gross outliers) as Parquet, then
runs ``kincal calibrate FILE --robot kinova -o result.json`` in a fresh process — the defaults:
REML covariances, the held-out evaluation, wherever the entry point chooses to run the passes —
and, as the baseline measured in the same run, the same command with ``--executor inprocess``
(one process). Wall time includes interpreter start and imports. Prints a markdown table with
the median of ``--repeats`` runs and the stages of the last one.

Usage (from the repository root): ``python -m benchmarks.default_calibrate [--sizes 1e5,1e6]
[--repeats 3]``.
"""

from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from benchmarks.scale import ROBOT, write_recording
from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.robots import load_robot
from service.render.result_json import chain_for

SIZES = (100_000, 1_000_000)
TARGET_S = {100_000: 10.0, 1_000_000: 15.0}
"""Issue 17's targets for ``kincal calibrate`` with no flags, wall seconds on 2 cores."""


@dataclass(frozen=True)
class Timing:
    n: int
    flags: str
    wall_s: list[float]
    execution: str
    stages: str
    heldout_mm: float | None
    estimator_status: str

    @property
    def median_s(self) -> float:
        return statistics.median(self.wall_s)


def kincal() -> str:
    return str(Path(sys.executable).with_name("kincal"))


def time_calibrate(path: Path, flags: list[str], repeats: int) -> tuple[list[float], str]:
    """Wall seconds of each run and the last run's output."""
    walls, text = [], ""
    out = path.with_suffix(".result.json")
    for _ in range(repeats):
        started = time.perf_counter()
        done = subprocess.run(
            [kincal(), "calibrate", str(path), "--robot", ROBOT, *flags, "-o", str(out)],
            capture_output=True,
            text=True,
            check=True,
        )
        walls.append(time.perf_counter() - started)
        text = done.stdout
    return walls, text


def measure(path: Path, n: int, flags: list[str], repeats: int) -> Timing:
    walls, text = time_calibrate(path, flags, repeats)
    match = re.search(r"^ran on (.+?) in [\d.]+ s, (.+)$", text, re.M)
    result = CalibrationResult.model_validate_json(path.with_suffix(".result.json").read_text())
    heldout = result.fit.after.heldout
    covariance = result.covariance
    return Timing(
        n,
        " ".join(flags) or "(none)",
        walls,
        match.group(1) if match else "?",
        match.group(2) if match else "?",
        None if heldout is None else heldout.translation_mean_mm,
        "-" if covariance is None else f"{covariance.estimator} {covariance.solver.status}",
    )


def table(timings: list[Timing]) -> str:
    header = "| N | flags | wall s (median) | runs | target | ran on | covariances | stages |"
    lines = [header, "|---|---|---|---|---|---|---|---|"]
    for t in timings:
        target = TARGET_S.get(t.n)
        verdict = (
            ""
            if target is None or t.flags != "(none)"
            else (f"≤ {target:.0f} s: {'met' if t.median_s <= target else 'not met'}")
        )
        runs = ", ".join(f"{w:.1f}" for w in t.wall_s)
        lines.append(
            f"| {t.n:,} | {t.flags} | {t.median_s:.1f} | {runs} | {verdict} | {t.execution} | "
            f"{t.estimator_status} | {t.stages} |"
        )
    return "\n".join(lines)


def main(sizes: tuple[int, ...] = SIZES, repeats: int = 3, out: Path = Path("out/default")) -> str:
    out.mkdir(parents=True, exist_ok=True)
    chain = chain_for(load_robot(ROBOT), CalibrationOptions())
    timings = []
    for n in sizes:
        path = out / f"kinova_{n}.parquet"
        if not path.exists():
            write_recording(path, chain, n, chunk_rows=65_536)
        for flags in ([], ["--executor", "inprocess"]):
            timings.append(measure(path, n, flags, repeats))
            print(f"N={n}: {' '.join(flags) or 'defaults'}: {timings[-1].median_s:.1f} s")
    cores = len(os.sched_getaffinity(0))
    return f"{cores} cores, load average {os.getloadavg()[0]:.2f} at the end\n\n" + table(timings)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", default=",".join(str(s) for s in SIZES))
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--out", type=Path, default=Path("out/default"))
    args = parser.parse_args()
    sizes = tuple(int(float(s)) for s in args.sizes.split(","))
    print(main(sizes, args.repeats, args.out))
