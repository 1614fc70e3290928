"""Solvers of the PSD-constrained moment matching, paper Eq. (14): clarabel, pgd, nnls.

All take :class:`MomentStatistics`, share :func:`moment_objective` and return a
:class:`CovarianceSolution` whose Σ_f are symmetric PSD (clipped at 0) and whose objective is
evaluated on exactly the returned θ. Statuses (never "optimal_inaccurate" as plain success):

- ``optimal``: solved and the scale-free KKT residual is below ``KKT_TOLERANCE``;
- ``optimal_inaccurate``: solver reports reduced accuracy (Clarabel "AlmostSolved") or the
  KKT check fails after a solver's own success;
- ``stopped_early``: the method's own stopping rule fired (Table I's test) but the KKT check
  fails: not a solution;
- ``iteration_limit``, ``diverged``, ``error``.
"""

from __future__ import annotations

import time
import warnings
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from solver.arrays import FloatArray
from solver.covariance.layout import TRANSLATION_AXES, CovarianceLayout
from solver.covariance.objective import (
    ScaledProblem,
    clip_psd,
    moment_objective,
    moment_residual_norm,
    project_psd,
    projected_gradient_residual,
    scaled_problem,
    silent_entries,
)
from solver.covariance.polish import polish_on_face
from solver.covariance.statistics import MomentStatistics
from solver.errors import SolverError

Status = Literal[
    "optimal",
    "optimal_inaccurate",
    "one_step",
    "stopped_early",
    "iteration_limit",
    "diverged",
    "error",
]
KKT_TOLERANCE = 1e-6


@dataclass(frozen=True)
class CovarianceSolution:
    """θ (Q,), Σ_f (F, 6, 6) in m²/rad², and how the solver got there.

    ``objective`` is the value the method minimised (Eq. 14 squared for the moment solvers, the
    NLL of Eq. 17 / REML for the likelihood estimators); ``moment_objective`` is always Eq. (14)
    squared, so solutions compare exactly. ``kkt_residual``: for the moment solvers the
    scale-free projected-gradient residual of Eq. (14); for ML/REML the predicted NLL decrease
    per sample of one more scoring step.
    """

    solver: str
    status: Status
    theta: FloatArray
    frame_covariances: FloatArray
    iterations: int
    wall_time_s: float
    objective: float
    moment_objective: float
    kkt_residual: float
    message: str = ""
    history: tuple[float, ...] = field(default=(), repr=False)

    @property
    def converged(self) -> bool:
        """Optimal, or the one-step estimator the caller asked for (a large recording)."""
        return self.status in ("optimal", "one_step")


def finish_solution(
    solver: str,
    status: Status,
    theta: FloatArray,
    stats: MomentStatistics,
    problem: ScaledProblem,
    *,
    iterations: int,
    started: float,
    message: str = "",
    history: tuple[float, ...] = (),
) -> CovarianceSolution:
    """Symmetrise/clip Σ_f to PSD, recompute θ and the objective on it, check KKT."""
    layout = stats.layout
    if np.all(np.isfinite(theta)):
        covs = clip_psd(layout.frame_covariances(theta))
        theta = layout.theta_from_covariances(covs)
        value = moment_objective(theta, stats)
        kkt = projected_gradient_residual(theta, problem)
        if status == "optimal" and not kkt <= KKT_TOLERANCE:
            status = "optimal_inaccurate"
            message = (message + f" KKT residual {kkt:.2e} > {KKT_TOLERANCE:g}").strip()
    else:
        covs = np.full((layout.n_frames, 6, 6), np.nan)
        value, kkt = float("nan"), float("nan")
    return CovarianceSolution(
        solver,
        status,
        theta,
        covs,
        iterations,
        time.perf_counter() - started,
        value,
        value,
        kkt,
        message,
        history,
    )


# --- clarabel -------------------------------------------------------------------------------

