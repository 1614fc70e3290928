"""Covariance calibration (paper §IV-C): solvers × estimators on simulated Jaco2 data.

Data, per N and seed: the paper-like Jaco2 of :func:`service.app.simulate.scenario` (geometric
errors, compliant 2nd and 3rd joints, unknown camera and marker, random rotations ξ_j with σ
0.3 → 2 mrad on every joint frame, noise 0.05 mm / 0.05 mrad), simulated by
:func:`solver.simulate.simulate_recording`, so the truth is known. The deterministic fit
(:func:`solver.measurement.pose.fit_deterministic`, Eq. 10) leaves end-effector-frame residuals; the
frame Jacobians J_j = Ad_{B_j}⁻¹ are taken at the fitted geometry, exactly as the pipeline's
covariance stage does. Σ_n is estimated with the rest (product default) unless
``--known-noise``.

Per solver (clarabel; pgd-published = paper Table I taken literally; pgd-published-kkt = Table I
step and start, run until the KKT residual is below 1e-6 or 10⁵ iterations — what the published
step costs to reach an answer, cf. the paper's 7.56 s; pgd-stable; nnls) and estimator (moment,
ml, reml) :func:`solver.covariance.estimate_covariances` runs without standard errors and the
table reports, median over seeds:

* stats s — building the sufficient statistics of Eq. (13–14) (timed on its own);
* solve s — the Eq. (14) solver plus, for ml/reml, the likelihood fit started from it;
* total s — the whole ``estimate_covariances`` call (statistics, identifiability, solve);
* status / iter — of the final stage; objective — Eq. (14) squared for moment, the NLL for
  ml/reml; Δ vs clarabel — (f − f_clarabel)/f_clarabel for moment, f − f_clarabel for ml/reml;
* task err — mean |score − true score| / true score of tr(W Σ_E Wᵀ), W = diag(0.4, 0.4, 0,
  0.1, 0.1, 0), Σ_n excluded, on held-out configurations (the product's
  :func:`solver.ranking.score_configurations` with the fitted vs the true robot);
* σ rot / σ trans — RMS error of the per-axis σ of the joint frames vs truth (mrad, mm).

ml/reml with the non-default solvers are skipped above ``--likelihood-all-max-n``: their moment
answer only starts the likelihood fit, whose fixed point does not depend on it.

With ``--write-results`` also ``docs/results/compare_solvers.{json,md}`` (every estimate, and
the table of the rows :data:`PAGE_ROWS` picks) and ``docs/results/compare_solvers_timing.{json,md}``
(the timing figures), the tables docs/covariance.md includes.

Usage: ``python -m benchmarks.compare_solvers [--sizes 119,1e3,1e4,1e5] [--seeds 1,2,3]
[--csv out.csv] [--known-noise] [--idle 0.1] [--write-results]``.
"""

from __future__ import annotations

import argparse
import csv
import sys
import time
from collections import Counter
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np

import solver  # noqa: F401  (BLAS defaults before numpy work)
from benchmarks import results
from benchmarks.scale import wait_until_idle
from schemas.calibration import CalibrationOptions
from schemas.robots import load_robot
from service.app.simulate import scenario
from solver.arrays import FloatArray
from solver.covariance import (
    KKT_TOLERANCE,
    PGD_PUBLISHED,
    PGD_STABLE,
    PGDSettings,
    build_moment_statistics,
    estimate_covariances,
    make_layout,
    solve_moment,
)
from solver.covariance.estimate import CovarianceEstimate, EstimatorName
from solver.covariance.solvers import ConcreteSolver, concrete_solver
from solver.kinematics import ChainParameters, evaluate_chain
from solver.measurement import FullPose
from solver.measurement.pose import fit_deterministic
from solver.model import KinematicChain, gravity_loads, sample_configurations
from solver.ranking import (
    PAPER_WEIGHTS,
    RandomEffects,
    TaskMetric,
    UncertaintyModel,
    score_configurations,
)
from solver.simulate import simulate_recording

