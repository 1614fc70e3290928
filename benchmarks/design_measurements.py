"""Designs for the measurement types other than pose and position (issue 16, deliverable 4).

For each case it runs the user's path (:func:`service.app.design.run_design`, the defaults of
``kincal design --measurement TYPE``: D, method auto) and prints one row: candidates, the
columns of the information (chain parameters p + the measurement's own unknowns e, profiled
out), the method auto chose and its time, the design's criterion, the relaxation's certified
bound and the efficiency, and the median criterion of random K-subsets of the same candidates.
With ``--clarabel N`` the same relaxation on the first N candidates is also solved by the
first-order method and by Clarabel (the Schur-complement LMI when e > 0): both times and values,
the numbers behind ``auto``'s rule (docs/design.md, Measurement types).

Cases: a simulated Jaco2 (kinova) with sampled candidates for a plane contact
(``components:tz,rx,ry``), three markers, a base marker (``relative-base``) and a sensor after
joint 2 (``eye-on-head``); the real platonics Panda ball-in-socket folders ``panda_right``
(2 sockets) and ``panda_1`` (3 placements × 2 sockets, known 50 mm distances). Usage::

    python -m benchmarks.design_measurements [--candidates 200] [--poses 20] [--clarabel 40]
        [--write-results]

With ``--write-results`` also ``docs/results/design_measurements.{json,md}``, the table
docs/design.md includes.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.results import Row, markdown_table, write_results
from schemas.calibration import CalibrationOptions
from schemas.design import DesignOptions
from schemas.robots import load_robot
from service.app import design
from solver.design.criteria import DesignProblem
from solver.design.relaxation import solve_clarabel, solve_first_order

SOCKETS = Path(__file__).resolve().parents[1] / "data/real/platonics_ball_socket"
OFFSETS_M = [[0.05, 0.0, 0.02], [-0.03, 0.04, 0.03], [0.0, -0.05, 0.06]]
RANDOM_SUBSETS = 200


@dataclass(frozen=True)
class Case:
    name: str
    robot: str
    options: dict[str, object]
    folder: str | None = None
    calibration: dict[str, object] = field(default_factory=dict)


CASES = (
    Case("plane contact", "kinova", {"measurement": "components:tz,rx,ry"}),
    Case("3 markers", "kinova", {"measurement": "markers", "marker_offsets_m": OFFSETS_M}),
    Case("relative-base", "kinova", {"measurement": "relative-base"}),
    Case("eye-on-head", "kinova", {"measurement": "eye-on-head:j2s6s200_joint_2"}),
    Case("point panda_right", "panda", {"measurement": "point"}, "panda_right"),
    Case(
        "point panda_1 + 50 mm",
        "panda",
        {"measurement": "point"},
        "panda_1",
        {"point_distance_m": 0.05},
    ),
)


def run_case(case: Case, n_candidates: int, n_poses: int, clarabel: int) -> Row:
    """One table row (see the module docstring)."""
    robot = load_robot(case.robot)
    options = DesignOptions.model_validate(
        {
            **case.options,
            "n_poses": n_poses,
            "n_candidates": n_candidates,
            "calibration": CalibrationOptions.model_validate(case.calibration),
        }
    )
    model = design.design_model(robot, options)
    given, sockets = None, None
    if case.folder is not None:
        given, sockets = design.read_candidates(SOCKETS / case.folder, model)
    started = time.perf_counter()
    out = design.run_design(robot, options, candidates=given, model=model, sockets=sockets)
    total_s = time.perf_counter() - started
    q, _, sockets = design.candidate_set(model, options, given, sockets)
    _, block = design.measurement_block(model, options, q, design.design_loads(model, q), sockets)
    problem = DesignProblem((block,), "D", n_poses)
    rng = np.random.default_rng(0)
    randoms = [
        problem.set_value(rng.choice(q.shape[0], n_poses, replace=False))
        for _ in range(RANDOM_SUBSETS)
    ]
    c = out.criterion
    row: Row = {
        "case": case.name,
        "robot": case.robot,
        "candidates": int(q.shape[0]),
        "parameters": int(block.dimension),
        "nuisance": int(block.nuisance),
        "poses": n_poses,
        "method": c.method,
        "status": c.status,
        "relaxation_s": c.elapsed_s,
        "total_s": total_s,
        "value": c.value,
        "upper_bound": c.upper_bound,
        "efficiency": c.efficiency,
        "random_median": float(np.median(randoms)),
        "small": None,
    }
    if clarabel:
        small = DesignProblem((block.subset(np.arange(min(clarabel, q.shape[0]))),), "D", n_poses)
        first = solve_first_order(small)
        conic = solve_clarabel(small)
        row["small"] = {
            "candidates": small.n_candidates,
            "first_order_s": first.elapsed_s,
            "first_order_value": first.value,
            "first_order_status": first.status,
            "clarabel_s": conic.elapsed_s,
            "clarabel_value": conic.value,
            "clarabel_status": conic.status,
        }
    return row


def line(row: Row) -> str:
    """``row`` as one line of the terminal table."""
    text = (
        f"{row['case']:24s} {row['candidates']:5d} {row['parameters']:3d}+{row['nuisance']:<3d} "
        f"{row['method']:11s} {row['status']:14s} {row['relaxation_s']:7.2f} "
        f"{row['total_s']:7.2f} {row['value']:9.4f} {row['upper_bound']:9.4f} "
        f"{row['efficiency']:6.3f} {row['random_median']:9.4f}"
    )
    small = row["small"]
    if small is not None:
        text += (
            f" | N={small['candidates']}: first-order {small['first_order_s']:.2f} s "
            f"{small['first_order_value']:.6f}, Clarabel {small['clarabel_s']:.2f} s "
            f"{small['clarabel_value']:.6f} ({small['clarabel_status']})"
        )
    return text


HEADER = (
    f"{'case':24s} {'cands':>5s} {'p+e':7s} {'method':11s} {'status':14s} {'relax s':>7s} "
    f"{'total s':>7s} {'D':>9s} {'bound':>9s} {'effic':>6s} {'random D':>9s}"
)

TITLES = {
    "plane contact": "plane contact `components:tz,rx,ry` (Jaco2)",
    "3 markers": "3 markers (Jaco2)",
    "relative-base": "relative-base (Jaco2)",
    "eye-on-head": "eye-on-head after joint 2 (Jaco2)",
    "point panda_right": "point, platonics `panda_right`",
    "point panda_1 + 50 mm": "point, platonics `panda_1` + 50 mm",
}
"""The cases' names in the results table."""

