"""Where ``kincal discover``'s seconds go, and what local worker processes buy (issue 29):
whole-process wall time with its defaults, in this process against ``--executor processes``,
on the same recording side by side, and whether the findings are the same.

The stated detectable sizes (every library term left out, calibrated on sign-flip replicates
of the recording) are most of a run's time; ``--executor processes --workers N`` sizes the
terms in N local processes. Rows: the real FR3 recording (114 poses) and a simulated Jaco2
recording of ``--n`` poses (``kincal simulate``, seed 1000; issue 29's N = 500), each run
``--repeats`` times per setting, alternating, plus once without sizes (``--no-detectability``)
for the part the sizes cost. The findings documents of the settings must be equal but for
their time stamps. With ``--write-results`` also ``docs/results/discover_speed.{json,md}``.
Usage: ``python -m benchmarks.discover_speed [--repeats 3] [--workers 2] [--n 500]
[--write-results]``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

from benchmarks.results import Row, dash, markdown_table, write_results

DATA = Path(__file__).resolve().parents[1] / "data" / "real"
KINCAL = str(Path(sys.executable).with_name("kincal"))
FR3 = [str(DATA / "philnad_fr3_eye_in_hand" / "fr3_poses.csv"), "--robot", "panda"]


def simulated(folder: Path, n: int) -> list[str]:
    """A simulated Jaco2 recording of ``n`` poses (``kincal simulate``) and its robot flag."""
    path = folder / f"jaco2_{n}.csv"
    subprocess.run(
        [KINCAL, "simulate", "--robot", "kinova", "--n", str(n), "--seed", "1000", "-o", path],
        check=True,
        capture_output=True,
    )
    return [str(path), "--robot", "kinova"]


def discover(recording: list[str], extra: list[str], output: Path) -> tuple[float, dict[str, Any]]:
    """One whole ``kincal discover`` process: wall seconds and its findings document (without
    the time stamps)."""
    command = [KINCAL, "discover", *recording, "--no-plots", "-o", str(output), *extra]
    started = time.perf_counter()
    run = subprocess.run(command, capture_output=True, text=True)
    seconds = time.perf_counter() - started
    if run.returncode != 0:
        raise RuntimeError(f"{' '.join(command)}: exit {run.returncode}: {run.stderr[-500:]}")
    document = json.loads(output.read_text())
    for varying in ("created_utc", "elapsed_s"):
        document.pop(varying)
    return seconds, document


def measure(
    name: str,
    recording: list[str],
    repeats: int,
    workers: int,
    folder: Path,
    *,
    without_sizes: bool = True,
) -> Row:
    """The row of one recording: median wall time per setting (alternating runs), and with
    ``without_sizes`` one run with ``--no-detectability``."""
    settings = {
        "inprocess": [],
        "processes": ["--executor", "processes", "--workers", str(workers)],
    }
    times: dict[str, list[float]] = {key: [] for key in settings}
    documents: dict[str, dict[str, Any]] = {}
    for _ in range(repeats):
        for key, extra in settings.items():
            seconds, documents[key] = discover(recording, extra, folder / f"{key}.json")
            times[key].append(seconds)
    without = None
    if without_sizes:
        without, _ = discover(recording, ["--no-detectability"], folder / "none.json")
    n_samples = documents["inprocess"]["dataset"]["n_samples"]
    here, there = (statistics.median(times[key]) for key in settings)
    return {
        "recording": name,
        "n_samples": n_samples,
        "workers": workers,
        "inprocess_s": times["inprocess"],
        "processes_s": times["processes"],
        "median_inprocess_s": round(here, 2),
        "median_processes_s": round(there, 2),
        "speed_up": round(here / there, 2),
        "without_sizes_s": None if without is None else round(without, 2),
        "same_findings": documents["inprocess"] == documents["processes"],
        "load_average": round(os.getloadavg()[0], 2),
        "cpus": os.cpu_count(),
    }


def render(rows: list[Row]) -> str:
    header = [
        "Recording",
        "Poses",
        "Defaults (in this process) s, median",
        "`--executor processes` s, median",
        "Speed-up",
        "Without sizes s",
        "Same findings",
    ]
    body = [
        [
            r["recording"],
            r["n_samples"],
            f"{r['median_inprocess_s']:.2f}",
            f"{r['median_processes_s']:.2f} ({r['workers']} workers)",
            f"{r['speed_up']:.2f}×",
            dash(r["without_sizes_s"], 2),
            "yes" if r["same_findings"] else "**no**",
        ]
        for r in rows
    ]
    runs = sorted({len(r["inprocess_s"]) for r in rows})
    loads = ", ".join(f"{r['load_average']:.1f}" for r in rows)
    return (
        f"{markdown_table(header, body)}\n\nWhole `kincal discover` processes, "
        f"{' or '.join(map(str, runs))} run(s) per setting, alternating; {rows[0]['cpus']} CPUs, "
        f"load average after each row: {loads}."
    )


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--n", type=int, default=500, help="poses of the simulated recording")
    parser.add_argument("--fr3", action=argparse.BooleanOptionalAction, default=True)
    parser.add_argument("--write-results", action="store_true")
    arguments = parser.parse_args(argv)
    rows = []
    with tempfile.TemporaryDirectory() as name:
        folder = Path(name)
        recordings = [(f"simulated Jaco2, {arguments.n} poses", simulated(folder, arguments.n))]
        if arguments.fr3:
            recordings.insert(0, ("FR3 eye-in-hand (real)", FR3))
        for label, recording in recordings:
            rows.append(measure(label, recording, arguments.repeats, arguments.workers, folder))
            print(render(rows[-1:]), flush=True)
    if arguments.write_results:
        command = (
            f"python -m benchmarks.discover_speed --repeats {arguments.repeats} "
            f"--workers {arguments.workers} --n {arguments.n} --write-results"
        )
        for path in write_results("discover_speed", command, rows, render):
            print(f"wrote {path}")
    return rows


if __name__ == "__main__":
    main()
