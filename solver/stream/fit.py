"""Streamed damped Gauss–Newton (Levenberg–Marquardt, paper Eq. 8–10): one pass per iterate,
several fits in lockstep, and the in-memory warm start on the head rows.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
import operator
import time
from collections.abc import Generator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from solver import lie
from solver.arrays import BoolArray, FloatArray, IntArray
from solver.batch_chain import (
    column_rows,
    is_unit_column,
    joint_motions,
    pose_residuals,
    sweep_chain,
)
from solver.calibration import (
    DeterministicFit,
    FitOptions,
    LeastSquaresRun,
    NormalEquations,
    ResidualSpread,
    implausible_link_columns,
    levenberg_marquardt_iteration,
    parameter_standard_errors,
    removed_names,
    scaled_condition_number,
    without_columns,
)
from solver.executors import Executor
from solver.gravity import static_gravity_loads
from solver.kinematics import ChainParameters, parameter_names
from solver.measurement.pose import fit_deterministic
from solver.model import KinematicChain
from solver.stream.chunks import (
    Block,
    ChunkArrays,
    StreamProblem,
    gravity_model,
    keep_residuals,
    prepared_blocks,
)
from solver.stream.screening import (
    RowRule,
    Rule,
    block_residuals,
    parameters_key,
    rule_mask,
    used_mask,
)
from solver.stream.sums import (
    CovarianceSpec,
    ErrorSums,
    FitSums,
    covariance_sums,
    frame_range,
)


@dataclass(frozen=True, eq=False)
class _Evaluation:
    """One point of one fit in a pass: normal equations over the columns ``keep`` at
    ``params`` of the samples ``rule`` keeps (their dropped rows listed when
    ``collect_removed``); ``keep_residuals``: remember each block's residuals in this process
    (the outlier rule is applied to them later without another sweep); ``covariance``: also
    the Eq. (13–14) statistics at this point."""

    params: ChainParameters
    keep: IntArray
    rotation_weight: float
    rule: Rule | None
    collect_removed: bool = False
    keep_residuals: bool = False
    covariance: CovarianceSpec | None = None


@dataclass(frozen=True, eq=False)
class _FitPass:
    problem: StreamProblem
    evaluations: tuple[_Evaluation, ...]


def fit_chunk(request: _FitPass, ref: Any) -> tuple[FitSums, ...]:
    """Eq. (9–10) sums of one chunk at each evaluation's point: FK, Jacobian columns,
    residuals (and the covariance statistics where asked), block by block."""
    problem = request.problem
    blocks = prepared_blocks(problem, ref)
    out = []
    for evaluation in request.evaluations:
        parts = []
        residuals = []
        for index, block in enumerate(blocks):
            used = used_mask(problem, evaluation.rule, ref, index, blocks)
            part, residual = _evaluate_block(problem, evaluation, block, used)
            parts.append(part)
            residuals.append(residual)
        if evaluation.keep_residuals:
            keep_residuals(problem, ref, blocks, parameters_key(evaluation.params), residuals)
        out.append(functools.reduce(operator.add, parts))
    return tuple(out)


@dataclass(frozen=True, eq=False)
class _ColumnPlan:
    """Which Jacobian columns one evaluation sweeps, in which order, and what they are.

    ``requested``: the fit's general columns, those with every row first (the link
    translation columns, without rotation rows, after them), then the columns only the
    covariance statistics need; the fit's unit columns (the tip link's ``e_m``) are not swept.
    ``general``/``units``: positions in ``keep`` of the general columns (sweep order) and of
    the unit columns, with ``unit_rows`` the row of each unit column's 1.
    """

    requested: list[int]
    rows: IntArray
    general: IntArray
    units: IntArray
    unit_rows: IntArray
    position: dict[int, int]

    @classmethod
    def of(
        cls, chain: KinematicChain, keep: IntArray, d: int, spec: CovarianceSpec | None
    ) -> _ColumnPlan:
        kept = [int(c) for c in keep]
        units = [i for i, c in enumerate(kept) if is_unit_column(chain, c)]
        general = [i for i, c in enumerate(kept) if not is_unit_column(chain, c)]
        general.sort(key=lambda i: -column_rows(chain, kept[i], d))  # stable: full rows first
        fitted = {kept[i] for i in general}
        extra = [] if spec is None else [c for c in spec.frame_columns if c not in fitted]
        requested = [kept[i] for i in general] + extra
        return cls(
            requested,
            np.array([column_rows(chain, c, d) for c in requested], dtype=np.intp),
            np.array(general, dtype=np.intp),
            np.array(units, dtype=np.intp),
            np.array([kept[i] % 6 for i in units], dtype=np.intp),
            {c: s for s, c in enumerate(requested)},
        )


def _evaluate_block(
    problem: StreamProblem, evaluation: _Evaluation, block: Block, used: BoolArray | None
) -> tuple[FitSums, FloatArray]:
    """:func:`fit_chunk` for one block: the sums, and the unweighted residuals (d, b)."""
    d = problem.residual_dim
    spec = evaluation.covariance
    plan = _ColumnPlan.of(problem.chain, evaluation.keep, d, spec)
    sweep = sweep_chain(
        problem.chain,
        evaluation.params,
        block.motions,
        block.loads_nm,
        residual_dim=d,
        columns=plan.requested,
    )
    assert sweep.columns is not None
    res = pose_residuals(sweep, block.rotation, block.translation)
    residual = res.residual
    columns = sweep.columns
    translation_mm, rotation = 1e3 * res.translation_error_m, res.rotation_error_rad
    removed = np.zeros(0, dtype=np.int64)
    fitted = residual
    covariance = None
    if spec is not None:
        ranges = frame_range(spec, columns, plan.position, used)
    if used is not None:  # zero the dropped samples: they add nothing to any sum
        skip = ~used
        fitted = residual.copy()
        fitted[:, skip] = 0.0
        columns[:, :, skip] = 0.0
        translation_mm = translation_mm[used]
        rotation = None if rotation is None else rotation[used]
        if evaluation.collect_removed:
            removed = block.first_row + np.flatnonzero(skip).astype(np.int64)
    n_used = block.n if used is None else int(np.count_nonzero(used))
    if spec is not None:
        covariance = covariance_sums(
            spec, columns, plan.rows, plan.position, fitted, used, ranges, n_used
        )
    weights = _row_weights(d, evaluation.rotation_weight)
    design = columns[: plan.general.size]
    if evaluation.rotation_weight != 1.0 and d == 6:
        design[:, 3:] *= evaluation.rotation_weight
        fitted = fitted * weights[:, None]
    normal = _normal_equations(design, plan, fitted, weights, n_used, evaluation.keep.size)
    spread = ResidualSpread.of(residual.T if used is None else residual.T[used])
    errors = ErrorSums.of(translation_mm, None if rotation is None else np.degrees(rotation))
    return FitSums(normal, spread, errors, removed, covariance), residual


def _row_weights(d: int, rotation_weight: float) -> FloatArray:
    """Weights of the residual rows (d,): rotation rows times the weight (full pose only)."""
    weights = np.ones(d)
    weights[3:] = rotation_weight
    return weights


def _normal_equations(
    design: FloatArray,
    plan: _ColumnPlan,
    target: FloatArray,
    weights: FloatArray,
    n_used: int,
    size: int,
) -> NormalEquations:
    """Eq. (10) sums ``AᵀA, Aᵀy, yᵀy`` of one block, in ``keep`` order, from the general
    columns ``design`` (g, d, b) (weighted, rows beyond ``plan.rows`` zero, full ones first),
    the unit columns ``weights[m] e_m`` of ``plan`` and the weighted residuals (d, b).

    The Gram is taken band by band of rows, each over the columns that can be non-zero there
    (a link translation column has no rotation rows): for 6-row residuals about half the
    products of a plain ``AᵀA``; the unit columns' entries are row sums.
    """
    g, d, _ = design.shape
    rows = plan.rows[:g]
    gram = np.zeros((size, size))
    general, units = plan.general, plan.units
    inner = np.zeros((g, g))
    bounds = sorted({0, *rows.tolist()})
    for low, high in itertools.pairwise(bounds):
        active = int(np.count_nonzero(rows >= high))
        band = design[:active, low:high].reshape(active, -1)
        inner[:active, :active] += band @ band.T
    gram[np.ix_(general, general)] = inner
    flat = design.reshape(g, -1)
    cross = np.zeros(size)
    cross[general] = flat @ target.reshape(-1)
    if units.size:
        row_sums = design.sum(axis=2)[:, plan.unit_rows]  # (g, u): Σ_n a_g[m]
        unit_weights = weights[plan.unit_rows]
        gram[np.ix_(general, units)] = row_sums * unit_weights
        gram[np.ix_(units, general)] = (row_sums * unit_weights).T
        gram[units, units] = unit_weights**2 * n_used
        cross[units] = unit_weights * target[plan.unit_rows].sum(axis=-1)
    gram = 0.5 * (gram + gram.T)
    return NormalEquations(gram, cross, float(np.vdot(target, target)), d * n_used)


# --- streamed deterministic fit ----------------------------------------------------------


@dataclass(frozen=True)
class StreamedFit:
    """A deterministic fit (Eq. 8–10) over a streamed recording; the fields shared with
    :class:`solver.calibration.DeterministicFit` mean the same. ``sums``: normal equations,
    residual spread and errors at the solution over the used samples (and the covariance
    statistics there, when they were asked for and came with a pass); ``passes``: passes over
    the data that evaluated this fit (shared with the fits run beside it)."""

    params: ChainParameters
    estimated: list[str]
    removed: list[str]
    standard_errors: FloatArray
    rank: int
    condition_number: float
    iterations: int
    converged: bool
    cost_history: list[float]
    sums: FitSums
    passes: int
    elapsed_s: float
    pruned: list[str] = dataclasses.field(default_factory=list)


def _run_pass(
    problem: StreamProblem, executor: Executor, evaluations: Sequence[_Evaluation]
) -> list[FitSums]:
    """One pass over the chunks evaluating every point of ``evaluations``; per evaluation the
    chunk sums added in chunk order."""
    per_chunk = executor.map(fit_chunk, _FitPass(problem, tuple(evaluations)), problem.refs)
    return [
        functools.reduce(operator.add, [chunk[e] for chunk in per_chunk])
        for e in range(len(evaluations))
    ]


def streamed_fit_sums(
    problem: StreamProblem,
    executor: Executor,
    params: ChainParameters,
    keep: IntArray,
    options: FitOptions,
    *,
    rule: Rule | None = None,
    collect_removed: bool = False,
) -> FitSums:
    """One pass: the Eq. (10) normal equations over the columns ``keep`` at ``params`` (and the
    residual spread and errors), summed over the chunks in order; samples failing ``rule`` are
    left out (and listed when ``collect_removed``)."""
    evaluation = _Evaluation(
        params, keep, options.rotation_weight_m_per_rad, rule, collect_removed=collect_removed
    )
    return _run_pass(problem, executor, [evaluation])[0]


@dataclass(frozen=True, eq=False)
class FitRequest:
    """A streamed Gauss–Newton fit to run: from ``start`` over the columns ``keep``, on the
    samples ``rule`` keeps; ``keep_residuals``: leave each chunk's residuals at the last point
    in the workers (the outlier rule of this fit is then applied without another sweep);
    ``covariance``: take the covariance statistics along in every pass after the first (the
    final point's are the covariance stage's, without a pass of their own)."""

    start: ChainParameters
    keep: IntArray
    options: FitOptions
    rule: Rule | None = None
    keep_residuals: bool = False
    covariance: CovarianceSpec | None = None
    start_is_close: bool = False
    """The start is expected to be the optimum (e.g. from
    :func:`~solver.calibration.without_columns`): the first pass takes the covariance
    statistics along as well."""
    pruned: tuple[str, ...] = ()
    """Parameters outside ``keep`` fixed by the physical-range rule (:func:`warm_start`):
    listed as pruned, not as unidentifiable."""
    first: FitSums | None = None
    """The sums at ``start`` from a pass that evaluated it as this fit's first pass would
    (:func:`evaluate_starts`): the fit takes its first step from them, without a pass."""


@dataclass
class PassCount:
    """Passes over the data so far (a pass may serve several fits)."""

    passes: int = 0


def _evaluation(request: FitRequest, point: ChainParameters, passes: int) -> _Evaluation:
    """What the pass after ``passes`` passes of ``request``'s fit evaluates at ``point``: the
    first lists the rows its rule drops, the later ones (or, with ``start_is_close``, every
    one) take the covariance statistics along."""
    return _Evaluation(
        point,
        request.keep,
        request.options.rotation_weight_m_per_rad,
        request.rule,
        collect_removed=request.rule is not None and passes == 0,
        keep_residuals=request.keep_residuals,
        covariance=request.covariance if passes > 0 or request.start_is_close else None,
    )


def evaluate_starts(
    problem: StreamProblem,
    executor: Executor,
    requests: Sequence[FitRequest],
    count: PassCount | None = None,
) -> list[FitSums]:
    """One pass: the sums at each request's start, as the first pass of its fit takes them
    (give them back as :attr:`FitRequest.first`), e.g. to choose between starts by their cost."""
    sums = _run_pass(problem, executor, [_evaluation(r, r.start, 0) for r in requests])
    if count is not None:
        count.passes += 1
    return sums


def fit_streamed_together(
    problem: StreamProblem,
    executor: Executor,
    requests: Sequence[FitRequest],
    count: PassCount | None = None,
) -> list[StreamedFit]:
    """Levenberg–Marquardt (Eq. 10, :func:`solver.calibration.levenberg_marquardt_iteration`)
    for each request, in lockstep: every pass over the data evaluates the next point of every fit
    still running, so fits that do not depend on each other (the refit and the "before" fit)
    share their passes. Each fit's iterates are exactly those it would take alone."""
    count = count if count is not None else PassCount()
    started = time.perf_counter()
    chain = problem.chain
    iterations: list[
        Generator[ChainParameters, tuple[NormalEquations, FitSums], LeastSquaresRun[FitSums]]
    ] = [levenberg_marquardt_iteration(chain, r.start, r.keep, r.options) for r in requests]
    pending: list[ChainParameters | None] = [next(it) for it in iterations]
    runs: list[LeastSquaresRun[FitSums] | None] = [None] * len(requests)
    first_sums: list[FitSums | None] = [None] * len(requests)
    passes = [0] * len(requests)

    def take(i: int, sums: FitSums) -> None:
        passes[i] += 1
        if first_sums[i] is None:
            first_sums[i] = sums
        try:
            pending[i] = iterations[i].send((sums.normal, sums))
        except StopIteration as done:
            runs[i], pending[i] = done.value, None

    for i, request in enumerate(requests):
        if request.first is not None:  # its pass was counted where it ran
            take(i, request.first)
    while any(p is not None for p in pending):
        active = [i for i, p in enumerate(pending) if p is not None]
        evaluations = []
        for i in active:
            point = pending[i]
            assert point is not None
            evaluations.append(_evaluation(requests[i], point, passes[i]))
        results = _run_pass(problem, executor, evaluations)
        count.passes += 1
        for i, sums in zip(active, results, strict=True):
            take(i, sums)
    names = parameter_names(chain)
    fits = []
    for request, run, first, n_passes in zip(requests, runs, first_sums, passes, strict=True):
        assert run is not None and first is not None
        sums = dataclasses.replace(run.payload, removed_rows=first.removed_rows)
        fits.append(
            StreamedFit(
                params=run.params,
                estimated=[names[i] for i in request.keep],
                removed=[n for n in removed_names(names, request.keep) if n not in request.pruned],
                standard_errors=parameter_standard_errors(run.normal),
                rank=int(request.keep.size),
                condition_number=scaled_condition_number(run.normal.gram),
                iterations=run.iterations,
                converged=run.converged,
                cost_history=run.cost_history,
                sums=sums,
                passes=n_passes,
                elapsed_s=time.perf_counter() - started,
                pruned=list(request.pruned),
            )
        )
    return fits