SIZES = (119, 1_000, 10_000, 100_000)
SEEDS = (1, 2, 3)
EFFECTS = ("geometry", "compliance", "random", "camera", "marker")
SOLVERS: dict[str, tuple[ConcreteSolver, PGDSettings]] = {
    "clarabel": ("clarabel", PGD_STABLE),
    "pgd-published": ("pgd", PGD_PUBLISHED),
    "pgd-published-kkt": (
        "pgd",
        replace(PGD_PUBLISHED, stopping="projected_gradient", tolerance=KKT_TOLERANCE),
    ),
    "pgd-stable": ("pgd", PGD_STABLE),
    "nnls": ("nnls", PGD_STABLE),
}
ESTIMATORS: tuple[EstimatorName, ...] = ("moment", "ml", "reml")
_PRODUCT = CalibrationOptions()
DEFAULT_SOLVER = {"clarabel": "clarabel", "pgd": "pgd-stable", "nnls": "nnls"}[
    concrete_solver(_PRODUCT.covariance_solver, "diag")
]
DEFAULT_ESTIMATOR: EstimatorName = _PRODUCT.covariance_estimator
N_HELDOUT = 1_000


@dataclass(frozen=True)
class Problem:
    """One simulated recording after the deterministic fit, and its truth.

    ``residuals`` (N, 6) EE frame, m and rad; ``frame_jacobians`` (N, k, 6, 6) at the fitted
    geometry; ``fit_jacobian`` (N, 6, p) of the deterministic fit (rotation weight 1).
    ``true_scores`` (N_heldout,) m² of the true robot at ``heldout_q`` (N_heldout, k) rad.
    """

    n: int
    seed: int
    chain: KinematicChain
    residuals: FloatArray
    frame_jacobians: FloatArray
    fit_jacobian: FloatArray
    fitted_params: ChainParameters
    true_sigma: FloatArray  # (k, 6) m, rad
    noise_covariance: FloatArray  # (6, 6) true Σ_n
    heldout_q: FloatArray
    true_scores: FloatArray
    setup_s: float


@dataclass(frozen=True)
class Row:
    """One estimate; times in s, σ errors in mrad / mm, task error as a fraction."""

    n: int
    seed: int
    solver: str
    estimator: str
    stats_s: float
    solve_s: float
    total_s: float
    status: str
    iterations: int
    moment_status: str
    moment_iterations: int
    objective: float
    moment_objective: float
    delta_vs_clarabel: float
    sigma_maxdiff_vs_clarabel: float
    task_error: float
    sigma_rmse_rot_mrad: float
    sigma_rmse_trans_mm: float
    rank: int
    n_params: int


def simulate_problem(n: int, seed: int) -> Problem:
    """Simulate, fit the deterministic model, and prepare the held-out truth."""
    started = time.perf_counter()
    setup = scenario(load_robot("kinova"), n_samples=n, seed=seed, effects=EFFECTS)
    chain = setup.chain
    recording = simulate_recording(chain, setup.spec)
    q = recording.joint_positions
    loads = gravity_loads(chain, q)
    fit = fit_deterministic(chain, q, recording.measured_pose, loads, measurement=FullPose())
    evaluation = evaluate_chain(chain, fit.params, q, loads)
    noise = np.diag(recording.noise_sigma**2)
    truth = UncertaintyModel.build(
        chain,
        recording.true_params,
        RandomEffects.from_std(recording.perturbation_sigma, recording.noise_sigma),
    )
    heldout_q = sample_configurations(chain, N_HELDOUT, np.random.default_rng(10_000 + seed))
    metric = TaskMetric.pose_weights(PAPER_WEIGHTS)
    return Problem(
        n=n,
        seed=seed,
        chain=chain,
        residuals=fit.residuals,
        frame_jacobians=evaluation.link_jacobians[:, : chain.n_joints],
        fit_jacobian=fit.jacobian,
        fitted_params=fit.params,
        true_sigma=recording.perturbation_sigma,
        noise_covariance=noise,
        heldout_q=heldout_q,
        true_scores=score_configurations(truth, heldout_q, metric).score,
        setup_s=time.perf_counter() - started,
    )


