"""Concealed-effects benchmark of missing-physics discovery (issue 5).

Each scenario hides known physics in simulated Kinova Jaco2 recordings (per-link geometric
errors of 1 mm / 2 mrad, an unknown camera 1.2 m away and an unknown marker, 0.05 mm / 0.003°
noise, rows in execution order 4 s apart) and runs :func:`solver.discovery.discover` from the
rigid model (or from the declared springs, for effects only visible through them), over many
seeds. The groups and what they must show:

* ``null``       — nothing hidden: false-alarm rate (runs naming anything) ≤ 5 %;
* ``single``     — one library effect at a detectable size: right effect *and* joint ≥ 90 %;
* ``hard``       — the same effects made hard (small backlash, 2nd harmonic on a joint with
  restricted travel, drift with a blocked acquisition order): reported, no target;
* ``multi``      — two effects at once: both named;
* ``collinear``  — effects the data cannot (or can barely) tell apart: flagged ambiguous, or
  the truth named where the data separate them; never mislabelled;
* ``off``        — effects outside the library: reported unexplained at the right joint, not
  given a library name;
* ``random``     — floating backlash: the load-sign part named, the floating part routed to
  the covariance calibration.

Metrics per scenario: detection (every hidden effect named with its joint; for ``collinear``
also an ambiguity containing it, for ``off`` an unexplained report at its joint and no name),
ambiguity with the truth among the candidates, wrong name (runs naming something not hidden),
false-discovery rate (wrong names / all names), unexplained rate, 95 % CI coverage
(|estimate − truth| ≤ 1.96 standard errors) and median relative magnitude error of every true
parameter, mean held-out translation error after discovery over the true model's error on the
same samples, median seconds per run. The scenario runs leave out the detectable sizes (a
report after the search: it changes nothing discovery names, ``tests/solver/test_discovery.py::
test_discovery_is_deterministic_given_a_seed``); a timing run at ``--timing-n`` samples uses the
full library and states the sizes, as ``kincal discover`` does by default.

Timings are wall-clock seconds inside each worker; on a shared machine they are inflated by
the load (``os.getloadavg`` is printed with them).

Usage::

    python -m benchmarks.concealed_effects [--seeds 50] [--n 200] [--workers 2]
        [--scenarios null,compliance,...] [--out out/concealed_effects] [--timing-n 500]
        [--write-results]
    python -m benchmarks.concealed_effects --real [--seeds 10] [--workers 2]
        [--recordings fr3,ur10e,talos,tiago,positioner,platonics] [--scenarios backlash_load,...]
        [--sizes 1,2,4] [--out out/concealed_real] [--write-results]

``--real`` runs the semi-real benchmark instead (:mod:`benchmarks.concealed_real`): the
mechanism simulator conceals each library effect in the shipped real recordings at 1, 2 and 4
(``--sizes``) times the detectability their discovery report states. ``--write-results``:
``docs/results/discovery_simulated.{json,md}`` (``--real``: ``discovery_real.{json,md}``), the
tables docs/discovery_benchmark.md and docs/discovery_real_benchmark.md include, with every
run, so tests/test_quoted_numbers.py can check each row against its runs and re-run one.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path
from typing import Any

# One BLAS thread per process: OpenBLAS reads the setting when numpy loads it, and with more
# threads than free cores these small dense problems run about 5x slower.
import solver  # noqa: F401

# isort: split
import numpy as np
import scipy.stats

from benchmarks.results import Row, markdown_table, percent, write_results
from schemas.robots import load_robot
from service.app.simulate import marker_offset
from solver import lie
from solver.calibration import pose_errors
from solver.discovery import DiscoveryData, DiscoveryOptions, discover
from solver.discovery.library import measurement_drift_parameters
from solver.measurement import FullPose
from solver.model import KinematicChain, build_chain
from solver.simulate import JointEffect, SimulationSpec, look_at, simulate_recording

Expected = tuple[str, int | None]  # (effect, joint index)
GROUPS = ("null", "single", "hard", "multi", "collinear", "off", "random")
TARGETS = {
    "null_false_alarm_max": 0.05,
    "single_detection_min": 0.90,
    "fdr_max": 0.10,
    "timing_s_max": 60.0,
}


@dataclasses.dataclass(frozen=True)
class Scenario:
    """Hidden physics: simulation fields, what discovery should report, and the true sizes."""

    group: str
    description: str
    hidden: dict[str, Any] = dataclasses.field(default_factory=dict)
    expect: tuple[Expected, ...] = ()
    truth: dict[Expected, dict[str, float]] = dataclasses.field(default_factory=dict)
    declared: tuple[int, ...] = ()  # joints the user's model already treats as springs
    virtual_at: tuple[int, ...] = ()  # joints of the true robot with virtual flex axes
    unexplained_joint: int | None = None  # off-library: reported unexplained here
    random_joint: int | None = None  # floating: routed to random effects here


NAMED_AS: dict[str, tuple[str, str]] = {
    "gear_periodic": ("gear_periodic", "amplitude_rad"),
    "backlash_load": ("backlash", "backlash_rad"),
    "backlash_direction": ("backlash", "backlash_rad"),
    "joint_scale": ("joint_scale", "scale_error"),
    "drift_linear": ("thermal_drift", "drift_rad_per_s"),
}
"""A hidden joint effect's kind -> the library family discovery should name and that family's
parameter holding the effect's size."""