def fit_streamed(
    problem: StreamProblem,
    executor: Executor,
    *,
    start: ChainParameters,
    keep: IntArray,
    options: FitOptions,
    rule: Rule | None = None,
) -> StreamedFit:
    """Gauss–Newton (Eq. 10) over the columns ``keep`` from ``start``, each iterate's normal
    equations summed over the chunks; samples failing ``rule`` are left out (their rows are
    collected on the first pass)."""
    return fit_streamed_together(problem, executor, [FitRequest(start, keep, options, rule)])[0]


# --- warm start ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class RowSample:
    """Rows of a recording in memory, as the in-memory fit takes them: joint positions (n, k)
    rad, measured poses (n, 4, 4) in the measurement frame, gravity loads (n, n_axes) N·m and
    the rows' 0-based indices in the recording (n,)."""

    joint_positions: FloatArray
    measured_pose: FloatArray
    loads_nm: FloatArray
    rows: IntArray

    @property
    def n(self) -> int:
        return int(self.rows.size)

    def take(self, index: IntArray) -> RowSample:
        return RowSample(
            self.joint_positions[index],
            self.measured_pose[index],
            self.loads_nm[index],
            self.rows[index],
        )

    def _block(
        self, problem: StreamProblem
    ) -> tuple[list[lie.ScrewMotion], FloatArray, FloatArray | None, FloatArray]:
        """The rows as a streamed block takes them: joint motions, loads, measured rotations
        (3, 3, n) (None when position-only) and translations (3, n)."""
        return (
            joint_motions(problem.chain, self.joint_positions),
            self.loads_nm,
            self.measured_pose[:, :3, :3].transpose(1, 2, 0)
            if problem.measurement.measures_rotation
            else None,
            np.ascontiguousarray(self.measured_pose[:, :3, 3].T),
        )

    def residuals_at(self, problem: StreamProblem, params: ChainParameters) -> FloatArray:
        """Residuals (n, d) of the rows at ``params`` (as a streamed pass computes them)."""
        return block_residuals(problem, params, *self._block(problem)).T

    def kept_by(self, problem: StreamProblem, rule: Rule) -> RowSample:
        """The rows ``rule`` keeps (the same computation as on streamed chunks)."""
        if isinstance(rule, RowRule):
            return self.take(np.flatnonzero(rule.keep(self.rows)))
        return self.take(np.flatnonzero(rule_mask(problem, rule, *self._block(problem))))


