"""Deterministic calibration of geometry and compliance (paper Eq. 8–10, §V-A).

Gauss–Newton on the stacked end-effector-frame residuals with the columns of
:func:`solver.kinematics.stacked_jacobian`, after a closed-form alignment of the measurement frame
and tool offset. Columns that the data cannot identify are removed once, up front, by a
column-pivoted QR and reported by name; the same columns stay fixed through the iterations.

Every step reduces to sums over samples, so the same code serves in-memory arrays
(:func:`fit_deterministic`) and data streamed in chunks (:mod:`solver.stream`):

- the Gauss–Newton step (Eq. 10) is solved from the normal equations :class:`NormalEquations`
  (``JᵀJ``, ``Jᵀr``, ``rᵀr``), which add over chunks; :func:`gauss_newton_iteration` is the one
  iteration (step halving included), a generator that yields each point where it needs the
  normal equations — :func:`gauss_newton` feeds it from a callable, the streamed fit from
  passes over the data that several fits share;
- the pruning (:func:`identifiable_columns`) is a column-pivoted QR of an in-memory stacked
  Jacobian; the streamed fit runs it on its warm-start rows (see :mod:`solver.stream`);
- the outlier rule (§V-A) is :func:`within_spread` of a per-component :class:`ResidualSpread`,
  which also merges over chunks.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Generator
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np
import scipy.linalg
import scipy.linalg.blas
from numpy.typing import NDArray

from solver import lie
from solver.alignment import align_full_pose, align_position_only
from solver.errors import CalibrationError
from solver.kinematics import (
    ChainParameters,
    evaluate_chain,
    forward_kinematics,
    parameter_names,
    pose_residuals,
    stacked_jacobian,
)
from solver.model import KinematicChain, gravity_loads, sample_configurations

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]
Payload = TypeVar("Payload")


@dataclass(frozen=True)
class FitOptions:
    """Settings of the deterministic fit.

    ``rotation_weight_m_per_rad``: residual rotation rows are multiplied by this (paper: 1, i.e.
    1 rad counts like 1 m). ``rank_tolerance``: a column is unidentifiable when its pivoted-QR
    diagonal, relative to the largest, falls below this (columns scaled to unit norm first).
    ``free_links``: indices of the links ``L_i`` (0-based) to calibrate, None = all;
    ``(0, k)`` calibrates only the measurement frame and the tool offset.
    ``free_columns``: stacked-Jacobian columns the fit may move (:mod:`solver.selection`),
    None = all; the others keep their starting value.
    ``non_negative_compliance``: a compliance estimated negative (no spring bends against the
    torque on it, DESIGN.md §2: c ≥ 0) or not identified in any physical range is fixed at 0
    and the fit repeated (see :func:`implausible_compliance_columns`).
    """

    max_iterations: int = 50
    tolerance: float = 1e-10
    rotation_weight_m_per_rad: float = 1.0
    rank_tolerance: float = 1e-7
    free_links: tuple[int, ...] | None = None
    fit_compliance: bool = True
    free_columns: tuple[int, ...] | None = None
    non_negative_compliance: bool = True


@dataclass(frozen=True)
class DeterministicFit:
    """Result of :func:`fit_deterministic`.

    ``estimated``/``removed``: parameter names kept / dropped as unidentifiable (or not free).
    ``standard_errors``: of the estimated parameters at the solution (same order as
    ``estimated``; link entries are local twists in m and rad, compliance in rad/N·m).
    ``residuals`` (N, d) unweighted, m and rad; ``jacobian`` (N, d, p) of the estimated columns,
    weighted like the fit (rotation rows times the weight).
    """

    params: ChainParameters
    estimated: list[str]
    removed: list[str]
    standard_errors: FloatArray
    rank: int
    condition_number: float
    iterations: int
    converged: bool
    cost_history: list[float]
    residuals: FloatArray
    jacobian: FloatArray
    elapsed_s: float
    pruned: list[str] = field(default_factory=list)  # compliance fixed at 0: not physical
    notes: list[str] = field(default_factory=list)


def nominal_pose(chain: KinematicChain, joint_positions: FloatArray) -> FloatArray:
    """URDF forward kinematics base -> tip, rigid; (N, 4, 4)."""
    params = ChainParameters.nominal(chain)
    zero_loads = np.zeros((joint_positions.shape[0], len(chain.compliance_axes)))
    return forward_kinematics(chain, params, joint_positions, zero_loads)


def initial_parameters(
    chain: KinematicChain,
    joint_positions: FloatArray,
    measured_pose: FloatArray,
    *,
    position_only: bool,
) -> ChainParameters:
    """Nominal geometry; closed-form measurement frame folded into L_1, tool into L_{k+1}."""
    nominal = nominal_pose(chain, joint_positions)
    if position_only:
        world, tool = align_position_only(nominal, measured_pose[:, :3, 3])
    else:
        world, tool = align_full_pose(nominal, measured_pose)
    links = chain.nominal_links.copy()
    links[0] = world @ links[0]
    links[-1] = links[-1] @ tool
    return ChainParameters(links, np.zeros(len(chain.compliance_axes)))


def weighted(values: FloatArray, *, position_only: bool, rotation_weight: float) -> FloatArray:
    """Multiply the rotation rows (axis 1, entries 3..5) by the weight (full pose only)."""
    if position_only or rotation_weight == 1.0:
        return values
    scale = np.r_[1.0, 1.0, 1.0, rotation_weight, rotation_weight, rotation_weight]
    return values * scale.reshape((1, 6) + (1,) * (values.ndim - 2))


def fit_deterministic(
    chain: KinematicChain,
    joint_positions: FloatArray,
    measured_pose: FloatArray,
    loads_nm: FloatArray,
    *,
    position_only: bool,
    options: FitOptions = FitOptions(),
    start: ChainParameters | None = None,
) -> DeterministicFit:
    """Paper Eq. (10): iterate ``x_w = A_w^+ y_w`` and re-linearise until the cost settles.

    ``measured_pose`` (N, 4, 4) in the measurement frame (rotation ignored if position-only);
    ``loads_nm`` (N, n_axes) from :func:`solver.model.gravity_loads`.
    """
    started = time.perf_counter()
    params = start or initial_parameters(
        chain, joint_positions, measured_pose, position_only=position_only
    )
    names = parameter_names(chain)
    rows = 3 if position_only else 6

    def linearise(p: ChainParameters) -> tuple[FloatArray, FloatArray]:
        evaluation = evaluate_chain(chain, p, joint_positions, loads_nm)
        residual = pose_residuals(evaluation.pose, measured_pose, position_only=position_only)
        jacobian = stacked_jacobian(evaluation)[:, :rows]
        w = options.rotation_weight_m_per_rad
        return (
            weighted(residual, position_only=position_only, rotation_weight=w),
            weighted(jacobian, position_only=position_only, rotation_weight=w),
        )

    check_sample_count(
        chain, joint_positions.shape[0], position_only=position_only, options=options
    )
    residual, jacobian = linearise(params)
    keep, rank, condition = identifiable_columns(jacobian, chain, options)

    def evaluate(p: ChainParameters) -> tuple[NormalEquations, FloatArray]:
        r, j = linearise(p)
        kept = j[:, :, keep]
        return normal_equations(kept.reshape(-1, keep.size), r.reshape(-1)), kept

    first = normal_equations(jacobian[:, :, keep].reshape(-1, keep.size), residual.reshape(-1))
    run = gauss_newton(chain, params, keep, (first, jacobian[:, :, keep]), evaluate, options)
    pruned: list[int] = []
    while options.non_negative_compliance:
        negative = implausible_compliance_columns(
            chain, run.params, keep, parameter_standard_errors(run.normal)
        )
        if negative.size == 0:
            break
        pruned += negative.tolist()
        keep = np.setdiff1d(keep, negative)
        start_point = without_compliance(chain, run.params, negative)
        run = gauss_newton(chain, start_point, keep, evaluate(start_point), evaluate, options)
    final_residual = pose_residuals(
        forward_kinematics(chain, run.params, joint_positions, loads_nm),
        measured_pose,
        position_only=position_only,
    )
    return DeterministicFit(
        params=run.params,
        estimated=[names[i] for i in keep],
        removed=[n for n in removed_names(names, keep) if names.index(n) not in pruned],
        standard_errors=parameter_standard_errors(run.normal),
        rank=rank,
        condition_number=condition,
        iterations=run.iterations,
        converged=run.converged,
        cost_history=run.cost_history,
        residuals=final_residual,
        jacobian=run.payload,
        elapsed_s=time.perf_counter() - started,
        pruned=[names[i] for i in sorted(pruned)],
    )


PLAUSIBLE_COMPLIANCE_RAD_PER_NM = 0.01
"""A compliance whose standard error exceeds this (10 mrad per N·m; the joints of arms are
about 1e-5 to 1e-3 rad/N·m) is not identified by the data in any physical range."""


def implausible_compliance_columns(
    chain: KinematicChain,
    params: ChainParameters,
    keep: NDArray[np.intp],
    standard_errors: FloatArray,
) -> NDArray[np.intp]:
    """The compliance columns among ``keep`` (:func:`solver.kinematics.parameter_names` order,
    ``standard_errors`` aligned with ``keep``) that no physical joint could have: a negative
    value (deflecting against the gravity torque on it, which no elastic element does;
    DESIGN.md §2, ``c ≥ 0`` in rad/N·m), or a standard error above
    :data:`PLAUSIBLE_COMPLIANCE_RAD_PER_NM` (the torque on it barely varies, so the data say
    nothing about it)."""
    offset = 6 * chain.n_links
    values = params.compliance_rad_per_nm
    return np.array(
        [
            c
            for c, stderr in zip(keep, standard_errors, strict=True)
            if c >= offset
            and (values[c - offset] < 0.0 or stderr > PLAUSIBLE_COMPLIANCE_RAD_PER_NM)
        ],
        dtype=np.intp,
    )


def without_compliance(
    chain: KinematicChain, params: ChainParameters, columns: NDArray[np.intp]
) -> ChainParameters:
    """``params`` with the compliance of ``columns`` set to 0."""
    compliance = params.compliance_rad_per_nm.copy()
    compliance[np.asarray(columns) - 6 * chain.n_links] = 0.0
    return ChainParameters(params.links, compliance)


def check_sample_count(
    chain: KinematicChain, n_samples: int, *, position_only: bool, options: FitOptions
) -> None:
    """A clear error when ``n_samples`` poses give no more equations than identifiable
    parameters."""
    rows = 3 if position_only else 6
    required = identifiable_parameter_count(chain, position_only=position_only, options=options)
    if rows * n_samples <= required:
        raise CalibrationError(
            f"fewer samples than identifiable parameters: {n_samples} samples give "
            f"{rows * n_samples} equations for {required} identifiable parameters; "
            f"record at least {required // rows + 1} configurations (3x that is advisable)"
        )


def removed_names(names: list[str], keep: NDArray[np.intp]) -> list[str]:
    """Names of the columns not in ``keep``, in column order."""
    kept = set(keep.tolist())
    return [names[i] for i in range(len(names)) if i not in kept]


@functools.lru_cache(maxsize=64)
def identifiable_parameter_count(
    chain: KinematicChain, *, position_only: bool, options: FitOptions = FitOptions()
) -> int:
    """Parameters identifiable from generic data: the rank on 200 random configurations.

    Depends only on the chain and the options, so it is cached (chains are immutable).
    """
    rng = np.random.default_rng(0)
    q = sample_configurations(chain, 200, rng)
    evaluation = evaluate_chain(chain, ChainParameters.nominal(chain), q, gravity_loads(chain, q))
    jacobian = stacked_jacobian(evaluation)[:, : 3 if position_only else 6]
    return identifiable_columns(jacobian, chain, options)[1]


# --- the shared Gauss–Newton core --------------------------------------------------------------


@dataclass(frozen=True)
class NormalEquations:
    """Eq. (10) as sums over samples of the weighted, stacked system ``A x ≈ y``.

    ``gram`` AᵀA (p, p), ``cross`` Aᵀy (p,), ``cost`` yᵀy, ``n_rows`` the number of stacked
    rows (d per sample); residuals in m and (weighted) rad, columns per parameter unit (local
    twists m/rad, compliance rad/N·m). Sums of two sets of samples add (:meth:`__add__`).
    """

    gram: FloatArray
    cross: FloatArray
    cost: float
    n_rows: int

    def __add__(self, other: NormalEquations) -> NormalEquations:
        return NormalEquations(
            self.gram + other.gram,
            self.cross + other.cross,
            self.cost + other.cost,
            self.n_rows + other.n_rows,
        )


def normal_equations(design: FloatArray, target: FloatArray) -> NormalEquations:
    """Normal equations of ``design`` (m, p) and ``target`` (m,): AᵀA, Aᵀy, yᵀy, m."""
    return NormalEquations(
        _gram(design), design.T @ target, float(target @ target), int(target.shape[0])
    )


def _gram(design: FloatArray) -> FloatArray:
    """AᵀA (p, p) by BLAS ``syrk`` (one triangle: half the work of a general product) when
    ``design`` is contiguous either way, without copying it."""
    if design.shape[0] == 0:
        return np.zeros((design.shape[1],) * 2)
    if design.flags.f_contiguous:
        upper = scipy.linalg.blas.dsyrk(1.0, design, trans=1)
    elif design.flags.c_contiguous:
        upper = scipy.linalg.blas.dsyrk(1.0, design.T, trans=0)
    else:
        return np.asarray(design.T @ design, dtype=float)
    return np.asarray(np.triu(upper) + np.triu(upper, 1).T, dtype=float)


def gauss_newton_step(normal: NormalEquations) -> FloatArray:
    """``x = (AᵀA)⁻¹ Aᵀy`` (p,) with the columns scaled to unit norm first (Jacobi), so the
    solve sees the condition number of the scaled columns, squared; falls back to the
    minimum-norm least-squares solution if the scaled Gram is not positive definite."""
    norms = np.sqrt(np.clip(np.diag(normal.gram), 0.0, None))
    norms = np.where(norms > 0.0, norms, 1.0)
    scaled = normal.gram / np.outer(norms, norms)
    rhs = normal.cross / norms
    try:
        solution = scipy.linalg.solve(scaled, rhs, assume_a="pos", check_finite=False)
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        solution = np.linalg.lstsq(scaled, rhs, rcond=None)[0]
    return np.asarray(solution / norms, dtype=float)


def parameter_standard_errors(normal: NormalEquations) -> FloatArray:
    """Standard errors of the estimated parameters, ``sqrt(diag(σ² (AᵀA)⁺))`` with
    ``σ² = cost / (rows − p)`` (p,), in the units of the parameters."""
    dof = normal.n_rows - normal.gram.shape[0]
    sigma2 = normal.cost / dof
    covariance = sigma2 * np.linalg.pinv(normal.gram)
    return np.sqrt(np.clip(np.diag(covariance), 0.0, None))


@dataclass(frozen=True)
class GaussNewtonRun(Generic[Payload]):
    """Result of :func:`gauss_newton`: final parameters, the normal equations there (kept
    columns) and whatever the evaluation returned with them (``payload``)."""

    params: ChainParameters
    normal: NormalEquations
    payload: Payload
    iterations: int
    converged: bool
    cost_history: list[float]


def gauss_newton(
    chain: KinematicChain,
    start: ChainParameters,
    keep: NDArray[np.intp],
    first: tuple[NormalEquations, Payload],
    evaluate: Callable[[ChainParameters], tuple[NormalEquations, Payload]],
    options: FitOptions,
) -> GaussNewtonRun[Payload]:
    """The iteration of Eq. (10) over the columns ``keep`` (:func:`gauss_newton_iteration`)
    with the normal equations (and payload) at ``start`` given as ``first`` and
    ``evaluate(params)`` giving them at any other point — from arrays in memory or summed
    over streamed chunks."""
    iteration: Generator[
        ChainParameters, tuple[NormalEquations, Payload], GaussNewtonRun[Payload]
    ] = gauss_newton_iteration(chain, start, keep, options)
    params = next(iteration)
    answer = first
    while True:
        try:
            params = iteration.send(answer)
        except StopIteration as done:
            run: GaussNewtonRun[Payload] = done.value
            return run
        answer = evaluate(params)


def gauss_newton_iteration(
    chain: KinematicChain,
    start: ChainParameters,
    keep: NDArray[np.intp],
    options: FitOptions,
) -> Generator[ChainParameters, tuple[NormalEquations, Payload], GaussNewtonRun[Payload]]:
    """The iteration of Eq. (10) over the columns ``keep``, as a generator: it yields each
    point where it needs the normal equations (``start`` first) and is sent them (with any
    payload) back; it returns the :class:`GaussNewtonRun`.

    Step from the normal equations, halve it while the cost rises (at most 20 halvings),
    stop when the relative cost change — achieved, or predicted by the linearisation before
    the step is tried — is below ``options.tolerance``, or after ``options.max_iterations``
    steps. As a generator, several fits can share each pass over streamed data.
    """
    params = start
    normal, payload = yield start
    costs = [normal.cost]
    converged = False
    iterations = 0
    while iterations < options.max_iterations:
        step = gauss_newton_step(normal)
        # The full step lowers the linearised cost by xᵀAᵀy; below the tolerance the iterate
        # has settled and trying the step (a pass over the data when streaming) is pointless.
        if float(step @ normal.cross) <= options.tolerance * max(costs[-1], 1e-300):
            converged = True
            break
        iterations += 1
        params, normal, payload = yield from _accept_step(
            params, step, keep, (normal, payload), chain
        )
        costs.append(normal.cost)
        if abs(costs[-2] - normal.cost) <= options.tolerance * max(costs[-2], 1e-300):
            converged = True
            break
    return GaussNewtonRun(params, normal, payload, iterations, converged, costs)


def _accept_step(
    params: ChainParameters,
    step: FloatArray,
    keep: NDArray[np.intp],
    current: tuple[NormalEquations, Payload],
    chain: KinematicChain,
) -> Generator[
    ChainParameters,
    tuple[NormalEquations, Payload],
    tuple[ChainParameters, NormalEquations, Payload],
]:
    """Apply a Gauss–Newton step, shortened while the cost rises (at most 20 tries); if none
    lowers the cost, stay (the caller then sees no change and stops). Yields each trial point
    for its normal equations.

    Each shorter trial goes to the minimum of the parabola through the current cost, its
    slope along the step (``−2 xᵀAᵀy``) and the failed trial, kept within [0.1, 0.5] of the
    failed length (safeguarded backtracking): with large residuals the Gauss–Newton step can
    overshoot by orders of magnitude, and each trial is a pass over the data when streaming.
    """
    cost = current[0].cost
    slope = -2.0 * float(step @ current[0].cross)
    scale = 1.0
    for _ in range(20):
        candidate = _apply_step(params, scale * step, keep, chain)
        normal, payload = yield candidate
        if normal.cost <= cost:
            return candidate, normal, payload
        curvature = (normal.cost - cost - slope * scale) / scale**2
        best = -slope / (2.0 * curvature) if curvature > 0.0 else 0.5 * scale
        scale = float(np.clip(best, 0.1 * scale, 0.5 * scale))
    return params, *current


def _apply_step(
    params: ChainParameters, step: FloatArray, keep: NDArray[np.intp], chain: KinematicChain
) -> ChainParameters:
    full = np.zeros(6 * chain.n_links + len(chain.compliance_axes))
    full[keep] = step
    link_twists = full[: 6 * chain.n_links].reshape(chain.n_links, 6)
    updated = params.with_link_corrections(link_twists)
    return ChainParameters(updated.links, params.compliance_rad_per_nm + full[6 * chain.n_links :])


def identifiable_columns(
    jacobian: FloatArray, chain: KinematicChain, options: FitOptions
) -> tuple[NDArray[np.intp], int, float]:
    """Free columns that survive column-pivoted QR on the unit-norm-scaled stacked Jacobian.

    ``jacobian`` (N, d, P): all P columns, weighted like the fit. Returns kept column indices
    (sorted), the rank and the condition number of the kept, scaled columns.
    """
    n_link_cols = 6 * chain.n_links
    free = np.zeros(jacobian.shape[2], dtype=bool)
    links = range(chain.n_links) if options.free_links is None else options.free_links
    for i in links:
        free[6 * i : 6 * i + 6] = True
    free[n_link_cols:] = options.fit_compliance
    if options.free_columns is not None:
        free &= np.isin(np.arange(free.size), options.free_columns)
    candidates = np.flatnonzero(free)
    a = jacobian[:, :, candidates].reshape(-1, candidates.size)
    norms = np.linalg.norm(a, axis=0)
    nonzero = norms > 1e-12 * max(norms.max(), 1e-300)
    candidates, a, norms = candidates[nonzero], a[:, nonzero], norms[nonzero]
    _, upper, pivots = scipy.linalg.qr(a / norms, mode="economic", pivoting=True)
    diagonal = np.abs(np.diag(upper))
    rank = int(np.sum(diagonal > options.rank_tolerance * diagonal[0]))
    keep = np.sort(candidates[pivots[:rank]])
    singular = np.linalg.svd(
        a[:, np.isin(candidates, keep)] / norms[np.isin(candidates, keep)], compute_uv=False
    )
    return keep, rank, float(singular[0] / singular[-1])


# --- outlier rule (§V-A) ---------------------------------------------------------------------


@dataclass(frozen=True)
class ResidualSpread:
    """Per residual component (d,): count, mean and sum of squared deviations (m, rad).

    Merges over chunks exactly (Chan et al.'s pairwise update), so a streamed recording gets
    the spread of the whole recording without holding it.
    """

    n: int
    mean: FloatArray
    m2: FloatArray

    @classmethod
    def of(cls, residuals: FloatArray) -> ResidualSpread:
        """Spread of residuals (N, d)."""
        mean = residuals.mean(axis=0) if residuals.shape[0] else np.zeros(residuals.shape[1])
        return cls(int(residuals.shape[0]), mean, np.sum((residuals - mean) ** 2, axis=0))

    def __add__(self, other: ResidualSpread) -> ResidualSpread:
        n = self.n + other.n
        if n == 0:
            return self
        delta = other.mean - self.mean
        mean = self.mean + delta * (other.n / n)
        m2 = self.m2 + other.m2 + delta**2 * (self.n * other.n / n)
        return ResidualSpread(n, mean, m2)

    @property
    def std(self) -> FloatArray:
        """Population standard deviation per component (d,)."""
        return np.sqrt(self.m2 / max(self.n, 1))


def within_spread(
    residuals: FloatArray, mean: FloatArray, std: FloatArray, sigma: float
) -> BoolArray:
    """Samples (N, d) whose every component is within ``sigma`` standard deviations of its
    mean -> (N,) bool; a component without spread never rejects."""
    spread = np.where(std > 0.0, std, np.inf)
    return np.all(np.abs(residuals - mean) <= sigma * spread, axis=1)


def outlier_mask(residuals: FloatArray, sigma: float) -> BoolArray:
    """Paper §V-A: keep samples whose every residual component is within ``sigma`` standard
    deviations of that component's mean; (N, d) -> (N,) bool."""
    return within_spread(residuals, residuals.mean(axis=0), residuals.std(axis=0), sigma)


def pose_errors(
    predicted: FloatArray, measured: FloatArray, *, position_only: bool
) -> tuple[FloatArray, FloatArray | None]:
    """Per-sample translation error (mm) and rotation error (deg; None if position-only)."""
    translation_mm = 1e3 * np.linalg.norm(predicted[:, :3, 3] - measured[:, :3, 3], axis=1)
    if position_only:
        return translation_mm, None
    relative = np.swapaxes(predicted[:, :3, :3], 1, 2) @ measured[:, :3, :3]
    return translation_mm, np.degrees(lie.rotation_angle_rad(relative))