METHOD_TITLES = {"clarabel": "Clarabel", "first_order": "first-order"}


def render(rows: list[Row]) -> str:
    """The table of ``docs/results/design_measurements.md``: per case the candidates, the
    information's columns (chain parameters p + the measurement's own unknowns e), the method
    ``auto`` chose (with its status when not optimal), the relaxation's and the whole design's
    wall time (to 0.1 s), the design's D criterion, the certified bound and the efficiency (to
    0.001), the median D of random subsets of as many poses; then the same relaxation on the
    first candidates solved by both methods (wall time to 0.01 s, and whether Clarabel's answer
    is inaccurate)."""
    cells = []
    for r in rows:
        small = r["small"]
        both = "–"
        if small is not None:
            clarabel = f"{small['clarabel_s']:.2f} s"
            if small["clarabel_status"] != "optimal":
                clarabel += f" ({small['clarabel_status'].replace('optimal_', '')})"
            both = f"{small['first_order_s']:.2f} s / {clarabel}"
        cells.append(
            (
                TITLES.get(r["case"], r["case"]),
                r["candidates"],
                f"{r['parameters']}+{r['nuisance']}",
                METHOD_TITLES.get(r["method"], str(r["method"]))
                + ("" if r["status"] == "optimal" else f" ({r['status'].replace('_', ' ')})"),
                f"{r['relaxation_s']:.1f} s",
                f"{r['total_s']:.1f} s",
                f"{r['value']:.3f}",
                f"{r['upper_bound']:.3f}",
                f"{r['efficiency']:.3f}",
                f"{r['random_median']:.3f}",
                both,
            )
        )
    small = next((r["small"] for r in rows if r["small"] is not None), None)
    last = "first-order / Clarabel" + (
        "" if small is None else f", {small['candidates']} candidates"
    )
    poses = rows[0]["poses"] if rows else 0
    header = (
        "case", "candidates", "p+e", "auto", "relaxation", "total", "D", "bound",
        "efficiency", f"median D of random {poses}", last,
    )  # fmt: skip
    return markdown_table(header, cells)


def main(argv: list[str] | None = None) -> list[Row]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--candidates", type=int, default=200, help="sampled candidates")
    parser.add_argument("--poses", type=int, default=20)
    parser.add_argument(
        "--clarabel", type=int, default=0, help="also time Clarabel on this many candidates"
    )
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="write docs/results/design_measurements.{json,md} (docs/design.md)",
    )
    args = parser.parse_args(argv)
    print(HEADER, flush=True)
    rows = []
    for case in CASES:
        rows.append(run_case(case, args.candidates, args.poses, args.clarabel))
        print(line(rows[-1]), flush=True)
    if args.write_results:
        command = (
            f"python -m benchmarks.design_measurements --candidates {args.candidates} "
            f"--poses {args.poses} --clarabel {args.clarabel} --write-results"
        )
        for path in write_results("design_measurements", command, rows, render):
            print(f"wrote {path}")
    return rows


if __name__ == "__main__":
    main()