def _joint_effect(
    group: str,
    description: str,
    effect: JointEffect,
    joints: tuple[str, ...],
    hidden: dict[str, Any] | None = None,
    random_joint: int | None = None,
) -> Scenario:
    """A scenario hiding the one joint effect ``effect`` on one of ``joints`` (with the
    simulation fields ``hidden``), which discovery should name by its family on that joint
    (:data:`NAMED_AS`), the family's parameter the effect's size: stated once, so the truth
    cannot disagree with what was hidden."""
    family, parameter = NAMED_AS[effect.kind]
    named = (family, joints.index(effect.joint))
    return Scenario(
        group,
        description,
        {"joint_effects": (effect,), **(hidden or {})},
        (named,),
        {named: {parameter: effect.size}},
        random_joint=random_joint,
    )


def scenarios(joints: tuple[str, ...]) -> dict[str, Scenario]:
    """The scenario table (Jaco2 joint indices; sizes chosen well above the noise)."""
    j = joints
    k = len(j)
    perturbation = np.zeros((k, 6))
    perturbation[:, 3:] = np.linspace(1e-4, 5e-4, k)[:, None]
    tilt = lie.so3_exp(np.array([np.radians(1.0), 0.0, 0.0])) @ np.array([0.0, 0.0, -9.81])
    restricted = np.ones(k)
    restricted[2] = 0.15
    only_second = np.r_[0.0, 1.0, np.zeros(k - 2)]
    mostly_second = np.r_[0.05, 1.0, np.full(k - 2, 0.05)]
    springs = {j[1]: 5e-4, j[2]: 5e-4}
    gear = JointEffect(j[2], "gear_periodic", 5e-5, harmonic=2)
    camera_drift = np.full(6, 3e-3 / 3600.0 / math.sqrt(3.0))  # 3 mm and 3 mrad per hour
    return {
        "null": Scenario("null", "nothing hidden (white noise)"),
        "null_random": Scenario(
            "null",
            "nothing hidden, random joint perturbations 0.1-0.5 mrad (paper Eq. 7)",
            {"perturbation_sigma": perturbation},
        ),
        "compliance": Scenario(
            "single",
            "joint 2 spring 2e-5 rad/Nm",
            {"compliance_rad_per_nm": {j[1]: 2e-5}},
            (("joint_compliance", 1),),
            {("joint_compliance", 1): {"compliance_rad_per_nm": 2e-5}},
        ),
        "base_flex": Scenario(
            "single",
            "base flex 3e-5 and 1.5e-5 rad/Nm about the two axes ⟂ joint 1",
            {"compliance_rad_per_nm": {f"{j[0]}.flex_a": 3e-5, f"{j[0]}.flex_b": 1.5e-5}},
            (("base_flex", 0),),
            {("base_flex", 0): {"flex_a_rad_per_nm": 3e-5, "flex_b_rad_per_nm": 1.5e-5}},
            virtual_at=(0,),
        ),
        "link_bending": Scenario(
            "single",
            "link carrying joint 3 bends 5e-5 rad/Nm about both axes ⟂ it",
            {"compliance_rad_per_nm": {f"{j[2]}.flex_a": 5e-5, f"{j[2]}.flex_b": 5e-5}},
            (("link_bending", 2),),
            {("link_bending", 2): {"flex_a_rad_per_nm": 5e-5, "flex_b_rad_per_nm": 5e-5}},
            virtual_at=(2,),
        ),
        "gear_h1": _joint_effect(
            "single",
            "joint 4 gear error, 1st harmonic, 0.1 mrad",
            JointEffect(j[3], "gear_periodic", 1e-4, harmonic=1),
            j,
        ),
        "gear_h2": _joint_effect(
            "single",
            "joint 3 gear error, 2nd harmonic, 0.05 mrad",
            gear,
            j,
        ),
        "gear_h3": _joint_effect(
            "single",
            "joint 2 gear error, 3rd harmonic, 0.05 mrad",
            JointEffect(j[1], "gear_periodic", 5e-5, harmonic=3),
            j,
        ),
        "backlash": _joint_effect(
            "single",
            "joint 2 backlash 0.2 mrad, taken up by the load sign",
            JointEffect(j[1], "backlash_load", 2e-4),
            j,
        ),
        "backlash_direction": _joint_effect(
            "single",
            "joint 3 backlash 0.2 mrad, taken up by the approach direction",
            JointEffect(j[2], "backlash_direction", 2e-4),
            j,
        ),
        "joint_scale": _joint_effect(
            "single",
            "joint 2 gear ratio off by 1e-4",
            JointEffect(j[1], "joint_scale", 1e-4),
            j,
        ),
        "drift_shuffled": _joint_effect(
            "single",
            "joint 2 zero drifts 1.8 mrad/h, shuffled acquisition order",
            JointEffect(j[1], "drift_linear", 5e-7),
            j,
        ),
        "camera_drift": Scenario(
            "single",
            "camera frame drifts 3 mm and 3 mrad per hour",
            {"measurement_drift_per_s": camera_drift},
            (("thermal_drift", None),),
            {
                ("thermal_drift", None): dict(
                    zip(measurement_drift_parameters("linear", "s"), camera_drift, strict=True)
                )
            },
        ),
        "gravity_tilt": Scenario(
            "single",
            "base tilted 1° (joints 2, 3: springs 5e-4 rad/Nm, declared)",
            {"compliance_rad_per_nm": springs, "gravity_base": tilt},
            (("gravity_direction", None),),
            {("gravity_direction", None): {"tilt_rad": np.radians(1.0)}},
            declared=(1, 2),
        ),
        "payload": Scenario(
            "single",
            "undeclared 0.3 kg payload (joints 2, 3: springs, declared)",
            {"compliance_rad_per_nm": springs, "payload_kg": 0.3},
            (("payload_mass", None),),
            {("payload_mass", None): {"payload_kg": 0.3}},
            declared=(1, 2),
        ),
        "depth_scale": Scenario(
            "single",
            "camera depth reads 0.05 % long",
            {"depth_scale": 5e-4},
            (("depth_scale", None),),
            {("depth_scale", None): {"scale": 5e-4}},
        ),
        "base_flex_small": Scenario(
            "hard",
            "base flex 1e-5 rad/Nm about both axes ⟂ joint 1 (isotropic: nearly a shoulder spring)",
            {"compliance_rad_per_nm": {f"{j[0]}.flex_a": 1e-5, f"{j[0]}.flex_b": 1e-5}},
            (("base_flex", 0),),
            {("base_flex", 0): {"flex_a_rad_per_nm": 1e-5, "flex_b_rad_per_nm": 1e-5}},
            virtual_at=(0,),
        ),
        "backlash_small": _joint_effect(
            "hard",
            "joint 2 backlash 0.03 mrad by load sign (about the noise)",
            JointEffect(j[1], "backlash_load", 3e-5),
            j,
        ),
        "gear_h2_restricted": _joint_effect(
            "hard",
            "joint 3 gear error (2nd harmonic, 0.05 mrad), its travel restricted to 15 %",
            gear,
            j,
            hidden={"joint_range_fraction": restricted},
        ),
        "drift_blocked": _joint_effect(
            "hard",
            "joint 2 drift 1.8 mrad/h, samples recorded in order of joint 2's angle",
            JointEffect(j[1], "drift_linear", 5e-7),
            j,
            hidden={"order_by_joint": j[1]},
        ),
        "two_effects": Scenario(
            "multi",
            "joint 2 spring 2e-5 rad/Nm and joint 3 gear error (2nd harmonic, 0.05 mrad)",
            {"compliance_rad_per_nm": {j[1]: 2e-5}, "joint_effects": (gear,)},
            (("joint_compliance", 1), ("gear_periodic", 2)),
            {
                ("joint_compliance", 1): {"compliance_rad_per_nm": 2e-5},
                ("gear_periodic", 2): {"amplitude_rad": 5e-5},
            },
        ),
        "collinear": Scenario(
            "collinear",
            "joint 2 spring, every other joint fixed: its torque is a 1st harmonic of q2",
            {"compliance_rad_per_nm": {j[1]: 2e-5}, "joint_range_fraction": only_second},
            (("joint_compliance", 1),),
        ),
        "nearly_collinear": Scenario(
            "collinear",
            "joint 2 spring, the other joints move over 5 % of their range",
            {"compliance_rad_per_nm": {j[1]: 2e-5}, "joint_range_fraction": mostly_second},
            (("joint_compliance", 1),),
        ),
        "gear_dent": Scenario(
            "off",
            "joint 4 gear has a local defect: 0.4 mrad over ±0.25 rad (not in the library)",
            {"joint_effects": (JointEffect(j[3], "bump", 4e-4, centre_rad=1.0, width_rad=0.25),)},
            unexplained_joint=3,
        ),
        "softening_spring": Scenario(
            "off",
            "joint 2 deflects 1e-6 rad × τ|τ| (a softening spring; not in the library)",
            {"joint_effects": (JointEffect(j[1], "load_quadratic", 1e-6),)},
            unexplained_joint=1,
        ),
        "floating_backlash": _joint_effect(
            "random",
            "joint 2 backlash 2 mrad, floating where |τ| < 3 N·m",
            JointEffect(j[1], "backlash_load", 2e-3, float_below_nm=3.0),
            j,
            random_joint=1,
        ),
    }


