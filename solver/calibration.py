"""Deterministic calibration of geometry and compliance (paper Eq. 8–10, §V-A).

Gauss–Newton on the stacked end-effector-frame residuals with the columns of
:func:`solver.kinematics.stacked_jacobian`, after a closed-form alignment of the measurement frame
and tool offset. Columns that the data cannot identify are removed once, up front, by a
column-pivoted QR and reported by name; the same columns stay fixed through the iterations.

Every step reduces to sums over samples, so the same code serves in-memory arrays
(:func:`solver.measurement.fit.fit_measurement`, for poses
:func:`solver.measurement.pose.fit_deterministic`) and data streamed in chunks
(:mod:`solver.stream`):

- the (damped) Gauss–Newton step (Eq. 10) is solved from the normal equations
  :class:`NormalEquations` (``JᵀJ``, ``Jᵀr``, ``rᵀr``), which add over chunks;
  :func:`levenberg_marquardt_iteration` is the one iteration, a generator that yields each
  point where it needs the normal equations — :func:`levenberg_marquardt` feeds it from a
  callable, the streamed fit from passes over the data that several fits share;
- the pruning (:func:`identifiable_columns`) is a column-pivoted QR of an in-memory stacked
  Jacobian; the streamed fit runs it on its warm-start rows (see :mod:`solver.stream`);
- the outlier rule (§V-A) is :func:`within_spread` of a per-component :class:`ResidualSpread`,
  which also merges over chunks.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, field
from typing import Generic, TypeVar

import numpy as np
import scipy.linalg
import scipy.linalg.blas
from numpy.typing import NDArray

from solver import lie
from solver.arrays import BoolArray, FloatArray
from solver.errors import CalibrationError
from solver.kinematics import (
    ChainParameters,
    evaluate_chain,
    stacked_jacobian,
)
from solver.model import KinematicChain, gravity_loads, sample_configurations
from solver.pivoting import tiered_pivoted_qr

Payload = TypeVar("Payload")
Start = TypeVar("Start")
StepRule = Callable[[ChainParameters, FloatArray, NDArray[np.intp]], ChainParameters]
"""``apply(params, step, keep)``: how a (damped) Gauss–Newton step over the columns ``keep``
moves the parameters."""


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
    torque on it, DESIGN.md §2: c ≥ 0) or not identified in any physical range is fixed at 0,
    an inner link's twist component not identified in any physical range at its nominal value,
    and the fit repeated (see :func:`implausible_columns`).
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
    """Result of :func:`solver.measurement.pose.fit_deterministic`.

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


def weighted(values: FloatArray, *, dim: int, rotation_weight: float) -> FloatArray:
    """Multiply the rotation rows (axis 1, entries 3..5) by the weight; ``dim`` rows per
    sample (6: a full pose, 3: a position, which has no rotation rows)."""
    if dim == 3 or rotation_weight == 1.0:
        return values
    scale = np.r_[1.0, 1.0, 1.0, rotation_weight, rotation_weight, rotation_weight]
    return values * scale.reshape((1, 6) + (1,) * (values.ndim - 2))


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


PLAUSIBLE_LINK_ROTATION_RAD = 0.1
"""A rotation component of an inner link's correction whose standard error exceeds this (5.7°;
a URDF's joint frames are off by milliradians) is not identified in any physical range."""

PLAUSIBLE_LINK_TRANSLATION_M = 0.05
"""Likewise a translation component whose standard error exceeds 5 cm."""