_CVXPY_STATUS: dict[str, Status] = {
    "optimal": "optimal",
    "optimal_inaccurate": "optimal_inaccurate",
    "user_limit": "iteration_limit",
    "unbounded": "diverged",
    "unbounded_inaccurate": "diverged",
    "infeasible": "error",
    "infeasible_inaccurate": "error",
    "infeasible_or_unbounded": "error",
    "solver_error": "error",
}


CLARABEL_TOLERANCE = 1e-8
"""Clarabel's gap and feasibility tolerances on the equilibrated problem (its defaults). Asking
for 1e-10 made it end "AlmostSolved" on rank-deficient full-Σ problems, or fail, depending on
the CPU's BLAS kernels; optimality is certified by the scale-free KKT residual instead."""


def solve_clarabel(
    stats: MomentStatistics,
    *,
    start: FloatArray | None = None,
    max_iterations: int = 500,
    tolerance: float = CLARABEL_TOLERANCE,
) -> CovarianceSolution:
    """Eq. (14) as a second-order-cone program: min ‖Rθ̂ − b‖² over θ̂ ≥ 0 or Σ̂_f ⪰ 0.

    R is the eigen-factor of the equilibrated Gram (rank-deficient directions dropped), so the
    cone program never sees N; the answer is unscaled afterwards. An answer whose KKT residual
    is above :data:`KKT_TOLERANCE` (Clarabel "AlmostSolved", or its own success) is refined by
    accelerated projected gradient from it; when Clarabel gives no answer, projected gradient
    solves from ``start`` (a PSD θ, e.g. the scoring step's current point) or from θ = 0
    (:func:`refine`). The status says what happened: never a plain "optimal" that is not.
    """
    import cvxpy as cp

    started = time.perf_counter()
    problem = scaled_problem(stats)
    layout = stats.layout
    theta_hat = _cvxpy_variable(layout)
    objective = cp.Minimize(cp.sum_squares(problem.factor @ theta_hat - problem.target))
    # Entries without any effect are pinned at 0: an interior-point method would otherwise
    # drift along these free, unbounded directions.
    silent = np.flatnonzero(silent_entries(stats))
    program = cp.Problem(objective, [theta_hat[silent] == 0] if silent.size else [])
    settings = {
        "max_iter": max_iterations,
        "tol_gap_abs": tolerance,
        "tol_gap_rel": tolerance,
        "tol_feas": tolerance,
        "tol_ktratio": 1e-8,
    }
    try:
        with warnings.catch_warnings():  # the status is mapped below
            warnings.simplefilter("ignore", UserWarning)
            program.solve(solver=cp.CLARABEL, **settings)
    except cp.error.SolverError as exc:
        failed = finish_solution(
            "clarabel",
            "error",
            np.full(layout.n_params, np.nan),
            stats,
            problem,
            iterations=0,
            started=started,
            message=f"Clarabel failed ({exc})",
        )
        return refine(failed, stats, problem, start=start, started=started)
    status = _CVXPY_STATUS.get(str(program.status), "error")
    value = theta_hat.value
    theta = (
        problem.scaling.from_scaled(np.asarray(value, float))
        if value is not None and status in ("optimal", "optimal_inaccurate")
        else np.full(layout.n_params, np.nan)
    )
    stats_info = program.solver_stats
    iterations = int(stats_info.num_iters or 0) if stats_info is not None else 0
    solution = finish_solution(
        "clarabel",
        status,
        theta,
        stats,
        problem,
        iterations=iterations,
        started=started,
        message=f"Clarabel status {program.status}",
    )
    return refine(solution, stats, problem, start=start, started=started)


REFINE_ITERATIONS = 20_000