def statistics_time(problem: Problem, *, known_noise: bool, repeats: int) -> float:
    """Best-of-``repeats`` seconds to build G, h, c of Eq. (13–14) for this problem."""
    layout = make_layout(problem.chain.joint_names, 6, include_noise=not known_noise)
    known = problem.noise_covariance if known_noise else None
    best = np.inf
    for _ in range(repeats):
        started = time.perf_counter()
        build_moment_statistics(
            problem.residuals, problem.frame_jacobians, layout, known_covariance=known
        )
        best = min(best, time.perf_counter() - started)
    return float(best)


def estimate(
    problem: Problem, solver_label: str, estimator: EstimatorName, *, known_noise: bool
) -> tuple[CovarianceEstimate, float]:
    """The product's entry point with one solver and estimator; returns it and its wall time."""
    solver_name, settings = SOLVERS[solver_label]
    started = time.perf_counter()
    result = estimate_covariances(
        problem.residuals,
        problem.frame_jacobians,
        problem.chain.joint_names,
        estimator=estimator,
        solver=solver_name,
        pgd_settings=settings,
        fit_jacobian=problem.fit_jacobian,
        noise_covariance=problem.noise_covariance if known_noise else None,
        standard_errors=False,
    )
    return result, time.perf_counter() - started


def task_error(problem: Problem, result: CovarianceEstimate) -> float:
    """Mean relative error of the noise-free task score on the held-out configurations."""
    effects = RandomEffects(result.frame_covariances(), result.noise_covariance())
    model = UncertaintyModel.build(problem.chain, problem.fitted_params, effects)
    predicted = score_configurations(
        model, problem.heldout_q, TaskMetric.pose_weights(PAPER_WEIGHTS)
    ).score
    return float(np.mean(np.abs(predicted - problem.true_scores) / problem.true_scores))


def sigma_errors(problem: Problem, result: CovarianceEstimate) -> tuple[float, float]:
    """RMS error of the joint frames' per-axis σ: rotation (mrad) and translation (mm)."""
    error = np.array([f.std for f in result.frames]) - problem.true_sigma
    return (
        1e3 * float(np.sqrt(np.mean(error[:, 3:] ** 2))),
        1e3 * float(np.sqrt(np.mean(error[:, :3] ** 2))),
    )


def all_sigmas(result: CovarianceEstimate) -> FloatArray:
    noise = [] if result.noise is None else [result.noise.std]
    return np.concatenate([*(f.std for f in result.frames), *noise])


def run_problem(
    problem: Problem,
    *,
    solvers: Sequence[str],
    estimators: Sequence[EstimatorName],
    known_noise: bool,
    likelihood_all_max_n: int,
    repeats: int,
) -> list[Row]:
    """Every solver × estimator on one problem (clarabel first: it is the reference)."""
    stats_s = statistics_time(problem, known_noise=known_noise, repeats=repeats)
    ordered = ["clarabel", *(s for s in solvers if s != "clarabel")]
    reference: dict[str, CovarianceEstimate] = {}
    rows = []
    for label in ordered:
        for estimator in estimators:
            if estimator != "moment" and label != "clarabel" and problem.n > likelihood_all_max_n:
                continue
            result, total_s = estimate(problem, label, estimator, known_noise=known_noise)
            if label == "clarabel":
                reference[estimator] = result
            ref = reference[estimator]
            moment = result.moment_solution
            final = result.solution
            if estimator == "moment":
                delta = (final.objective - ref.solution.objective) / ref.solution.objective
            else:
                delta = final.objective - ref.solution.objective
            if label not in solvers:
                continue
            rot, trans = sigma_errors(problem, result)
            rows.append(
                Row(
                    n=problem.n,
                    seed=problem.seed,
                    solver=label,
                    estimator=estimator,
                    stats_s=stats_s,
                    solve_s=moment.wall_time_s + (final.wall_time_s if final is not moment else 0),
                    total_s=total_s,
                    status=final.status,
                    iterations=final.iterations,
                    moment_status=moment.status,
                    moment_iterations=moment.iterations,
                    objective=final.objective,
                    moment_objective=final.moment_objective,
                    delta_vs_clarabel=float(delta),
                    sigma_maxdiff_vs_clarabel=float(
                        np.max(np.abs(all_sigmas(result) - all_sigmas(ref)))
                    ),
                    task_error=task_error(problem, result),
                    sigma_rmse_rot_mrad=rot,
                    sigma_rmse_trans_mm=trans,
                    rank=result.identifiability.rank,
                    n_params=result.identifiability.n_params,
                )
            )
    return rows