@dataclasses.dataclass(frozen=True)
class RunResult:
    scenario: str
    seed: int
    n: int
    named: list[Expected]
    ambiguous: list[list[Expected]]
    unexplained: list[int | None]
    random: list[int]
    z_scores: list[float]
    relative_errors: list[float]
    heldout_before_mm: float
    heldout_after_mm: float
    oracle_mm: float
    seconds: float


def _chains(robot_name: str, virtual_at: tuple[int, ...]) -> KinematicChain:
    robot = load_robot(robot_name)
    probe = build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)
    virtual = [probe.joint_names[i] for i in virtual_at]
    return build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame, virtual_axes_at=virtual)


def scenarios_of(robot_name: str) -> dict[str, Scenario]:
    """The scenario table on ``robot_name``'s joints."""
    return scenarios(_chains(robot_name, ()).joint_names)


def _spec(scenario: Scenario, seed: int, n: int) -> SimulationSpec:
    return SimulationSpec(
        n_samples=n,
        seed=seed,
        noise_sigma=np.r_[[5e-5] * 3, [np.radians(0.003)] * 3],
        measurement_frame=look_at(np.array([0.9, -0.6, 0.5]), np.array([0.0, 0.0, 0.25])),
        tool_offset=marker_offset(),
        **scenario.hidden,
    )