def implausible_columns(
    chain: KinematicChain,
    params: ChainParameters,
    keep: NDArray[np.intp],
    standard_errors: FloatArray,
) -> NDArray[np.intp]:
    """The columns among ``keep`` (``standard_errors`` aligned with ``keep``) that the data do
    not determine in any physical range: the compliances of
    :func:`implausible_compliance_columns`, and the twist components of the inner links
    ``L_2 … L_k`` (not ``L_1``, which carries the measurement frame, nor ``L_{k+1}``, the
    tool: both may be anywhere) whose standard error exceeds
    :data:`PLAUSIBLE_LINK_TRANSLATION_M` (tx, ty, tz) or :data:`PLAUSIBLE_LINK_ROTATION_RAD`
    (rx, ry, rz). Such a component only follows a direction of the cost the data barely see
    (e.g. a wrist whose joints hardly move: the link frame drifts by radians along a flat,
    curved valley and no iteration limit is enough)."""
    links = [
        c
        for c, stderr in zip(keep, standard_errors, strict=True)
        if 6 <= c < 6 * (chain.n_links - 1)
        and stderr > (PLAUSIBLE_LINK_TRANSLATION_M if c % 6 < 3 else PLAUSIBLE_LINK_ROTATION_RAD)
    ]
    compliance = implausible_compliance_columns(chain, params, keep, standard_errors)
    return np.array(sorted([*links, *compliance.tolist()]), dtype=np.intp)


def implausible_link_columns(
    chain: KinematicChain,
    params: ChainParameters,
    keep: NDArray[np.intp],
    standard_errors: FloatArray,
) -> NDArray[np.intp]:
    """The inner-link twist columns of :func:`implausible_columns` (no compliance: whether a
    compliance is physical is decided on the whole recording, not on a subset of it)."""
    columns = implausible_columns(chain, params, keep, standard_errors)
    return columns[columns < 6 * chain.n_links]