@dataclass(frozen=True)
class Timing:
    """Timing-critical figures at one N, best of ``repeats`` (s)."""

    n: int
    default_moment_solve_s: float  # the default solver on Eq. (14) alone
    default_total_s: float  # estimate_covariances with the product defaults, no standard errors
    default_solve_s: float  # its moment solve + likelihood fit
    stats_s: float
    published_kkt_s: float
    published_kkt_status: str
    published_kkt_iterations: int


def timing(problem: Problem, *, known_noise: bool, repeats: int, published: bool) -> Timing:
    """Re-measure the README figures: default solver vs published PGD, stats + solve."""
    layout = make_layout(problem.chain.joint_names, 6, include_noise=not known_noise)
    known = problem.noise_covariance if known_noise else None
    stats = build_moment_statistics(
        problem.residuals, problem.frame_jacobians, layout, known_covariance=known
    )
    solver_name, settings = SOLVERS[DEFAULT_SOLVER]
    moment_s = min(
        solve_moment(stats, solver_name, pgd_settings=settings).wall_time_s for _ in range(repeats)
    )
    default_total, default_solve = np.inf, np.inf
    for _ in range(repeats):
        result, total = estimate(
            problem, DEFAULT_SOLVER, DEFAULT_ESTIMATOR, known_noise=known_noise
        )
        default_total = min(default_total, total)
        default_solve = min(
            default_solve, result.moment_solution.wall_time_s + result.solution.wall_time_s
        )
    status, iterations, published_s = "skipped", 0, float("nan")
    if published:
        answer = solve_moment(stats, "pgd", pgd_settings=SOLVERS["pgd-published-kkt"][1])
        status, iterations, published_s = answer.status, answer.iterations, answer.wall_time_s
    return Timing(
        problem.n,
        moment_s,
        default_total,
        default_solve,
        statistics_time(problem, known_noise=known_noise, repeats=repeats),
        published_s,
        status,
        iterations,
    )


def _median(values: Sequence[float]) -> float:
    finite = [v for v in values if np.isfinite(v)]
    return float(np.median(finite)) if finite else float("nan")


def _status(values: Sequence[str]) -> str:
    counts = Counter(values)
    if len(counts) == 1:
        return values[0]
    return ", ".join(f"{s} {c}/{len(values)}" for s, c in counts.most_common())