def run_one(job: tuple[str, str, int, int, int, bool]) -> RunResult:
    """One discovery on one seed of one scenario (top level, so worker processes can run it);
    the job's last field: state the detectable sizes too."""
    robot_name, name, seed, n, bootstrap, sizes = job
    scenario = scenarios(_chains(robot_name, ()).joint_names)[name]
    truth = _chains(robot_name, scenario.virtual_at)
    recording = simulate_recording(truth, _spec(scenario, seed, n))
    axes = tuple(
        a for a in truth.compliance_axes if a.is_joint_axis and a.joint_index in scenario.declared
    )
    model = dataclasses.replace(truth, compliance_axes=axes)
    data = DiscoveryData(
        recording.joint_positions, recording.measured_pose, FullPose(), recording.time_s
    )
    started = time.perf_counter()
    options = DiscoveryOptions(seed=seed, bootstrap=bootstrap, detectability=sizes)
    result = discover(model, data, options)
    seconds = time.perf_counter() - started
    z_scores, relative = [], []
    for finding in result.findings:
        key = (finding.estimate.term.effect, finding.estimate.term.joint_index)
        true_values = scenario.truth.get(key, {})
        scale = max((abs(v) for v in true_values.values()), default=1.0)
        for parameter, true_value in true_values.items():
            if parameter not in finding.estimate.parameters:
                continue  # another shape of the same effect (e.g. warm-up vs linear drift)
            value = finding.estimate.parameters[parameter]
            error = finding.estimate.stderr.get(parameter, float("nan"))
            z_scores.append((value - true_value) / error)
            relative.append(abs(value - true_value) / scale)
    oracle = pose_errors(recording.true_mean_pose, recording.measured_pose, rotation=True)[0]
    kept = np.setdiff1d(np.arange(n), result.outlier_rows)
    return RunResult(
        scenario=name,
        seed=seed,
        n=n,
        named=[(f.estimate.term.effect, f.estimate.term.joint_index) for f in result.findings],
        ambiguous=[
            [(c.term.effect, c.term.joint_index) for c in a.candidates] for a in result.ambiguous
        ],
        unexplained=[u.joint_index for u in result.unexplained],
        random=[r.joint_index for r in result.random_effects],
        z_scores=z_scores,
        relative_errors=relative,
        heldout_before_mm=result.heldout_before.translation_mm,
        heldout_after_mm=result.heldout_after.translation_mm,
        oracle_mm=float(oracle[kept].mean()),
        seconds=seconds,
    )


def judge(scenario: Scenario, run: RunResult) -> tuple[bool, int]:
    """(detected, number of wrong names) of one run — see the module docstring."""
    expected = set(scenario.expect)
    wrong = sum(1 for item in run.named if item not in expected)
    if scenario.group == "null":
        return not run.named, wrong
    if scenario.group == "off":
        return scenario.unexplained_joint in run.unexplained and not run.named, wrong
    if scenario.group == "collinear":  # honest: flagged ambiguous, or the truth named
        flagged = any(expected & set(entry) for entry in run.ambiguous)
        return (flagged or expected <= set(run.named)) and wrong == 0, wrong
    detected = expected <= set(run.named)
    if scenario.random_joint is not None:
        detected = detected and scenario.random_joint in run.random
    return detected, wrong