def read_head(problem: StreamProblem, n_rows: int) -> RowSample:
    """The first ``n_rows`` rows (fewer if the recording is shorter), with gravity loads."""
    chunks: list[ChunkArrays] = []
    total = 0
    for ref in problem.refs:
        if total >= n_rows:
            break
        chunk = problem.load(ref)
        chunks.append(chunk)
        total += chunk.n_rows
    q = np.concatenate([c.joint_positions for c in chunks])[:n_rows]
    position = np.concatenate([c.position_m for c in chunks])[:n_rows]
    quaternion = (
        np.concatenate([c.quaternion_xyzw for c in chunks if c.quaternion_xyzw is not None])
        if problem.measurement.measures_rotation
        else None
    )
    payload: FloatArray | float = problem.payload_kg
    if chunks and chunks[0].payload_kg is not None:
        payload = np.concatenate([c.payload_kg for c in chunks if c.payload_kg is not None])
        payload = payload[:n_rows]
    loads = static_gravity_loads(
        gravity_model(problem), q, gravity_base=problem.gravity_base_m_s2, payload_kg=payload
    )
    pose = lie.pose_matrix(position, None if quaternion is None else quaternion[:n_rows])
    return RowSample(q, pose, loads, np.arange(q.shape[0], dtype=np.intp))


