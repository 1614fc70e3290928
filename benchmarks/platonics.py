"""Held-out ball-centre scatter of the platonics ball-in-socket Pandas, before and after
calibration (issue 15), through the same path as ``kincal calibrate <folder> --robot panda``.

Each robot folder of ``data/real/platonics_ball_socket`` holds several tool placements with two
sockets each (hole_0, hole_1; 50 mm apart). The measurement is 'point': one unknown point per
(placement, hole) file. Held-out protocol (DESIGN.md §4): 10 random 90/10 splits of the rows
kept by the outlier rule; each split fits on its training rows (the sockets too) and scores the
distance of each held-out ball centre from its socket point. "before": nominal URDF with the
ball offset and the socket points fitted; "after": the calibration (link rotations, compliance,
ball offset, points); "after, 50 mm": also the link lengths, with the known socket distance.

Usage: ``python -m benchmarks.platonics [--seeds 10] [--robots panda_1,panda_2]
[--write-results]``; with ``--write-results`` also ``docs/results/platonics.{json,md}`` (the
table docs/ball-in-socket.md includes; tests/test_quoted_numbers.py checks it).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import solver  # noqa: F401  (BLAS defaults)
from benchmarks.results import Row, markdown_table, write_results
from schemas.calibration import CalibrationOptions, CalibrationResult
from schemas.robots import load_robot
from service.app import calibrate as pipeline

DATA = Path(__file__).resolve().parents[1] / "data" / "real" / "platonics_ball_socket"
SOCKET_DISTANCE_M = 0.05


def panda_folders() -> list[str]:
    """The Panda robot folders (the built-in Panda URDF; KUKA and Kinova Gen3 lite are not
    built in)."""
    return sorted(p.name for p in DATA.iterdir() if p.is_dir() and p.name.startswith("panda"))


def calibrate(folder: str, seeds: int, distance_m: float | None) -> tuple[CalibrationResult, float]:
    options = CalibrationOptions(
        seeds=list(range(1, seeds + 1)), measurement="point", point_distance_m=distance_m
    )
    setup = pipeline.check_calibration(load_robot("panda"), options)
    started = time.perf_counter()
    run = pipeline.calibrate_source(DATA / folder, setup)
    return run.result, time.perf_counter() - started


def row(folder: str, seeds: int) -> tuple[str, dict[str, float]]:
    plain, seconds = calibrate(folder, seeds, None)
    scaled, _ = calibrate(folder, seeds, SOCKET_DISTANCE_M)
    before, after = plain.fit.before.heldout, plain.fit.after.heldout
    after_scaled = scaled.fit.after.heldout
    assert before is not None and after is not None and after_scaled is not None
    assert plain.measurement is not None
    numbers = {
        "rows": plain.outliers.n_input,
        "used": plain.outliers.n_used,
        "sockets": len(plain.measurement.labels),
        "before_mm": before.translation_mean_mm,
        "after_mm": after.translation_mean_mm,
        "after_distance_mm": after_scaled.translation_mean_mm,
        "seconds": seconds,
    }
    line = render([{"robot": folder, **numbers}]).splitlines()[-1] + f" {seconds:.1f} s"
    return line, numbers


HEADER = ("robot", "rows", "sockets", "before, mm", "after, mm", "after with 50 mm, mm")


def render(rows: list[Row]) -> str:
    """The table of the rows (held-out mean distances, mm to 3 decimals; the improvement is
    before / after without the distance)."""
    return markdown_table(
        (*HEADER, "improvement"),
        [
            (
                r["robot"],
                f"{r['rows']:.0f} ({r['used']:.0f} used)",
                f"{r['sockets']:.0f}",
                f"{r['before_mm']:.3f}",
                f"{r['after_mm']:.3f}",
                f"{r['after_distance_mm']:.3f}",
                f"{r['before_mm'] / r['after_mm']:.1f}x",
            )
            for r in rows
        ],
    )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--robots", default=None, help="comma-separated robot folders")
    parser.add_argument("--write-results", action="store_true", help="docs/results/platonics.*")
    args = parser.parse_args()
    folders = args.robots.split(",") if args.robots else panda_folders()
    print(
        "Held-out ball-centre scatter (mean distance of held-out ball centres from the socket "
        f"point fitted on the training rows), {args.seeds} splits 90/10; wall time per robot"
    )
    rows: list[Row] = []
    for folder in folders:
        line, numbers = row(folder, args.seeds)
        print(line, flush=True)
        rows.append({"robot": folder, **{k: v for k, v in numbers.items() if k != "seconds"}})
    if args.write_results:
        command = f"python -m benchmarks.platonics --seeds {args.seeds} --write-results"
        for path in write_results("platonics", command, rows, render):
            print("wrote", path)


if __name__ == "__main__":
    main()