def summarise(scenario: Scenario, runs: list[RunResult]) -> dict[str, float]:
    judged = [judge(scenario, run) for run in runs]
    names = sum(len(run.named) for run in runs)
    wrong = sum(w for _, w in judged)
    z = np.array([v for run in runs for v in run.z_scores])
    rel = np.array([v for run in runs for v in run.relative_errors])
    expected = set(scenario.expect)
    flagged = [any(expected & set(entry) for entry in run.ambiguous) for run in runs]
    return {
        "runs": float(len(runs)),
        "detected": float(np.mean([d for d, _ in judged])),
        "ambiguous_truth": float(np.mean(flagged)) if expected else 0.0,
        "named_right": float(np.mean([bool(expected) and expected <= set(r.named) for r in runs])),
        "honest": float(
            np.mean([(d or f) and w == 0 for (d, w), f in zip(judged, flagged, strict=True)])
        ),
        "named_any": float(np.mean([bool(run.named) for run in runs])),
        "false_runs": float(np.mean([w > 0 for _, w in judged])),
        "names": float(names),
        "wrong_names": float(wrong),
        "fdr": wrong / names if names else 0.0,
        "ambiguous": float(np.mean([bool(r.ambiguous) for r in runs])),
        "unexplained": float(np.mean([bool(r.unexplained) for r in runs])),
        "random": float(np.mean([bool(r.random) for r in runs])),
        "coverage": float(np.mean(np.abs(z) <= 1.96)) if z.size else float("nan"),
        "z_count": float(z.size),
        "z_inside": float(np.sum(np.abs(z) <= 1.96)),
        "z_sd": float(np.std(z)) if z.size > 1 else float("nan"),
        "rel_error": float(np.median(rel)) if rel.size else float("nan"),
        "rel_error_p90": float(np.quantile(rel, 0.9)) if rel.size else float("nan"),
        "heldout_before": float(np.mean([r.heldout_before_mm / r.oracle_mm for r in runs])),
        "heldout_ratio": float(np.mean([r.heldout_after_mm / r.oracle_mm for r in runs])),
        "seconds": float(np.median([r.seconds for r in runs])),
        "seconds_max": float(np.max([r.seconds for r in runs])),
    }


def clopper_pearson(successes: int, trials: int, level: float = 0.95) -> tuple[float, float]:
    """Exact (Clopper–Pearson) binomial confidence interval of a rate; ``trials`` ≥ 1."""
    interval = scipy.stats.binomtest(successes, trials).proportion_ci(level, method="exact")
    return float(interval.low), float(interval.high)


def _pct(value: float | None, digits: int = 0) -> str:
    return "–" if value is None or math.isnan(value) else percent(value, digits)


def _term_text(item: Expected) -> str:
    effect, joint = item
    return f"{effect}@{'-' if joint is None else joint}"


def _term(text: str) -> Expected:
    effect, _, joint = text.rpartition("@")
    return effect, None if joint == "-" else int(joint)


def outcome(run: RunResult) -> Row:
    """One run as the results file keeps it (terms as ``effect@joint index``; sizes rounded
    far below what the table shows)."""
    return {
        "seed": run.seed,
        "named": [_term_text(t) for t in run.named],
        "ambiguous": [[_term_text(t) for t in entry] for entry in run.ambiguous],
        "unexplained": run.unexplained,
        "random": run.random,
        "z_scores": [round(z, 4) for z in run.z_scores],
        "relative_errors": [round(e, 6) for e in run.relative_errors],
        "heldout_before_mm": round(run.heldout_before_mm, 6),
        "heldout_after_mm": round(run.heldout_after_mm, 6),
        "oracle_mm": round(run.oracle_mm, 6),
        "seconds": round(run.seconds, 3),
    }


def run_of(scenario: str, n: int, record: Row) -> RunResult:
    """The run :func:`outcome` kept."""
    return RunResult(
        scenario=scenario,
        seed=record["seed"],
        n=n,
        named=[_term(t) for t in record["named"]],
        ambiguous=[[_term(t) for t in entry] for entry in record["ambiguous"]],
        unexplained=record["unexplained"],
        random=record["random"],
        z_scores=record["z_scores"],
        relative_errors=record["relative_errors"],
        heldout_before_mm=record["heldout_before_mm"],
        heldout_after_mm=record["heldout_after_mm"],
        oracle_mm=record["oracle_mm"],
        seconds=record["seconds"],
    )


def scenario_row(name: str, scenario: Scenario, n: int, runs: list[RunResult]) -> Row:
    """One results row: the scenario, :func:`summarise` of its kept runs (NaN as null) and the
    runs (``outcomes``), so the row can be checked against them."""
    outcomes = [outcome(r) for r in runs]
    numbers = summarise(scenario, [run_of(name, n, o) for o in outcomes])
    return {
        "scenario": name,
        "group": scenario.group,
        "description": scenario.description,
        "n": n,
        **{k: None if math.isnan(v) else v for k, v in numbers.items()},
        "outcomes": outcomes,
    }