@dataclass(frozen=True, eq=False)
class _GatherPass:
    problem: StreamProblem
    rule: Rule | None
    stride: int


def gather_chunk(request: _GatherPass, ref: Any) -> RowSample:
    """The used rows of one chunk whose row number is a multiple of the stride."""
    problem = request.problem
    blocks = prepared_blocks(problem, ref)
    parts = []
    for index, block in enumerate(blocks):
        used = used_mask(problem, request.rule, ref, index, blocks)
        rows = block.first_row + np.arange(block.n)
        keep = np.flatnonzero((rows % request.stride == 0) & (True if used is None else used))
        q = np.stack([m.angle for m in block.motions], axis=1)[keep]
        pose = np.zeros((keep.size, 4, 4))
        pose[:, 3, 3] = 1.0
        pose[:, :3, 3] = block.translation[:, keep].T
        if block.rotation is None:
            pose[:, :3, :3] = np.eye(3)
        else:
            pose[:, :3, :3] = block.rotation[:, :, keep].transpose(2, 0, 1)
        parts.append(RowSample(q, pose, block.loads_nm[keep], rows[keep].astype(np.intp)))
    return join_rows(parts)


def join_rows(parts: Sequence[RowSample]) -> RowSample:
    """Row samples one after the other."""
    return RowSample(
        np.concatenate([p.joint_positions for p in parts]),
        np.concatenate([p.measured_pose for p in parts]),
        np.concatenate([p.loads_nm for p in parts]),
        np.concatenate([p.rows for p in parts]),
    )