def refine(
    solution: CovarianceSolution,
    stats: MomentStatistics,
    problem: ScaledProblem,
    *,
    start: FloatArray | None,
    started: float,
) -> CovarianceSolution:
    """An interior-point answer made exact, or reported as not optimal.

    A finite answer is polished on the face of the PSD cone it lies on
    (:func:`~.polish.polish_on_face`: the least squares on that face, exact to rounding, kept
    when feasible and nearer to optimal), so that it no longer depends on where the interior
    point stopped. If that does not bring the KKT residual below :data:`KKT_TOLERANCE`,
    accelerated projected gradient on the equilibrated problem (:func:`solve_pgd`'s iteration:
    every iterate finite and in the cone) starts from the answer when it is finite, else from
    ``start`` or θ = 0, and is polished in turn. The status is "optimal" only when the KKT
    residual says so; the message says how the answer was reached.
    """
    polished = _polished(solution, stats, problem, started)
    if polished.status == "optimal":
        return polished
    finite = bool(np.all(np.isfinite(polished.theta)))
    origin = polished.theta if finite else start
    if finite:
        how = "refined from its answer"
    else:
        how = "solved from the given start" if start is not None else "solved from θ = 0"
    descent = solve_pgd(
        stats,
        PGDSettings(tolerance=KKT_TOLERANCE, max_iterations=REFINE_ITERATIONS),
        start=origin,
        problem=problem,
    )
    descent = replace(
        descent,
        solver=solution.solver,
        iterations=solution.iterations + descent.iterations,
        message=f"{polished.message}; {how} by {descent.iterations} projected-gradient steps",
    )
    return _polished(descent, stats, problem, started)


def _polished(
    solution: CovarianceSolution,
    stats: MomentStatistics,
    problem: ScaledProblem,
    started: float,
) -> CovarianceSolution:
    """``solution`` polished on its face when that lowers its KKT residual."""
    if not np.all(np.isfinite(solution.theta)):
        return solution
    theta, kkt = polish_on_face(solution.theta, problem)
    if not kkt < solution.kkt_residual:
        return solution
    return finish_solution(
        solution.solver,
        "optimal" if kkt <= KKT_TOLERANCE else solution.status,
        theta,
        stats,
        problem,
        iterations=solution.iterations,
        started=started,
        message=f"{solution.message}; polished on its face of the PSD cone",
    )


def _cvxpy_variable(layout: CovarianceLayout):
    """θ̂ as a cvxpy expression in its cone: θ̂ ≥ 0, or entries of PSD variables Σ̂_f ⪰ 0."""
    import cvxpy as cp
    import scipy.sparse as sp

    if layout.structure == "diag":
        return cp.Variable(layout.n_params, nonneg=True)
    parts = []
    for f in range(layout.n_frames):
        mine = np.flatnonzero(layout.param_frame == f)
        if mine.size == 0:
            continue
        axes = sorted(set(layout.param_row[mine]) | set(layout.param_col[mine]))
        pos = {a: k for k, a in enumerate(axes)}
        m = len(axes)
        sigma = cp.Variable((m, m), PSD=True)
        # θ_p = Σ̂_f[i, j]; cvxpy's vec is column-major.
        flat = [pos[layout.param_row[p]] + m * pos[layout.param_col[p]] for p in mine]
        select = sp.csr_matrix((np.ones(mine.size), (mine, flat)), shape=(layout.n_params, m * m))
        parts.append(select @ cp.vec(sigma, order="F"))
    return sum(parts[1:], parts[0])


# --- nnls -----------------------------------------------------------------------------------


def solve_nnls(stats: MomentStatistics) -> CovarianceSolution:
    """Diagonal Σ only: exact ``min ‖Rθ̂ − b‖ s.t. θ̂ ≥ 0`` (Lawson–Hanson, scipy.optimize.nnls)."""
    from scipy.optimize import nnls

    if stats.layout.structure != "diag":
        raise SolverError(
            "solver 'nnls' handles diagonal covariances only; use 'clarabel' for full"
        )
    started = time.perf_counter()
    problem = scaled_problem(stats)
    q = stats.layout.n_params
    try:
        theta_hat, _ = nnls(problem.factor, problem.target, maxiter=50 * q)
    except RuntimeError as exc:  # scipy raises when its iteration cap is hit
        nan = np.full(q, np.nan)
        return finish_solution(
            "nnls",
            "iteration_limit",
            nan,
            stats,
            problem,
            iterations=50 * q,
            started=started,
            message=str(exc),
        )
    theta = problem.scaling.from_scaled(theta_hat)
    return finish_solution("nnls", "optimal", theta, stats, problem, iterations=0, started=started)


