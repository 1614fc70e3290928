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

    python benchmarks/design_measurements.py [--candidates 200] [--poses 20] [--clarabel 40]
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

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


def run_case(case: Case, n_candidates: int, n_poses: int, clarabel: int) -> str:
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
    row = (
        f"{case.name:24s} {q.shape[0]:5d} {block.dimension:3d}+{block.nuisance:<3d} "
        f"{c.method:11s} {c.status:14s} {c.elapsed_s:7.2f} {total_s:7.2f} "
        f"{c.value:9.4f} {c.upper_bound:9.4f} {c.efficiency:6.3f} {float(np.median(randoms)):9.4f}"
    )
    if clarabel:
        small = DesignProblem((block.subset(np.arange(min(clarabel, q.shape[0]))),), "D", n_poses)
        first = solve_first_order(small)
        conic = solve_clarabel(small)
        row += (
            f" | N={small.n_candidates}: first-order {first.elapsed_s:.2f} s "
            f"{first.value:.6f}, Clarabel {conic.elapsed_s:.2f} s {conic.value:.6f} "
            f"({conic.status})"
        )
    return row


HEADER = (
    f"{'case':24s} {'cands':>5s} {'p+e':7s} {'method':11s} {'status':14s} {'relax s':>7s} "
    f"{'total s':>7s} {'D':>9s} {'bound':>9s} {'effic':>6s} {'random D':>9s}"
)


def table(cases: tuple[Case, ...], n_candidates: int, n_poses: int, clarabel: int) -> list[str]:
    return [HEADER, *(run_case(c, n_candidates, n_poses, clarabel) for c in cases)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--candidates", type=int, default=200, help="sampled candidates")
    parser.add_argument("--poses", type=int, default=20)
    parser.add_argument(
        "--clarabel", type=int, default=0, help="also time Clarabel on this many candidates"
    )
    args = parser.parse_args()
    print(HEADER, flush=True)
    for case in CASES:
        print(run_case(case, args.candidates, args.poses, args.clarabel), flush=True)


if __name__ == "__main__":
    main()
