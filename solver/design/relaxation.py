"""The convex relaxation of choosing K poses: maximise φ(M(w)) over Σw = 1, 0 ≤ w ≤ u.

u = 1/K when the poses must be distinct (every set of K distinct candidates is a feasible
point, so the optimum bounds every such set), u = 1 when repeats are allowed (the textbook
relaxation of approximate design theory). Two solvers of the same problem:

- :func:`solve_clarabel`: the conic program in cvxpy, solved by Clarabel. D, A and I as
  second-order cone programs (Sagnol 2011, *Computing optimal designs of multiresponse
  experiments reduces to second-order cone programming*; Sagnol & Harman 2015 for D): one small
  cone per candidate and parameter, about ten times faster than a p²-sized PSD cone
  (``log_det`` or a Schur complement) at 40 candidates and still faster at 200; E as
  ``lambda_min`` (a PSD cone). For up to a few hundred candidates;
- :func:`solve_first_order`: accelerated projected gradient ascent (FISTA with backtracking and
  adaptive restart; Euclidean projection onto the capped simplex) for the smooth criteria D, A,
  I; one pass over the candidates' factors per gradient, so 10⁴ candidates take seconds.

Both return a **certified bound**: for concave φ and any supergradient g at w,
``φ(w*) ≤ φ(w) + max_{v feasible} gᵀ(v − w)`` (the Frank–Wolfe gap, whose maximiser puts weight u
on the largest entries of g). The first-order method stops when that gap is below its tolerance.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import cvxpy as cp
import numpy as np

from solver.arrays import FloatArray
from solver.design.criteria import SMOOTH_CRITERIA, DesignProblem
from solver.errors import SolverError

CLARABEL_STATUS = {cp.OPTIMAL: "optimal", cp.OPTIMAL_INACCURATE: "optimal_inaccurate"}


@dataclass(frozen=True)
class Relaxation:
    """Optimal weights (N,) of the relaxation, their criterion ``value``, the certified
    ``upper_bound`` (value + Frank–Wolfe gap) on every feasible design, and how it was solved."""

    weights: FloatArray
    value: float
    upper_bound: float
    method: str
    status: str
    iterations: int
    elapsed_s: float


def project_capped_simplex(y: FloatArray, upper: float) -> FloatArray:
    """Euclidean projection of y (N,) onto {w: Σw = 1, 0 ≤ w ≤ upper} (needs N·upper ≥ 1):
    ``w = clip(y − τ, 0, upper)`` with τ found by bisection on the monotone mass."""
    low, high = float(np.min(y)) - upper, float(np.max(y))
    for _ in range(100):
        tau = 0.5 * (low + high)
        if np.clip(y - tau, 0.0, upper).sum() > 1.0:
            low = tau
        else:
            high = tau
        if high - low <= 1e-16 * max(1.0, abs(tau)):
            break
    w = np.clip(y - 0.5 * (low + high), 0.0, upper)
    return np.asarray(w / w.sum(), dtype=float)


def frank_wolfe_vertex(gradient: FloatArray, upper: float) -> FloatArray:
    """The feasible point maximising gᵀv: weight ``upper`` on the largest entries of g."""
    order = np.argsort(-gradient, kind="stable")
    v = np.zeros_like(gradient)
    full = int(np.floor(1.0 / upper + 1e-12))
    v[order[:full]] = upper
    rest = 1.0 - full * upper
    if rest > 1e-15 and full < gradient.size:
        v[order[full]] = rest
    return v


def frank_wolfe_gap(gradient: FloatArray, weights: FloatArray, upper: float) -> float:
    """``max_v gᵀ(v − w)`` ≥ φ(w*) − φ(w) for concave φ."""
    return float(gradient @ (frank_wolfe_vertex(gradient, upper) - weights))


def solve_first_order(
    problem: DesignProblem,
    *,
    gap_tolerance: float = 1e-7,
    max_iterations: int = 5000,
    start: FloatArray | None = None,
) -> Relaxation:
    """FISTA on the capped simplex for the smooth criteria, until the certified gap is below
    ``gap_tolerance``: absolute for D (a log: relative in the geometric-mean eigenvalue),
    relative to the criterion's size for A and I (variances, of any units)."""
    if problem.criterion not in SMOOTH_CRITERIA:
        raise SolverError(
            f"criterion {problem.criterion} is not differentiable; the first-order method "
            f"handles {', '.join(SMOOTH_CRITERIA)} (use the Clarabel relaxation for E)"
        )
    started = time.perf_counter()
    upper = problem.upper_weight
    n = problem.n_candidates
    w = np.full(n, 1.0 / n) if start is None else project_capped_simplex(start, upper)
    value, gradient = problem.value_and_gradient(w)
    if not np.isfinite(value):
        raise SolverError(
            "the candidates together do not determine the parameters (singular information); "
            "add candidates or widen the working volume"
        )
    y, y_value, y_gradient = w, value, gradient
    momentum = 1.0
    step = 1.0 / max(float(np.max(np.abs(gradient))) * n, 1e-300)
    gap = frank_wolfe_gap(gradient, w, upper)
    tolerance = gap_tolerance * (1.0 if problem.criterion == "D" else abs(value))
    iterations = 0
    while gap > tolerance and iterations < max_iterations:
        iterations += 1
        while True:
            candidate = project_capped_simplex(y + step * y_gradient, upper)
            c_value, c_gradient = problem.value_and_gradient(candidate)
            delta = candidate - y
            model = y_value + y_gradient @ delta - (delta @ delta) / (2.0 * step)
            if np.isfinite(c_value) and c_value >= model - 1e-15 * abs(model):
                break
            step *= 0.5
            if step < 1e-300:
                raise SolverError("first-order design: step size underflow")
        if c_value < value:  # adaptive restart: momentum went uphill of the objective
            momentum = 1.0
            y, y_value, y_gradient = w, value, gradient
            continue
        next_momentum = 0.5 * (1.0 + np.sqrt(1.0 + 4.0 * momentum**2))
        y = candidate + ((momentum - 1.0) / next_momentum) * (candidate - w)
        y = project_capped_simplex(y, upper)
        momentum = next_momentum
        w, value, gradient = candidate, c_value, c_gradient
        y_value, y_gradient = problem.value_and_gradient(y)
        if not np.isfinite(y_value):
            y, y_value, y_gradient, momentum = w, value, gradient, 1.0
        gap = frank_wolfe_gap(gradient, w, upper)
        step *= 1.25
    status = "optimal" if gap <= tolerance else "max_iterations"
    return Relaxation(
        w,
        value,
        value + max(gap, 0.0),
        "first_order",
        status,
        iterations,
        time.perf_counter() - started,
    )