def table(rows: Sequence[Row]) -> str:
    """Markdown table, one line per N × solver × estimator, medians over seeds."""
    header = (
        "| N | solver | estimator | stats s | solve s | total s | status | iter | objective "
        "| Δ vs clarabel | task err | σ rot mrad | σ trans mm |"
    )
    lines = [header, "|" + "---|" * (header.count("|") - 1)]
    groups: dict[tuple[int, str, str], list[Row]] = {}
    for row in rows:
        groups.setdefault((row.n, row.solver, row.estimator), []).append(row)
    for (n, label, estimator), group in groups.items():
        delta = _median([r.delta_vs_clarabel for r in group])
        delta_text = (
            "—"
            if label == "clarabel"
            else (f"{delta:+.1e}" if estimator == "moment" else f"{delta:+.2g}")
        )
        lines.append(
            f"| {n} | {label} | {estimator} "
            f"| {_median([r.stats_s for r in group]):.3f} "
            f"| {_median([r.solve_s for r in group]):.3f} "
            f"| {_median([r.total_s for r in group]):.3f} "
            f"| {_status([r.status for r in group])} "
            f"| {_median([float(r.iterations) for r in group]):.0f} "
            f"| {_median([r.objective for r in group]):.4g} "
            f"| {delta_text} "
            f"| {100 * _median([r.task_error for r in group]):.1f} % "
            f"| {_median([r.sigma_rmse_rot_mrad for r in group]):.3f} "
            f"| {_median([r.sigma_rmse_trans_mm for r in group]):.3f} |"
        )
    return "\n".join(lines)


def timing_lines(timings: Sequence[Timing], rows: Sequence[Row]) -> list[str]:
    """The README figures: speed-up over the published PGD at the smallest N, time at the
    largest."""
    out = []
    for t in timings:
        line = (
            f"N={t.n}: statistics {t.stats_s:.3f} s; default solver {DEFAULT_SOLVER} (moment) "
            f"{t.default_moment_solve_s:.4f} s; default {DEFAULT_SOLVER}+{DEFAULT_ESTIMATOR} "
            f"solve {t.default_solve_s:.3f} s, "
            f"statistics+solve {t.stats_s + t.default_solve_s:.3f} s, whole estimate "
            f"{t.default_total_s:.3f} s"
        )
        if np.isfinite(t.published_kkt_s):
            line += (
                f"; published-settings PGD {t.published_kkt_s:.2f} s ({t.published_kkt_status}, "
                f"{t.published_kkt_iterations} iterations) = "
                f"{t.published_kkt_s / t.default_moment_solve_s:.0f}× the {DEFAULT_SOLVER} "
                f"solve, {t.published_kkt_s / t.default_solve_s:.1f}× the "
                f"{DEFAULT_SOLVER}+{DEFAULT_ESTIMATOR} solve"
            )
        out.append(line)
    literal = [r for r in rows if r.solver == "pgd-published" and r.estimator == "moment"]
    if literal:
        n_min = min(r.n for r in literal)
        at = [r for r in literal if r.n == n_min]
        out.append(
            f"N={n_min}: Table I's stopping rule taken literally stops PGD after "
            f"{_median([float(r.iterations) for r in at]):.0f} iteration(s) in "
            f"{_median([r.solve_s for r in at]):.4f} s with status "
            f"{_status([r.status for r in at])}"
        )
    return out


PAGE_ROWS: tuple[tuple[int, str, str, str], ...] = (
    (119, DEFAULT_SOLVER, DEFAULT_ESTIMATOR, ""),
    (119, "clarabel", "moment", "paper's problem"),
    (119, "nnls", "moment", ""),
    (119, "pgd-stable", "moment", "stable step 1/λmax, KKT stop"),
    (119, "pgd-published", "moment", "paper's Table I as published"),
    (119, "pgd-published-kkt", "moment", "Table I step, run to KKT"),
    (10_000, DEFAULT_SOLVER, DEFAULT_ESTIMATOR, ""),
    (10_000, "nnls", "moment", ""),
    (100_000, "nnls", "moment", ""),
    (100_000, "clarabel", DEFAULT_ESTIMATOR, ""),
)
"""The rows docs/covariance.md shows (N, solver, estimator, a note), medians over the seeds."""


def _grouped(value: float) -> str:
    """A number to the unit, thousands grouped by a space (100 000)."""
    return f"{value:,.0f}".replace(",", " ")


def _seconds(value: float) -> str:
    """Seconds to 0.1 ms below 0.01 s, to 1 ms below 1 s, else to 0.01 s."""
    return f"{value:.4f}" if value < 0.01 else f"{value:.3f}" if value < 1 else f"{value:.2f}"