def table(rows: list[Row]) -> str:
    """Markdown table, one row per scenario row."""
    header = (
        "Scenario",
        "Group",
        "Runs",
        "Detected",
        "Ambiguous (truth among them)",
        "Wrong name",
        "False-discovery rate",
        "Unexplained",
        "CI coverage (95 %)",
        "Median rel. error",
        "Held-out / true model",
        "s/run",
    )
    lines = [
        (
            f"{r['scenario']}: {r['description']}".replace("|", "\\|"),  # |τ| in a cell
            r["group"],
            f"{r['runs']:.0f}",
            _pct(r["detected"]),
            _pct(r["ambiguous_truth"]),
            _pct(r["false_runs"]),
            _pct(r["fdr"]),
            _pct(r["unexplained"]),
            _pct(r["coverage"]),
            _pct(r["rel_error"], 1),
            f"{r['heldout_ratio']:.3f}",
            f"{r['seconds']:.1f}",
        )
        for r in rows
    ]
    return markdown_table(header, lines)


def headline(rows: list[Row], timing: Row | None) -> tuple[str, dict[str, float]]:
    """The issue's targets: pooled rates with exact 95 % intervals, and the timing runs
    (``timing``: :func:`timing_row`)."""
    by_group: dict[str, list[Row]] = {g: [] for g in GROUPS}
    for r in rows:
        by_group[r["group"]].append(r)
    out: dict[str, float] = {}
    lines = []
    null = by_group["null"]
    if null:
        runs = int(sum(r["runs"] for r in null))
        alarms = round(sum(r["named_any"] * r["runs"] for r in null))
        low, high = clopper_pearson(alarms, runs)
        out["null_false_alarm"] = alarms / runs
        lines.append(
            f"- null false-alarm rate (runs naming anything): {alarms}/{runs} = "
            f"{_pct(alarms / runs, 1)} (95 % CI {_pct(low, 1)}–{_pct(high, 1)}; target ≤ "
            f"{_pct(TARGETS['null_false_alarm_max'])})"
        )
    single = by_group["single"]
    if single:
        worst = min(single, key=lambda r: r["detected"])
        mean = float(np.mean([r["detected"] for r in single]))
        out["single_detection_min"] = worst["detected"]
        lines.append(
            f"- detection of single effects at a detectable size: mean {_pct(mean, 1)}, lowest "
            f"{_pct(worst['detected'], 1)} ({worst['scenario']}; target ≥ "
            f"{_pct(TARGETS['single_detection_min'])} each)"
        )
        count = int(sum(r["z_count"] for r in single))
        inside = int(sum(r["z_inside"] for r in single))
        spread = [r["z_sd"] for r in single if r["z_sd"] is not None]
        if count:
            low, high = clopper_pearson(inside, count)
            out["single_coverage"] = inside / count
            lines.append(
                f"- 95 % confidence intervals of the single effects' parameters hold the truth in "
                f"{inside}/{count} = {_pct(inside / count, 1)} (95 % CI {_pct(low, 1)}–"
                f"{_pct(high, 1)})"
                + (
                    "; standard deviation of (estimate − truth)/stderr per scenario "
                    f"{min(spread):.2f}–{max(spread):.2f}"
                    if spread
                    else ""
                )
            )
    names = sum(r["names"] for r in rows)
    wrong = sum(r["wrong_names"] for r in rows)
    if names:
        low, high = clopper_pearson(int(wrong), int(names))
        out["fdr"] = wrong / names
        lines.append(
            f"- false-discovery rate over all scenarios: {wrong:.0f}/{names:.0f} names = "
            f"{_pct(wrong / names, 1)} (95 % CI {_pct(low, 1)}–{_pct(high, 1)}; target ≤ "
            f"{_pct(TARGETS['fdr_max'])})"
        )
    for r in [r for r in rows if r["group"] in ("collinear", "hard")]:
        lines.append(
            f"- {r['scenario']}: named right in {_pct(r['named_right'])} of runs, flagged "
            f"ambiguous with the truth among the candidates in {_pct(r['ambiguous_truth'])}, a "
            f"wrong name in {_pct(r['false_runs'])}"
        )
    off = by_group["off"]
    if off:
        lines.append(
            "- off-library effects reported unexplained at their joint: "
            + ", ".join(f"{r['scenario']} {_pct(r['detected'])}" for r in off)
            + f"; given a library name in {_pct(float(np.mean([r['named_any'] for r in off])))}"
        )
    if timing and timing["timing_seconds"]:
        seconds = timing["timing_seconds"]
        out["timing_median_s"] = float(np.median(seconds))
        out["timing_max_s"] = float(np.max(seconds))
        load = ", ".join(f"{v:.1f}" for v in timing["load_average"])
        lines.append(
            f"- runtime at N = {timing['timing_n']}, full library with the detectable sizes: "
            f"median {np.median(seconds):.1f} s, max {np.max(seconds):.1f} s over "
            f"{len(seconds)} runs (target < {TARGETS['timing_s_max']:.0f} s; load average "
            f"{load} as the benchmark ended)"
        )
    return "\n".join(lines), out