def _information_expression(problem: DesignProblem, weights: cp.Variable, b: int) -> cp.Expression:
    """``P + K Σ w_n M_n`` (p+e, p+e) as an affine matrix expression (for E's ``lambda_min``
    and the nuisance parameters' Schur complement)."""
    block = problem.blocks[b]
    p = block.columns
    matrices = np.einsum("nri,nrj->nij", block.factors, block.factors)
    matrices = 0.5 * (matrices + matrices.transpose(0, 2, 1))
    flat = matrices.reshape(block.n_candidates, p * p)
    summed = cp.reshape(problem.count * (flat.T @ weights), (p, p), order="C")
    return 0.5 * (summed + summed.T) + block.prior


def prior_root(prior: FloatArray) -> FloatArray:
    """B (p, k) with ``B Bᵀ = P`` over P's positive eigenvalues (k = 0 for no prior)."""
    eigval, eigvec = np.linalg.eigh(0.5 * (prior + prior.T))
    keep = eigval > 1e-12 * max(float(eigval[-1]), 1e-300)
    return np.asarray(eigvec[:, keep] * np.sqrt(eigval[keep]), dtype=float)


def _rotated_cones(
    z: cp.Expression, bound: cp.Expression, weight: cp.Expression | FloatArray
) -> cp.Constraint:
    """``‖z_m‖² ≤ bound_m · weight_m`` for every column m of z (rows, M), as second-order cones
    ``‖[2 z_m; bound_m − weight_m]‖ ≤ bound_m + weight_m``."""
    gap = cp.reshape(bound - weight, (1, z.shape[1]), order="F")
    return cp.SOC(bound + weight, cp.vstack([2 * z, gap]), axis=0)


def _socp_term(
    problem: DesignProblem, weights: cp.Variable, b: int
) -> tuple[cp.Expression, list[cp.Constraint]]:
    """One block's criterion as a second-order cone program in the weights (Sagnol 2011 for A
    and I, Sagnol & Harman 2015 for D), with information ``M = Σ_n A_n A_nᵀ w_n + B Bᵀ``,
    ``A_n = √K F_nᵀ`` (p, r), B the prior's root (p, k):

    - A, I: ``tr(Rᵀ M⁻¹ R) = min Σ_n ‖Z_n‖²_F / w_n + ‖Z_0‖²_F`` over ``Σ_n A_n Z_n + B Z_0 = R``
      (R = I for A, the task root for I);
    - D: ``(det M)^{1/p} = max Π_j G_jj^{1/p}`` over G = ``Σ_n A_n Z_n + B Z_0`` lower
      triangular with ``Σ_n ‖Z_n e_j‖² / w_n + ‖Z_0 e_j‖² ≤ G_jj``.

    Returns the criterion (``log det M / p``; ``−tr(M⁻¹)/p``; ``−tr(Rᵀ M⁻¹ R)``) as an
    expression and its constraints: one cone of size r + 2 per candidate and column, so the
    cost grows with the candidates, never with a p² PSD cone."""
    block = problem.blocks[b]
    n, r, p = block.factors.shape
    if problem.criterion == "A":
        target: FloatArray | None = np.eye(p)
    elif problem.criterion == "I":
        target = problem.task_root
    else:
        target = None
    columns = p if target is None else target.shape[1]
    stacked = np.sqrt(problem.count) * block.factors.reshape(n * r, p)  # rows of every A_nᵀ
    z = cp.Variable((n * r, columns))
    bound = cp.Variable(n * columns)  # bound[n + N j] ≥ ‖Z_n e_j‖² / w_n
    # Column n + N·j of the Fortran reshape is Z_n e_j.
    per_column = cp.reshape(z, (r, n * columns), order="F")
    constraints = [_rotated_cones(per_column, bound, cp.hstack([weights] * columns))]
    combined = stacked.T @ z
    spent = cp.sum(cp.reshape(bound, (n, columns), order="F"), axis=0)
    root = prior_root(block.prior)
    if root.shape[1]:
        z0 = cp.Variable((root.shape[1], columns))
        bound0 = cp.Variable(columns)
        constraints.append(_rotated_cones(z0, bound0, np.ones(columns)))
        combined = combined + root @ z0
        spent = spent + bound0
    if target is None:
        constraints += [cp.upper_tri(combined) == 0, spent <= cp.diag(combined)]
        return cp.sum(cp.log(cp.diag(combined))) / p, constraints
    constraints.append(combined == target)
    return -cp.sum(spent) / (p if problem.criterion == "A" else 1), constraints