# --- projected gradient descent (paper Eq. 15) ----------------------------------------------


@dataclass(frozen=True)
class PGDSettings:
    """Projected gradient descent of Eq. (15).

    ``step``: α in raw units (Table I: 0.0025), or "lipschitz" for 1/λmax(Ĝ) on the
    equilibrated problem. ``initial_std_*``: initial σ on every frame's diagonal (Table I:
    0.001 m, 0.0085 rad), or None for θ = 0. ``stopping``: "published" is Table I's test
    ``‖z − Bθ_{w+1}‖₂ − ‖z − Bθ_w‖₂ < tolerance`` taken literally (no absolute value: it fires at
    the first decrease); "projected_gradient" stops when the KKT residual is below tolerance.
    ``accelerate``: FISTA momentum with gradient-based adaptive restart (O'Donoghue & Candès
    2015).
    A run is "diverged" if the objective exceeds ``divergence_factor`` × its start or is not
    finite; it always ends by ``max_iterations``.
    """

    step: float | Literal["lipschitz"] = "lipschitz"
    initial_std_translation_m: float | None = None
    initial_std_rotation_rad: float | None = None
    stopping: Literal["published", "projected_gradient"] = "projected_gradient"
    tolerance: float = 1e-10
    max_iterations: int = 100_000
    accelerate: bool = True
    divergence_factor: float = 1e6


PGD_PUBLISHED = PGDSettings(
    step=0.0025,
    initial_std_translation_m=0.001,
    initial_std_rotation_rad=0.0085,
    stopping="published",
    tolerance=1e-10,
    max_iterations=100_000,
    accelerate=False,
)
PGD_STABLE = PGDSettings()


def solve_pgd(
    stats: MomentStatistics,
    settings: PGDSettings = PGD_STABLE,
    *,
    start: FloatArray | None = None,
    problem: ScaledProblem | None = None,
) -> CovarianceSolution:
    """Eq. (15): ``θ ← Proj_PSD(θ − α(Gθ − h))`` with the settings' step, start and stop rule.

    The published step works on raw θ (m², rad²); the stable one on the equilibrated θ̂. Both
    iterate in Frobenius coordinates y = m∘θ so the projection is the true Euclidean one.
    ``start``: θ (Q,) to start from instead of the settings' (projected onto the cone first);
    ``problem``: the :func:`scaled_problem` of ``stats`` when the caller has it.
    """
    started = time.perf_counter()
    problem = scaled_problem(stats) if problem is None else problem
    layout = stats.layout
    metric = layout.frobenius_weights()
    raw = settings.step != "lipschitz"
    scale = np.ones(layout.n_params) if raw else problem.scaling.param_scale
    gram = stats.gram if raw else problem.gram
    cross = stats.cross if raw else problem.cross
    # In y = m∘θ/scale coordinates: f/κ = yᵀG_y y − 2h_yᵀy + const.
    gram_y = gram / np.outer(metric, metric)
    cross_y = cross / metric
    if raw:
        alpha = float(settings.step)
    else:
        alpha = 1.0 / max(float(np.linalg.eigvalsh(gram_y)[-1]), 1e-300)
    if start is None:
        y = metric * initial_theta(layout, settings) / scale
    else:
        y = project_psd(metric * np.asarray(start, dtype=float) / scale, layout)

    def norm_of(y_now: FloatArray) -> float:
        return moment_residual_norm(scale * y_now / metric, stats)

    history = [norm_of(y)]
    start_value = max(history[0], 1e-300)
    momentum_point, t_k = y.copy(), 1.0
    status: Status = "iteration_limit"
    iterations = 0
    check_every = 1 if layout.structure == "diag" else 5
    for iterations in range(1, settings.max_iterations + 1):
        base = momentum_point if settings.accelerate else y
        y_new = project_psd(base - alpha * (gram_y @ base - cross_y), layout)
        value = norm_of(y_new)
        history.append(value)
        if not np.isfinite(value) or value > settings.divergence_factor * start_value:
            y = y_new
            status = "diverged"
            break
        if settings.accelerate:
            # Gradient restart (O'Donoghue & Candès): objective values are too noisy near the
            # optimum (c − 2hᵀθ + θᵀGθ cancels), the sign of this inner product is not.
            if float((base - y_new) @ (y_new - y)) > 0.0:
                t_k, momentum_point = 1.0, y_new.copy()
            else:
                t_next = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * t_k * t_k))
                momentum_point = y_new + ((t_k - 1.0) / t_next) * (y_new - y)
                t_k = t_next
        y = y_new
        if settings.stopping == "published":
            if history[-1] - history[-2] < settings.tolerance:
                status = "optimal"
                break
        elif iterations % check_every == 0:
            kkt = projected_gradient_residual(scale * y / metric, problem)
            if kkt <= settings.tolerance:
                status = "optimal"
                break
    theta = scale * y / metric
    solution = finish_solution(
        "pgd",
        status,
        theta,
        stats,
        problem,
        iterations=iterations,
        started=started,
        history=tuple(history),
    )
    if settings.stopping == "published" and solution.status == "optimal_inaccurate":
        message = (
            "Table I stopping rule fired (objective decreased once) but KKT residual "
            f"{solution.kkt_residual:.2e}: not converged"
        )
        solution = replace(solution, status="stopped_early", message=message)
    return solution