def timing_row(
    robot_name: str,
    n: int,
    seeds: int,
    bootstrap: int,
    workers: int,
    discoveries: int,
    timing_n: int,
    timing_seconds: list[float],
    total_s: float,
) -> Row:
    """The results file's last row: how the benchmark ran, the timing runs and the load."""
    return {
        "robot": robot_name,
        "n": n,
        "seeds": seeds,
        "bootstrap": bootstrap,
        "workers": workers,
        "discoveries": discoveries,
        "timing_n": timing_n,
        "timing_seconds": [round(s, 3) for s in timing_seconds],
        "load_average": [round(v, 2) for v in os.getloadavg()],
        "total_s": round(total_s, 1),
    }


def footer(timing: Row) -> str:
    return (
        f"{timing['discoveries']} discoveries ({timing['robot']}, N = {timing['n']}, "
        f"{timing['seeds']} seeds per scenario, {timing['bootstrap']} bootstrap replicates) + "
        f"{len(timing['timing_seconds'])} timing runs at N = {timing['timing_n']}, "
        f"{timing['workers']} worker(s), {timing['total_s']:.0f} s in total."
    )


def render(rows: list[Row]) -> str:
    """``docs/results/discovery_simulated.md``: the table, the targets and how it ran."""
    scenario_rows = [r for r in rows if "scenario" in r]
    (timing,) = [r for r in rows if "scenario" not in r]
    summary, _ = headline(scenario_rows, timing)
    return f"{table(scenario_rows)}\n\n{summary}\n\n{footer(timing)}"


def _write_csv(path: Path, rows: Iterable[dict[str, Any]]) -> None:
    rows = list(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)


def _label(items: Iterable[Expected], joints: tuple[str, ...]) -> str:
    return ";".join(f"{e}@{'-' if j is None else joints[j]}" for e, j in items)


def _run_record(run: RunResult, scenario: Scenario, joints: tuple[str, ...]) -> dict[str, Any]:
    detected, wrong = judge(scenario, run)
    return {
        "scenario": run.scenario,
        "group": scenario.group,
        "seed": run.seed,
        "n": run.n,
        "detected": int(detected),
        "wrong_names": wrong,
        "named": _label(run.named, joints),
        "ambiguous": "|".join(_label(entry, joints) for entry in run.ambiguous),
        "unexplained": ";".join("-" if j is None else joints[j] for j in run.unexplained),
        "random": ";".join(joints[j] for j in run.random),
        "z_scores": ";".join(f"{z:.3f}" for z in run.z_scores),
        "relative_errors": ";".join(f"{e:.4f}" for e in run.relative_errors),
        "heldout_before_mm": f"{run.heldout_before_mm:.5f}",
        "heldout_after_mm": f"{run.heldout_after_mm:.5f}",
        "oracle_mm": f"{run.oracle_mm:.5f}",
        "seconds": f"{run.seconds:.3f}",
    }


