"""Held-out ball-centre scatter of the platonics ball-in-socket Pandas, before and after
calibration (issue 15), through the same path as ``kincal calibrate <folder> --robot panda``.

Each robot folder of ``data/real/platonics_ball_socket`` holds several tool placements with two
sockets each (hole_0, hole_1; 50 mm apart). The measurement is 'point': one unknown point per
(placement, hole) file. Held-out protocol (DESIGN.md §4): 10 random 90/10 splits of the rows
kept by the outlier rule; each split fits on its training rows (the sockets too) and scores the
distance of each held-out ball centre from its socket point. "before": nominal URDF with the
ball offset and the socket points fitted; "after": the calibration (link rotations, compliance,
ball offset, points); "after, 50 mm": also the link lengths, with the known socket distance.

Usage: ``python benchmarks/platonics.py [--seeds 10] [--robots panda_1,panda_2]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import solver  # noqa: F401  (BLAS defaults)
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
    line = (
        f"| {folder} | {numbers['rows']:.0f} ({numbers['used']:.0f} used) | "
        f"{numbers['sockets']:.0f} | {numbers['before_mm']:.3f} | {numbers['after_mm']:.3f} | "
        f"{numbers['after_distance_mm']:.3f} | {numbers['before_mm'] / numbers['after_mm']:.1f}x | "
        f"{seconds:.1f} |"
    )
    return line, numbers


HEADER = (
    "| robot | rows | sockets | before, mm | after, mm | after with 50 mm, mm | improvement "
    "| time, s |\n|---|---|---|---|---|---|---|---|"
)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--robots", default=None, help="comma-separated robot folders")
    args = parser.parse_args()
    folders = args.robots.split(",") if args.robots else panda_folders()
    print(
        "Held-out ball-centre scatter (mean distance of held-out ball centres from the socket "
        f"point fitted on the training rows), {args.seeds} splits 90/10"
    )
    print(HEADER)
    for folder in folders:
        print(row(folder, args.seeds)[0], flush=True)


if __name__ == "__main__":
    main()