def gather_rows(
    problem: StreamProblem, executor: Executor, rule: Rule | None, stride: int
) -> RowSample:
    """One pass: the rows ``rule`` keeps whose row number is a multiple of ``stride``, in
    memory, in row order (the same rows however the recording is cut into chunks)."""
    return join_rows(executor.map(gather_chunk, _GatherPass(problem, rule, stride), problem.refs))


WARM_START_PROBE_ITERATIONS = 10
"""The head fit's first iterations before the physical-range rule judges its inner links: a
link frame the data cannot place drifts along a flat valley to the iteration limit, and its
standard error already says so after a few iterations (TALOS: > 0.1 rad)."""


def warm_start(
    problem: StreamProblem, head: RowSample, options: FitOptions
) -> tuple[ChainParameters, IntArray, tuple[str, ...]]:
    """In-memory fit of the head rows (closed-form alignment, pivoted-QR pruning, Eq. 10):
    its parameters start the streamed fit and its kept columns are the streamed fit's (with
    the names of the columns it pruned, for :attr:`FitRequest.pruned`). An
    inner link's twist component the head rows do not place in any physical range
    (:func:`~solver.calibration.implausible_link_columns`) is fixed at nominal and the head
    fit repeated without it (:func:`~solver.calibration.without_columns`), so that neither
    the head fit nor the streamed fits it starts (the refit, the 2σ rule's first fit) follow
    it along a flat valley to the iteration limit. Which compliances are physical is decided
    on the whole recording, after the streamed fit
    (:func:`solver.stream.calibrate.non_negative_fit`), not on the head rows."""
    chain = problem.chain
    head_options = dataclasses.replace(options, non_negative_compliance=False)

    def fit_head(start: ChainParameters | None, max_iterations: int) -> DeterministicFit:
        return fit_deterministic(
            chain,
            head.joint_positions,
            head.measured_pose,
            head.loads_nm,
            measurement=problem.measurement,
            options=dataclasses.replace(head_options, max_iterations=max_iterations),
            start=start,
        )

    probe = min(WARM_START_PROBE_ITERATIONS, options.max_iterations)
    fit = fit_head(None, probe)
    names = parameter_names(chain)
    keep = np.array([names.index(name) for name in fit.estimated], dtype=np.intp)
    pruned: list[int] = []
    while (
        options.non_negative_compliance
        and (links := implausible_link_columns(chain, fit.params, keep, fit.standard_errors)).size
    ):
        pruned += links.tolist()
        free = np.setdiff1d(keep, links)
        n_chain = 6 * chain.n_links + len(chain.compliance_axes)
        head_options = dataclasses.replace(
            head_options, free_columns=tuple(int(c) for c in free[free < n_chain])
        )
        fit = fit_head(without_columns(chain, fit.params, links), options.max_iterations)
        keep = np.array([names.index(name) for name in fit.estimated], dtype=np.intp)
    if not fit.converged and fit.iterations == probe < options.max_iterations:
        fit = fit_head(fit.params, options.max_iterations - probe)
    return fit.params, keep, tuple(names[c] for c in sorted(pruned))


def _warm_start_task(
    shared: tuple[StreamProblem, RowSample], options: FitOptions
) -> tuple[ChainParameters, IntArray, tuple[str, ...]]:
    return warm_start(*shared, options)


def warm_starts(
    problem: StreamProblem,
    executor: Executor,
    head: RowSample,
    options: Sequence[FitOptions],
) -> list[tuple[ChainParameters, IntArray, tuple[str, ...]]]:
    """:func:`warm_start` for each of ``options`` on the executor's workers, side by side
    (the same numbers as one after the other on the driver)."""
    return executor.map(_warm_start_task, (problem, head), list(options))