def _profiled_term(
    problem: DesignProblem, weights: cp.Variable, b: int
) -> tuple[cp.Expression, list[cp.Constraint]]:
    """A block with nuisance parameters: the criterion of X (p, p) subject to the LMI
    ``[[M_pp(w) − X, M_pe(w)], [M_ep(w), M_ee(w)]] ⪰ 0``, which holds exactly when X is below
    the Schur complement ``M_pp − M_pe M_ee⁻¹ M_ep`` (Boyd & Vandenberghe §A.5.5), so the
    maximum over X is the criterion of the profiled information (a p×p PSD cone per block)."""
    block = problem.blocks[b]
    p, e = block.dimension, block.nuisance
    full = _information_expression(problem, weights, b)
    x = cp.Variable((p, p), symmetric=True)
    lifted = cp.bmat([[x, np.zeros((p, e))], [np.zeros((e, p)), np.zeros((e, e))]])
    constraints = [full - lifted >> 0]
    if problem.criterion == "D":
        return cp.log_det(x) / p, constraints
    if problem.criterion == "E":
        return cp.lambda_min(x), constraints
    root = np.eye(p) if problem.criterion == "A" else problem.task_root
    assert root is not None
    # tr(Rᵀ X⁻¹ R) = Σ_j matrix_frac(R e_j, X)
    spent = cp.sum([cp.matrix_frac(root[:, j], x) for j in range(root.shape[1])])
    return -spent / (p if problem.criterion == "A" else 1), constraints


def solve_clarabel(problem: DesignProblem) -> Relaxation:
    """The relaxation as a conic program in cvxpy, solved by Clarabel."""
    started = time.perf_counter()
    n = problem.n_candidates
    w = cp.Variable(n, nonneg=True)
    terms, constraints = [], [cp.sum(w) == 1]
    for b in range(len(problem.blocks)):
        if problem.blocks[b].nuisance:
            term, lmi = _profiled_term(problem, w, b)
            terms.append(term)
            constraints += lmi
        elif problem.criterion == "E":
            terms.append(cp.lambda_min(_information_expression(problem, w, b)))
        else:
            term, cones = _socp_term(problem, w, b)
            terms.append(term)
            constraints += cones
    if problem.upper_weight < 1.0:
        constraints.append(w <= problem.upper_weight)
    program = cp.Problem(cp.Maximize(cp.sum(terms) if len(terms) > 1 else terms[0]), constraints)
    try:
        program.solve(solver=cp.CLARABEL)
    except cp.SolverError as exc:
        raise SolverError(f"Clarabel could not solve the design relaxation: {exc}") from exc
    status = CLARABEL_STATUS.get(program.status)
    if status is None or w.value is None:
        raise SolverError(f"Clarabel: design relaxation {program.status}")
    weights = project_capped_simplex(np.asarray(w.value, dtype=float), problem.upper_weight)
    value, gradient = problem.value_and_gradient(weights)
    if not np.isfinite(value):
        raise SolverError(
            "the candidates together do not determine the parameters (singular information); "
            "add candidates or widen the working volume"
        )
    bound = value + max(frank_wolfe_gap(gradient, weights, problem.upper_weight), 0.0)
    if problem.criterion == "E":
        # One supergradient of λ_min gives a loose gap at a multiple eigenvalue; Clarabel's
        # objective is within its duality-gap tolerance (1e-8 relative) of the optimum.
        bound = min(bound, max(value, float(program.value)) * (1.0 + 1e-7) + 1e-12)
    iterations = int(program.solver_stats.num_iters or 0)
    return Relaxation(
        weights,
        value,
        bound,
        "clarabel",
        status,
        iterations,
        time.perf_counter() - started,
    )