def render(rows: list[results.Row]) -> str:
    """The table of ``docs/results/compare_solvers.md`` from every estimate (``asdict(Row)``):
    the :data:`PAGE_ROWS` present, medians over seeds of the solve time (:func:`_seconds`), the
    iterations, the task-score error (to 0.1 %) and the RMS σ error of the
    joint frames' rotation axes (to 0.01 mrad)."""
    table = []
    for n, label, estimator, note in PAGE_ROWS:
        group = [r for r in rows if (r["n"], r["solver"], r["estimator"]) == (n, label, estimator)]
        if not group:
            continue
        name = f"{label.split('-')[0]} + {estimator}"
        notes = [note] if note else []
        if (label, estimator) == (DEFAULT_SOLVER, DEFAULT_ESTIMATOR):
            notes.append("default")
        if n == max(r["n"] for r in rows) and label == "nnls" and estimator == "moment":
            notes.append(f"statistics {_median([r['stats_s'] for r in group]):.2f} s")
        if notes:
            name += f" ({', '.join(notes)})"
        if "default" in notes and n == min(r["n"] for r in rows):
            name = f"**{name}**"
        table.append(
            (
                _grouped(n),
                name,
                _seconds(_median([r["solve_s"] for r in group])),
                _status([r["status"] for r in group]),
                _grouped(_median([float(r["iterations"]) for r in group])),
                f"{100 * _median([r['task_error'] for r in group]):.1f} %",
                f"{_median([r['sigma_rmse_rot_mrad'] for r in group]):.2f}",
            )
        )
    return results.markdown_table(
        ("N", "solver + estimator", "solve s", "status", "iterations", "task err", "σ rot. mrad"),
        table,
    )


def timing_row(t: Timing) -> results.Row:
    """A :class:`Timing` for the results file (no published PGD: ``None`` instead of NaN)."""
    row = asdict(t)
    if not np.isfinite(t.published_kkt_s):
        row.update(published_kkt_s=None, published_kkt_status=None, published_kkt_iterations=None)
    return row


def render_timing(rows: list[results.Row]) -> str:
    """The table of ``docs/results/compare_solvers_timing.md``: best-of-``repeats`` seconds of
    the default solver and estimator at the smallest and largest N (first seed), and the
    published PGD's run to the KKT tolerance with its speed-up over the default solver."""
    table = []
    for r in rows:
        published = r["published_kkt_s"]
        table.append(
            (
                _grouped(r["n"]),
                f"{r['stats_s']:.3f}",
                f"{1e3 * r['default_moment_solve_s']:.1f}",
                f"{r['default_solve_s']:.3f}",
                f"{r['stats_s'] + r['default_solve_s']:.2f}",
                f"{r['default_total_s']:.2f}",
                "–"
                if published is None
                else f"{published:.2f} ({r['published_kkt_status']}, "
                f"{_grouped(r['published_kkt_iterations'])} iterations; "
                f"{_grouped(published / r['default_moment_solve_s'])}×)",
            )
        )
    return results.markdown_table(
        (
            "N",
            "statistics s",
            f"{DEFAULT_SOLVER} moment solve ms",
            f"{DEFAULT_SOLVER} + {DEFAULT_ESTIMATOR} solve s",
            "statistics + solve s",
            "whole estimate s (no standard errors)",
            "published PGD to KKT s (× the moment solve)",
        ),
        table,
    )


def write_csv(rows: Sequence[Row], path: Path) -> None:
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=[f.name for f in fields(Row)])
        writer.writeheader()
        for row in rows:
            writer.writerow(asdict(row))