def without_columns(
    chain: KinematicChain,
    params: ChainParameters,
    columns: NDArray[np.intp],
    *,
    at_optimum: tuple[NDArray[np.intp], NormalEquations] | None = None,
    apply: StepRule | None = None,
) -> ChainParameters:
    """Where a fit at ``params`` restarts with the parameters of ``columns`` fixed at their
    nominal value (a compliance at 0; a link twist component at 0 in the link's total
    correction ``ξ = Log(L_nominal⁻¹ L)``, ``L = L_nominal Exp(ξ)``, ξ (6,) [v; w] in m and
    rad), the other parameters kept as they are.

    When only compliances are fixed and ``params`` is a converged fit, ``at_optimum`` (its
    kept columns and the normal equations there) gives a better restart: the Gauss–Newton
    step of Eq. (10) from the linearisation at ``params`` with the fixed components of the
    step at minus their value and the other kept columns solved given that change,
    ``x_f = (A_fᵀA_f)⁻¹ (A_fᵀy − A_fᵀA_c x_c)`` — the refit then starts next to its optimum
    (its first evaluation usually confirms it) rather than a step away. ``apply``: how a
    step moves the parameters (default: the chain's; a measurement model's carries its own
    unknowns in the columns after the chain's)."""
    columns = np.asarray(columns, dtype=np.intp)
    offset = 6 * chain.n_links
    link_columns = columns[columns < offset]
    if at_optimum is not None and link_columns.size == 0:
        keep, normal = at_optimum
        fixed = np.isin(keep, columns)
        change = -params.compliance_rad_per_nm[keep[fixed] - offset]
        free = ~fixed
        reduced = NormalEquations(
            normal.gram[np.ix_(free, free)],
            normal.cross[free] - normal.gram[np.ix_(free, fixed)] @ change,
            normal.cost,
            normal.n_rows,
        )
        step = np.zeros(keep.size)
        step[fixed] = change  # the compliance lands on exactly 0: c + (−c)
        step[free] = damped_step(reduced, 0.0)
        return (
            _apply_step(params, step, keep, chain) if apply is None else apply(params, step, keep)
        )
    compliance = params.compliance_rad_per_nm.copy()
    compliance[columns[columns >= offset] - offset] = 0.0
    links = params.links.copy()
    for link in np.unique(link_columns // 6):
        correction = lie.se3_log(lie.inverse(chain.nominal_links[link]) @ links[link])
        correction[link_columns[link_columns // 6 == link] % 6] = 0.0
        links[link] = chain.nominal_links[link] @ lie.se3_exp(correction)
    return dataclasses.replace(params, links=links, compliance_rad_per_nm=compliance)


def lower_cost_restart(
    restart: Start,
    fresh: Start,
    evaluate: Callable[[Sequence[Start]], Sequence[tuple[NormalEquations, Payload]]],
) -> tuple[Start, tuple[NormalEquations, Payload]]:
    """Where a fit restarts once implausible columns are fixed (:func:`implausible_columns`),
    with its normal equations there: at its last iterate with them reset (``restart``, from
    :func:`without_columns`), or at its start with every column fixed so far reset
    (``fresh``), whichever has the lower cost (a tie: ``restart``). ``evaluate`` gives the
    normal equations (and payload) at both — in memory one after the other, streamed in one
    pass over the data.

    A fit whose link columns are implausible has moved along a flat valley of the cost, its
    other parameters with those; resetting only those can land far up the valley's side (on a
    two-socket recording 400× the cost, and the refit then stays in a minimum 90× above the
    optimum), while the start never followed the drift."""
    at_restart, at_fresh = evaluate([restart, fresh])
    return (fresh, at_fresh) if at_fresh[0].cost < at_restart[0].cost else (restart, at_restart)


def check_sample_count(
    chain: KinematicChain, n_samples: int, *, dim: int, options: FitOptions
) -> None:
    """A clear error when ``n_samples`` poses of ``dim`` residual rows each (the measurement
    model's :attr:`~solver.measurement.MeasurementModel.dim`, 6 or 3) give no more equations
    than identifiable parameters."""
    required = identifiable_parameter_count(chain, dim=dim, options=options)
    if dim * n_samples <= required:
        raise CalibrationError(
            f"fewer samples than identifiable parameters: {n_samples} samples give "
            f"{dim * n_samples} equations for {required} identifiable parameters; "
            f"record at least {required // dim + 1} configurations (3x that is advisable)"
        )


def removed_names(names: list[str], keep: NDArray[np.intp]) -> list[str]:
    """Names of the columns not in ``keep``, in column order."""
    kept = set(keep.tolist())
    return [names[i] for i in range(len(names)) if i not in kept]


@functools.lru_cache(maxsize=64)
def identifiable_parameter_count(
    chain: KinematicChain, *, dim: int, options: FitOptions = FitOptions()
) -> int:
    """Parameters identifiable from generic data: the rank on 200 random configurations of
    the first ``dim`` rows of Eq. (9) (6: a full pose, 3: a position).

    Depends only on the chain and the options, so it is cached (chains are immutable).
    """
    rng = np.random.default_rng(0)
    q = sample_configurations(chain, 200, rng)
    evaluation = evaluate_chain(chain, ChainParameters.nominal(chain), q, gravity_loads(chain, q))
    jacobian = stacked_jacobian(evaluation)[:, :dim]
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


def damped_step(normal: NormalEquations, damping: float) -> FloatArray:
    """The Levenberg–Marquardt step of Eq. (10) (Marquardt 1963), (p,):

        (AᵀA + λ diag(AᵀA)) x = Aᵀy,

    solved with the columns scaled to unit norm (Jacobi, ``D = diag(AᵀA)``): ``(S + λ I) z =
    D^{-1/2} Aᵀy``, ``x = D^{-1/2} z`` with ``S = D^{-1/2} AᵀA D^{-1/2}``, so λ (``damping``,
    dimensionless) is relative to each column's own scale. ``damping`` 0 is the Gauss–Newton
    step ``x = (AᵀA)⁻¹ Aᵀy``; a larger λ shortens the step and turns it towards the gradient
    ``Aᵀy``. Falls back to the minimum-norm least-squares solution if ``S + λ I`` is not
    positive definite."""
    norms = np.sqrt(np.clip(np.diag(normal.gram), 0.0, None))
    norms = np.where(norms > 0.0, norms, 1.0)
    scaled = normal.gram / np.outer(norms, norms) + damping * np.eye(norms.size)
    rhs = normal.cross / norms
    try:
        solution = scipy.linalg.solve(scaled, rhs, assume_a="pos", check_finite=False)
    except (np.linalg.LinAlgError, scipy.linalg.LinAlgError):
        solution = np.linalg.lstsq(scaled, rhs, rcond=None)[0]
    return np.asarray(solution / norms, dtype=float)


def predicted_decrease(normal: NormalEquations, step: FloatArray) -> float:
    """Decrease of the linearised cost ``‖y − A x‖²`` by the step x: ``2 xᵀAᵀy − xᵀAᵀA x``
    (m², with the rows weighted like the fit)."""
    return float(2.0 * step @ normal.cross - step @ normal.gram @ step)


def parameter_standard_errors(normal: NormalEquations) -> FloatArray:
    """Standard errors of the estimated parameters, ``sqrt(diag(σ² (AᵀA)⁺))`` with
    ``σ² = cost / (rows − p)`` (p,), in the units of the parameters."""
    dof = normal.n_rows - normal.gram.shape[0]
    sigma2 = normal.cost / dof
    covariance = sigma2 * np.linalg.pinv(normal.gram)
    return np.sqrt(np.clip(np.diag(covariance), 0.0, None))


@dataclass(frozen=True)
class LeastSquaresRun(Generic[Payload]):
    """Result of :func:`levenberg_marquardt`: final parameters, the normal equations there (kept
    columns) and whatever the evaluation returned with them (``payload``); ``iterations``:
    accepted steps; ``trials``: points evaluated after the start (each a pass over the data
    when streaming)."""

    params: ChainParameters
    normal: NormalEquations
    payload: Payload
    iterations: int
    converged: bool
    cost_history: list[float]
    trials: int = 0


def levenberg_marquardt(
    chain: KinematicChain,
    start: ChainParameters,
    keep: NDArray[np.intp],
    first: tuple[NormalEquations, Payload],
    evaluate: Callable[[ChainParameters], tuple[NormalEquations, Payload]],
    options: FitOptions,
    apply: StepRule | None = None,
) -> LeastSquaresRun[Payload]:
    """The damped iteration of Eq. (10) over the columns ``keep``
    (:func:`levenberg_marquardt_iteration`) with the normal equations (and payload) at
    ``start`` given as ``first`` and ``evaluate(params)`` giving them at any other point —
    from arrays in memory or summed over streamed chunks. ``apply``: how a step moves the
    parameters (default: the chain's local link corrections and compliances); a measurement
    model with unknowns of its own (:mod:`solver.measurement`) passes its own."""
    iteration: Generator[
        ChainParameters, tuple[NormalEquations, Payload], LeastSquaresRun[Payload]
    ] = levenberg_marquardt_iteration(chain, start, keep, options, apply)
    params = next(iteration)
    answer = first
    while True:
        try:
            params = iteration.send(answer)
        except StopIteration as done:
            run: LeastSquaresRun[Payload] = done.value
            return run
        answer = evaluate(params)


FIRST_DAMPING = 1e-3
"""λ of :func:`damped_step` after the first step that raised the cost (relative to the unit
diagonal of the scaled normal matrix); before that the steps are Gauss–Newton's (λ = 0)."""

MAX_TRIALS = 30
"""Trial points per iteration at most; if none lowers the cost the iterate stays (and the
iteration stops)."""


def levenberg_marquardt_iteration(
    chain: KinematicChain,
    start: ChainParameters,
    keep: NDArray[np.intp],
    options: FitOptions,
    apply: StepRule | None = None,
) -> Generator[ChainParameters, tuple[NormalEquations, Payload], LeastSquaresRun[Payload]]:
    """Levenberg–Marquardt on Eq. (10) over the columns ``keep``, as a generator: it yields
    each point where it needs the normal equations (``start`` first) and is sent them (with
    any payload) back; it returns the :class:`LeastSquaresRun`. As a generator, several fits
    can share each pass over streamed data.

    Each iteration tries ``θ ⊕ x(λ)`` with ``x(λ)`` :func:`damped_step`; the gain ratio
    ``ρ = (cost − cost_new) / (2xᵀAᵀy − xᵀAᵀAx)`` (achieved over predicted decrease) sets λ
    (Nielsen 1999): a trial that lowers the cost is accepted and λ ← λ·max(1/3, 1 − (2ρ − 1)³);
    one that raises it is rejected and λ ← max(ν λ, :data:`FIRST_DAMPING`), ν doubling per
    rejection (ν = 2 after an acceptance). λ starts at 0: where Gauss–Newton's full steps lower
    the cost the iterates are exactly Gauss–Newton's. Near-singular directions (a long, flat
    valley) no longer force ever shorter steps along the Gauss–Newton direction: the damped
    step turns towards the gradient there.

    Stops when the relative cost change — achieved, or predicted for the undamped step
    (``xᵀAᵀy`` of the Gauss–Newton step, zero only at a stationary point) before it is tried —
    is below ``options.tolerance``, or after ``options.max_iterations`` accepted steps.
    """
    params = start
    normal, payload = yield start
    costs = [normal.cost]
    converged = False
    iterations = trials = 0
    damping = 0.0
    while iterations < options.max_iterations:
        # The full step lowers the linearised cost by xᵀAᵀy; below the tolerance the iterate
        # has settled and trying a step (a pass over the data when streaming) is pointless.
        if float(damped_step(normal, 0.0) @ normal.cross) <= options.tolerance * max(
            costs[-1], 1e-300
        ):
            converged = True
            break
        iterations += 1
        params, normal, payload, damping, tried = yield from _damped_trials(
            params, (normal, payload), damping, keep, chain, apply
        )
        trials += tried
        costs.append(normal.cost)
        if abs(costs[-2] - normal.cost) <= options.tolerance * max(costs[-2], 1e-300):
            converged = True
            break
    return LeastSquaresRun(params, normal, payload, iterations, converged, costs, trials)


def _damped_trials(
    params: ChainParameters,
    current: tuple[NormalEquations, Payload],
    damping: float,
    keep: NDArray[np.intp],
    chain: KinematicChain,
    apply: StepRule | None = None,
) -> Generator[
    ChainParameters,
    tuple[NormalEquations, Payload],
    tuple[ChainParameters, NormalEquations, Payload, float, int],
]:
    """One Levenberg–Marquardt iteration: damped steps (:func:`damped_step`) from ``params``
    until one lowers the cost, λ updated by the gain ratio as
    :func:`levenberg_marquardt_iteration` says. Yields each trial point for its normal
    equations; returns the accepted point, its normal equations and payload, the next λ and
    the number of trials (the current point and its λ if none of :data:`MAX_TRIALS` lowered
    the cost)."""
    normal = current[0]
    growth = 2.0
    for trial in range(1, MAX_TRIALS + 1):
        step = damped_step(normal, damping)
        candidate = (
            _apply_step(params, step, keep, chain) if apply is None else apply(params, step, keep)
        )
        new_normal, new_payload = yield candidate
        if new_normal.cost <= normal.cost:
            predicted = predicted_decrease(normal, step)
            ratio = (normal.cost - new_normal.cost) / predicted if predicted > 0.0 else 0.0
            damping *= max(1.0 / 3.0, 1.0 - (2.0 * ratio - 1.0) ** 3)
            return candidate, new_normal, new_payload, damping, trial
        damping = max(growth * damping, FIRST_DAMPING)
        growth *= 2.0
    return params, *current, damping, MAX_TRIALS


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
    free = free_columns(chain, options, jacobian.shape[2])
    first = frame_columns(chain, jacobian.shape[2])
    return pivoted_columns(
        jacobian.reshape(-1, jacobian.shape[2]), free, options.rank_tolerance, first
    )


def free_columns(chain: KinematicChain, options: FitOptions, n_columns: int) -> BoolArray:
    """The chain columns ``options`` lets the fit move (n_columns,): the links of
    ``free_links`` (all if None) and, with ``fit_compliance``, the compliances; columns beyond
    the chain's (a measurement model's own unknowns) are free."""
    n_link_cols = 6 * chain.n_links
    free = np.zeros(n_columns, dtype=bool)
    links = range(chain.n_links) if options.free_links is None else options.free_links
    for i in links:
        free[6 * i : 6 * i + 6] = True
    free[n_link_cols : n_link_cols + len(chain.compliance_axes)] = options.fit_compliance
    if options.free_columns is not None:  # a selection names chain columns only
        n_chain = n_link_cols + len(chain.compliance_axes)
        free[:n_chain] &= np.isin(np.arange(n_chain), options.free_columns)
    free[n_link_cols + len(chain.compliance_axes) :] = True
    return free


def pivoted_columns(
    design: FloatArray,
    free: BoolArray,
    rank_tolerance: float,
    first: BoolArray | None = None,
) -> tuple[NDArray[np.intp], int, float]:
    """The ``free`` columns of ``design`` (m, P) that survive column-pivoted QR of the
    unit-norm-scaled columns (:func:`~solver.pivoting.tiered_pivoted_qr`, ties by column
    order; a pivot below ``rank_tolerance`` of the first is dependent):
    kept indices (sorted), rank, condition number of the kept scaled columns.

    ``first`` (P,): columns pivoted before the others (:func:`frame_columns`), the others then
    orthogonal to the ones kept: a direction both can produce is carried by a ``first`` column.
    The kept columns span the same space either way; which of them carry it matters to the
    physical-range rule (:func:`implausible_columns`), which fixes inner-link columns but never
    the frames: an inner column that carried a frame's direction was fixed with it (a TIAGo
    wrist rotation standing for the marker offset: the refit then settled 15× above the
    cost of the fit without it)."""
    candidates = np.flatnonzero(free)
    a = design[:, candidates]
    norms = np.linalg.norm(a, axis=0)
    nonzero = norms > 1e-12 * max(norms.max(), 1e-300)
    candidates, a, norms = candidates[nonzero], a[:, nonzero], norms[nonzero]
    unit = a / norms
    subset = None if first is None else first[candidates]
    diagonal, pivots = tiered_pivoted_qr(unit, subset, rank_tolerance)
    taken = pivots[: int(np.sum(diagonal > rank_tolerance * diagonal[0]))]
    keep = np.sort(candidates[taken])
    kept = np.isin(candidates, keep)
    singular = np.linalg.svd(unit[:, kept], compute_uv=False)
    return keep, int(taken.size), float(singular[0] / singular[-1])


def scaled_condition_number(gram: FloatArray) -> float:
    """Condition number of the unit-norm-scaled columns from their Gram (p, p)."""
    norms = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
    eigenvalues = np.linalg.eigvalsh(gram / np.outer(norms, norms))
    return float(np.sqrt(eigenvalues[-1] / max(eigenvalues[0], 1e-300)))


def frame_columns(
    chain: KinematicChain, n_columns: int, n_compliance: int | None = None
) -> BoolArray:
    """The columns a fit may move anywhere (n_columns,): the measurement frame ``L_1``, the
    tool ``L_{k+1}`` and a measurement model's own unknowns (after the chain's 6 per link and
    ``n_compliance`` compliance columns, default one per compliance axis) — those the
    physical-range rule exempts (:func:`implausible_columns`); for ``first`` of
    :func:`pivoted_columns`."""
    if n_compliance is None:
        n_compliance = len(chain.compliance_axes)
    frames = np.zeros(n_columns, dtype=bool)
    frames[:6] = True
    frames[6 * (chain.n_links - 1) : 6 * chain.n_links] = True
    frames[6 * chain.n_links + n_compliance :] = True
    return frames


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
    predicted: FloatArray, measured: FloatArray, *, rotation: bool
) -> tuple[FloatArray, FloatArray | None]:
    """Per-sample translation error (mm) and rotation error (deg; None without ``rotation``,
    when the rows measure positions only: the measurement model's
    :attr:`~solver.measurement.FullPose.measures_rotation`)."""
    translation_mm = 1e3 * np.linalg.norm(predicted[:, :3, 3] - measured[:, :3, 3], axis=1)
    if not rotation:
        return translation_mm, None
    relative = np.swapaxes(predicted[:, :3, :3], 1, 2) @ measured[:, :3, :3]
    return translation_mm, np.degrees(lie.rotation_angle_rad(relative))