def _execute(
    jobs: list[tuple[str, str, int, int, int, bool]], workers: int, echo: Callable[[str], None]
) -> list[RunResult]:
    if workers <= 1:
        return [run_one(job) for job in jobs]
    results: list[RunResult] = []
    step = max(1, len(jobs) // 20)
    with ProcessPoolExecutor(workers) as pool:
        futures = [pool.submit(run_one, job) for job in jobs]
        for done, future in enumerate(as_completed(futures), start=1):
            results.append(future.result())
            if done % step == 0 or done == len(jobs):
                echo(f"[{done}/{len(jobs)} runs]")
    order = {(job[1], job[2], job[3]): i for i, job in enumerate(jobs)}
    return sorted(results, key=lambda r: order[(r.scenario, r.seed, r.n)])


RESULTS_NAME = "discovery_simulated"


def main(
    seeds: int = 50,
    n: int = 200,
    workers: int = 2,
    names: list[str] | None = None,
    robot_name: str = "kinova",
    bootstrap: int = 50,
    out_dir: Path | None = None,
    timing_n: int = 500,
    timing_seeds: int = 5,
    echo: Callable[[str], None] = print,
    first_seed: int = 0,
    write_command: str | None = None,
) -> tuple[str, dict[str, Row], dict[str, float]]:
    """Run the benchmark; returns (markdown table, per-scenario rows, headline numbers).
    ``write_command``: also write ``docs/results/discovery_simulated.{json,md}``, recording
    this command."""
    joints = _chains(robot_name, ()).joint_names
    described = scenarios(joints)
    chosen = names or list(described)
    unknown = sorted(set(chosen) - set(described))
    if unknown:
        raise SystemExit(f"unknown scenario(s) {', '.join(unknown)}; known: {', '.join(described)}")
    started = time.perf_counter()
    seed_range = range(first_seed, first_seed + seeds)
    jobs = [(robot_name, name, seed, n, bootstrap, False) for name in chosen for seed in seed_range]
    timing_jobs = [
        (robot_name, "two_effects", 1000 + seed, timing_n, bootstrap, True)
        for seed in range(timing_seeds)
    ]
    progress = (lambda text: print(text, file=sys.stderr, flush=True)) if echo is print else echo
    results = _execute(jobs + timing_jobs, workers, progress)
    runs, timed = results[: len(jobs)], results[len(jobs) :]
    rows = {
        name: scenario_row(name, described[name], n, [r for r in runs if r.scenario == name])
        for name in chosen
    }
    timing = timing_row(
        robot_name,
        n,
        seeds,
        bootstrap,
        workers,
        len(jobs),
        timing_n,
        [r.seconds for r in timed],
        time.perf_counter() - started,
    )
    text = table(list(rows.values()))
    summary, numbers = headline(list(rows.values()), timing)
    echo(text)
    echo("")
    echo(summary)
    echo("")
    echo(footer(timing))
    if out_dir is not None:
        _write_csv(
            out_dir / "runs.csv",
            (_run_record(r, described[r.scenario], joints) for r in runs + timed),
        )
        _write_csv(
            out_dir / "scenarios.csv",
            (
                {k: v for k, v in row.items() if k not in ("description", "outcomes")}
                for row in rows.values()
            ),
        )
        (out_dir / "table.md").write_text(
            f"{text}\n\n{summary}\n\n{footer(timing)}\n", encoding="utf-8"
        )
    if write_command is not None:
        for path in write_results(RESULTS_NAME, write_command, [*rows.values(), timing], render):
            echo(f"wrote {path}")
    return text, rows, numbers


def command_line(arguments: argparse.Namespace) -> str:
    """The command that re-makes a results file: the options that change a number."""
    flags = ["--real"] if arguments.real else []
    flags += [f"--seeds {arguments.seeds}"]
    if arguments.real:
        flags += [f"--sizes {arguments.sizes}"]
        if arguments.recordings:
            flags += [f"--recordings {arguments.recordings}"]
        if arguments.seeds_only:
            flags += ["--seeds-only"]
    else:
        flags += [f"--n {arguments.n}", f"--bootstrap {arguments.bootstrap}"]
        flags += [f"--timing-n {arguments.timing_n}", f"--timing-seeds {arguments.timing_seeds}"]
        if arguments.robot != "kinova":
            flags += [f"--robot {arguments.robot}"]
        if arguments.first_seed:
            flags += [f"--first-seed {arguments.first_seed}"]
    if arguments.scenarios:
        flags += [f"--scenarios {arguments.scenarios}"]
    flags += [f"--workers {arguments.workers}", "--write-results"]
    return "python -m benchmarks.concealed_effects " + " ".join(flags)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--seeds", type=int, default=50)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--n", type=int, default=200)
    parser.add_argument("--workers", type=int, default=2, help="Processes (≤ your free cores).")
    parser.add_argument("--robot", default="kinova")
    parser.add_argument("--bootstrap", type=int, default=50)
    parser.add_argument("--scenarios", default=None, help="Comma-separated subset.")
    parser.add_argument("--out", type=Path, default=Path("out/concealed_effects"))
    parser.add_argument("--timing-n", type=int, default=500)
    parser.add_argument("--timing-seeds", type=int, default=5)
    parser.add_argument("--real", action="store_true", help="Semi-real benchmark (data/real).")
    parser.add_argument("--recordings", default=None, help="--real: comma-separated subset.")
    parser.add_argument(
        "--seeds-only",
        action="store_true",
        help="--real: exactly --seeds runs per row, even where joints with a stated size are "
        "left untried (a quick run; by default every such joint gets one).",
    )
    parser.add_argument(
        "--sizes", default="1,2,4", help="--real: multiples of the stated detectability."
    )
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="docs/results/discovery_simulated.{json,md} (--real: discovery_real.{json,md})",
    )
    arguments = parser.parse_args()
    write_command = command_line(arguments) if arguments.write_results else None
    if arguments.real:
        from benchmarks import concealed_real

        real_text = concealed_real.main(
            seeds=arguments.seeds,
            workers=arguments.workers,
            recordings=arguments.recordings.split(",") if arguments.recordings else None,
            effects=arguments.scenarios.split(",") if arguments.scenarios else None,
            sizes=tuple(float(m) for m in arguments.sizes.split(",")),
            write_command=write_command,
            every_joint=not arguments.seeds_only,
        )[0]
        arguments.out.mkdir(parents=True, exist_ok=True)
        (arguments.out / "real_table.md").write_text(real_text, encoding="utf-8")
        raise SystemExit(0)
    main(
        seeds=arguments.seeds,
        n=arguments.n,
        workers=arguments.workers,
        names=arguments.scenarios.split(",") if arguments.scenarios else None,
        robot_name=arguments.robot,
        bootstrap=arguments.bootstrap,
        out_dir=arguments.out,
        timing_n=arguments.timing_n,
        timing_seeds=arguments.timing_seeds,
        first_seed=arguments.first_seed,
        write_command=write_command,
    )