def main(
    sizes: Sequence[int] = SIZES,
    seeds: Sequence[int] = SEEDS,
    *,
    solvers: Sequence[str] = tuple(SOLVERS),
    estimators: Sequence[EstimatorName] = ESTIMATORS,
    known_noise: bool = False,
    likelihood_all_max_n: int = 10_000,
    repeats: int = 3,
    csv_path: Path | None = None,
    echo: Callable[[str], None] = print,
    write: str | None = None,
    idle: float | None = None,
    idle_timeout_s: float = 600.0,
) -> tuple[str, list[Row], list[Timing]]:
    """Run everything; print the table and the timing lines; return them. ``write``: the
    command line to record in ``docs/results/compare_solvers{,_timing}.json`` (written with
    their tables when given). ``idle``: before each problem's estimates, wait (up to
    ``idle_timeout_s``) until the machine's CPUs are at most that fraction busy."""
    unknown = set(solvers) - set(SOLVERS)
    if unknown:
        raise SystemExit(f"unknown solvers {sorted(unknown)}; choose from {', '.join(SOLVERS)}")
    rows: list[Row] = []
    timings: list[Timing] = []
    for n in sizes:
        for seed in seeds:
            problem = simulate_problem(n, seed)
            if idle is not None:
                busy = wait_until_idle(idle, idle_timeout_s)
                if busy > idle:
                    echo(f"machine still {100 * busy:.0f} % busy after {idle_timeout_s:.0f} s")
            rows += run_problem(
                problem,
                solvers=solvers,
                estimators=estimators,
                known_noise=known_noise,
                likelihood_all_max_n=likelihood_all_max_n,
                repeats=repeats,
            )
            echo(f"N={n} seed={seed}: simulation + deterministic fit {problem.setup_s:.1f} s")
            if seed == seeds[0] and n in (min(sizes), max(sizes)):
                timings.append(
                    timing(
                        problem,
                        known_noise=known_noise,
                        repeats=repeats,
                        published=n == min(sizes) and "pgd-published-kkt" in solvers,
                    )
                )
    text = table(rows)
    echo("")
    echo(text)
    echo("")
    for line in timing_lines(timings, rows):
        echo(line)
    if csv_path is not None:
        write_csv(rows, csv_path)
        echo(f"wrote {csv_path}")
    if write is not None:
        every = [asdict(r) for r in rows]
        for path in (
            *results.write_results("compare_solvers", write, every, render),
            *results.write_results(
                "compare_solvers_timing", write, [timing_row(t) for t in timings], render_timing
            ),
        ):
            echo(f"wrote {path}")
    return text, rows, timings


def _sizes(text: str) -> list[int]:
    return [int(float(part)) for part in text.split(",") if part.strip()]


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sizes", type=_sizes, default=list(SIZES), help="e.g. 119,1e3,1e4,1e5")
    parser.add_argument("--seeds", type=_sizes, default=list(SEEDS), help="e.g. 1,2,3")
    parser.add_argument("--solvers", default=",".join(SOLVERS))
    parser.add_argument("--estimators", default=",".join(ESTIMATORS))
    parser.add_argument("--known-noise", action="store_true", help="pass the true Σ_n as known")
    parser.add_argument("--likelihood-all-max-n", type=int, default=10_000)
    parser.add_argument("--repeats", type=int, default=3, help="timing repeats (best of)")
    parser.add_argument("--csv", type=Path, default=None)
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="write docs/results/compare_solvers.{json,md} and compare_solvers_timing.{json,md}",
    )
    parser.add_argument(
        "--idle",
        type=float,
        default=None,
        help="before each problem wait (up to 10 min) until the CPUs are at most this fraction "
        "busy (e.g. 0.1)",
    )
    args = parser.parse_args()
    main(
        args.sizes,
        args.seeds,
        solvers=[s.strip() for s in args.solvers.split(",")],
        estimators=[e.strip() for e in args.estimators.split(",")],  # type: ignore[misc]
        known_noise=args.known_noise,
        likelihood_all_max_n=args.likelihood_all_max_n,
        repeats=args.repeats,
        csv_path=args.csv,
        write=" ".join(["python -m benchmarks.compare_solvers", *sys.argv[1:]])
        if args.write_results
        else None,
        idle=args.idle,
    )