def initial_theta(layout: CovarianceLayout, settings: PGDSettings) -> FloatArray:
    """Table I start: σ² on every diagonal entry (translation / rotation), 0 off-diagonal."""
    theta = np.zeros(layout.n_params)
    for std, is_translation in (
        (settings.initial_std_translation_m, True),
        (settings.initial_std_rotation_rad, False),
    ):
        if std is None:
            continue
        rows = np.isin(layout.param_row, TRANSLATION_AXES) == is_translation
        theta[layout.is_variance & rows] = std**2
    return theta


def published_step_limit(stats: MomentStatistics) -> float:
    """2/λmax(G): above it, Eq. (15)'s fixed raw step α makes the unprojected iteration
    diverge (the projection turns that into a bounded oscillation). λmax grows ∝ N."""
    return 2.0 / float(np.linalg.eigvalsh(stats.gram)[-1])


ConcreteSolver = Literal["clarabel", "pgd", "nnls"]
SolverName = Literal["auto", "clarabel", "pgd", "nnls"]


def concrete_solver(solver: SolverName, structure: Literal["diag", "full"]) -> ConcreteSolver:
    """The solver "auto" stands for: the exact active-set NNLS when Σ is diagonal (PSD is then
    θ ≥ 0 and Eq. 14 is a non-negative least-squares problem), the Clarabel cone program for
    full Σ (PSD cones). Both solve Eq. (14) to the same optimum (tested); NNLS needs no
    problem compilation, which makes it ~10× faster on the paper-sized problem."""
    if solver == "auto":
        return "nnls" if structure == "diag" else "clarabel"
    return solver


def solve_moment(
    stats: MomentStatistics,
    solver: SolverName = "auto",
    *,
    pgd_settings: PGDSettings = PGD_STABLE,
    start: FloatArray | None = None,
) -> CovarianceSolution:
    """Dispatch to one of the three solvers of Eq. (14) ("auto": :func:`concrete_solver`);
    ``start``: a PSD θ for Clarabel's fallback (:func:`refine`)."""
    solver = concrete_solver(solver, stats.layout.structure)
    if solver == "clarabel":
        return solve_clarabel(stats, start=start)
    if solver == "pgd":
        return solve_pgd(stats, pgd_settings)
    if solver == "nnls":
        return solve_nnls(stats)
    raise SolverError(f"unknown solver {solver!r}; use 'auto', 'clarabel', 'pgd' or 'nnls'")
