"""Throughput of configuration scoring (paper Eq. 12, 22–23) with gravity-dependent compliance.

For each robot (6-DOF Kinova Jaco2 with every joint compliant and two virtual base-flex axes;
7-DOF Panda likewise) and N = 10^3..10^6 configurations: configurations per second of
:func:`solver.ranking.score_configurations`, split into its stages (gravity loads, chain walk /
Jacobians, weighted traces), for diagonal and full covariances. The same run measures a
per-configuration reference: a Python loop calling Pinocchio once per configuration for the
same score (RNEA and its joint wrenches for the gravity moments, the calibrated chain as
``pin.SE3`` products, Eq. 12 with 6×6 numpy products), checks that both agree, and prints the
ratio; also the rate of the bare Pinocchio calls (one ``rnea`` + one ``forwardKinematics``).

Usage: ``python benchmarks/ranking_throughput.py [--sizes 1e3,1e4,1e5,1e6] [--repeats 3]``.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass

import numpy as np
import pinocchio as pin

import solver  # noqa: F401  (BLAS defaults)
from schemas.robots import load_robot
from solver import lie
from solver.arrays import FloatArray
from solver.kinematics import ChainParameters
from solver.model import build_chain, pin_configuration, sample_configurations
from solver.ranking import RandomEffects, TaskMetric, UncertaintyModel, score_configurations

ROBOTS = ("kinova", "panda")
SIZES = (1_000, 10_000, 100_000, 1_000_000)
STAGES = ("gravity", "jacobians", "score")


@dataclass(frozen=True)
class Row:
    robot: str
    structure: str
    n: int
    total_per_s: float
    total_per_cpu_s: float
    stage_per_s: dict[str, float]


def robot_model(name: str, structure: str) -> UncertaintyModel:
    """A calibrated-looking chain: every joint compliant, base flex, perturbed geometry."""
    description = load_robot(name)
    probe = build_chain(description.urdf_xml, description.base_frame, description.tip_frame)
    chain = build_chain(
        description.urdf_xml,
        description.base_frame,
        description.tip_frame,
        virtual_axes_at=[probe.joint_names[0]],
    )
    rng = np.random.default_rng(0)
    twists = rng.normal(scale=[1e-3] * 3 + [2e-3] * 3, size=(chain.n_links, 6))
    params = ChainParameters(
        chain.nominal_links @ lie.se3_exp(twists),
        rng.uniform(1e-4, 1e-3, len(chain.compliance_axes)),
    )
    k = chain.n_joints
    if structure == "diag":
        std = np.zeros((k, 6))
        std[:, 3:] = np.linspace(3e-4, 2e-3, k)[:, None]
        std[0, :3] = 1e-4
        effects = RandomEffects.from_std(std, np.full(6, 1e-4))
    else:
        factors = rng.normal(scale=1e-3, size=(k, 6, 6))
        effects = RandomEffects(factors @ factors.transpose(0, 2, 1), np.eye(6) * 1e-8)
    return UncertaintyModel.build(chain, params, effects)


def measure(model: UncertaintyModel, n: int, repeats: int) -> tuple[float, float, dict[str, float]]:
    """Best-of-``repeats`` configurations per wall-clock second and per CPU second of this
    process (less sensitive to other load on a shared machine), and per-stage rates (wall)."""
    q = sample_configurations(model.chain, n, np.random.default_rng(1))
    metric = TaskMetric.pose_weights()
    best, best_cpu, best_timings = np.inf, np.inf, {}
    for _ in range(repeats):
        timings: dict[str, float] = {}
        started, started_cpu = time.perf_counter(), time.process_time()
        score_configurations(model, q, metric, timings=timings)
        elapsed = time.perf_counter() - started
        best_cpu = min(best_cpu, time.process_time() - started_cpu)
        if elapsed < best:
            best, best_timings = elapsed, timings
    stages = {s: n / best_timings[s] if best_timings.get(s) else np.inf for s in STAGES}
    return n / best, n / max(best_cpu, 1e-9), stages


def per_configuration_scores(
    model: UncertaintyModel, joint_positions: FloatArray, metric: TaskMetric
) -> FloatArray:
    """The same score, one configuration at a time with Pinocchio (the reference).

    Per configuration: ``rnea`` and the wrenches ``data.f`` for the gravity moments about every
    compliance axis (as :func:`solver.model.gravity_loads`), the calibrated chain as a product
    of ``pin.SE3`` (``exp6`` per joint and flex axis), ``J_j`` = ``toActionMatrixInverse`` of
    the chain after ``L_j``, and Eq. (12)/(23) with 6×6 numpy products.
    """
    chain, params = model.chain, model.params
    pin_model = chain.pin_model.copy()
    gravity = chain.gravity_rotation_world_base @ model.gravity_base
    pin_model.gravity = pin.Motion(gravity, np.zeros(3))
    data = pin_model.createData()
    zero = np.zeros(pin_model.nv)
    links = [pin.SE3(link) for link in params.links]
    covariances = model.effects.frame_covariances
    quadratic = metric.quadratic_form
    axes = chain.compliance_axes
    q_pin = pin_configuration(chain, joint_positions)
    out = np.empty(joint_positions.shape[0])
    for n, (q, qp) in enumerate(zip(joint_positions, q_pin, strict=True)):
        pin.rnea(pin_model, data, qp, zero, zero)
        motions = [pin.exp6(chain.joint_screws[i] * q[i]) for i in range(chain.n_joints)]
        angle = q.copy()
        factors = [pin.SE3.Identity() for _ in range(chain.n_joints)]
        for a, axis in enumerate(axes):
            i = axis.joint_index
            wrench = data.f[chain.pin_joint_ids[i]]
            moment = motions[i].act(wrench).angular  # about the pre-motion frame
            deflection = -params.compliance_rad_per_nm[a] * float(moment @ axis.axis)
            if axis.is_joint_axis:
                angle[i] += deflection
            else:
                factors[i] = factors[i] * pin.exp6(np.r_[0.0, 0.0, 0.0, axis.axis * deflection])
        after = links[-1]
        sigma = np.zeros((6, 6))
        for i in range(chain.n_joints - 1, -1, -1):
            after = factors[i] * pin.exp6(chain.joint_screws[i] * angle[i]) * after
            jacobian = after.toActionMatrixInverse()
            sigma += jacobian @ covariances[i] @ jacobian.T
            after = links[i] * after
        out[n] = float(np.sum(quadratic * sigma))
    return out


def pinocchio_reference_rates(model: UncertaintyModel, n: int = 2000) -> tuple[float, float, float]:
    """Configurations/s of :func:`per_configuration_scores` and of the bare calls (one ``rnea``
    and one ``forwardKinematics`` per configuration), and the largest relative difference
    between the per-configuration and the vectorised scores."""
    chain = model.chain
    q = sample_configurations(chain, n, np.random.default_rng(2))
    metric = TaskMetric.pose_weights()
    started = time.perf_counter()
    reference = per_configuration_scores(model, q, metric)
    full_rate = n / (time.perf_counter() - started)
    pin_model, data = chain.pin_model, chain.pin_model.createData()
    zero = np.zeros(pin_model.nv)
    q_pin = pin_configuration(chain, q)
    started = time.perf_counter()
    for qp in q_pin:
        pin.rnea(pin_model, data, qp, zero, zero)
        pin.forwardKinematics(pin_model, data, qp)
    bare_rate = n / (time.perf_counter() - started)
    vectorised = score_configurations(model, q, metric).score
    mismatch = float(np.abs(vectorised - reference).max() / np.abs(reference).max())
    return full_rate, bare_rate, mismatch


def run(
    robots: tuple[str, ...] = ROBOTS,
    sizes: tuple[int, ...] = SIZES,
    repeats: int = 3,
    reference_n: int = 2000,
) -> tuple[list[Row], dict[str, tuple[float, float, float]]]:
    rows: list[Row] = []
    reference: dict[str, tuple[float, float, float]] = {}
    for name in robots:
        for structure in ("diag", "full"):
            model = robot_model(name, structure)
            if structure == "diag":
                reference[name] = pinocchio_reference_rates(model, reference_n)
            for n in sizes:
                total, total_cpu, stages = measure(model, n, repeats if n <= 100_000 else 1)
                rows.append(Row(name, structure, n, total, total_cpu, stages))
    return rows, reference


def table(rows: list[Row], reference: dict[str, tuple[float, float, float]]) -> str:
    header = ["robot", "Σ", "N", "configurations/s", "per CPU-s", "gravity /s", "Jacobians /s"]
    header += ["score /s", "× per-configuration Pinocchio"]
    lines = ["| " + " | ".join(header) + " |", "|---|---|" + "---:|" * 7]
    for row in rows:
        cells = [row.robot, row.structure, f"{row.n:,}", f"{row.total_per_s:,.0f}"]
        cells.append(f"{row.total_per_cpu_s:,.0f}")
        cells += [f"{row.stage_per_s[s]:,.0f}" for s in STAGES]
        cells.append(f"{row.total_per_s / reference[row.robot][0]:.1f}")
        lines.append("| " + " | ".join(cells) + " |")
    lines.append("")
    for name, (full, bare, mismatch) in reference.items():
        lines.append(
            f"{name}: per-configuration Pinocchio reference (rnea + data.f, exp6 chain, Eq. 12 "
            f"in numpy) {full:,.0f} configurations/s, same scores to {mismatch:.1e} (relative); "
            f"bare rnea + forwardKinematics calls alone {bare:,.0f}/s"
        )
    return "\n".join(lines)


def main(robots: tuple[str, ...] = ROBOTS, sizes: tuple[int, ...] = SIZES, repeats: int = 3) -> str:
    rows, reference = run(robots, sizes, repeats)
    text = table(rows, reference)
    print(text)
    return text


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--sizes", default=",".join(str(s) for s in SIZES))
    parser.add_argument("--robots", default=",".join(ROBOTS))
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    main(
        tuple(args.robots.split(",")),
        tuple(int(float(s)) for s in args.sizes.split(",")),
        args.repeats,
    )
