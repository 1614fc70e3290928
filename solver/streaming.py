"""Calibration of recordings larger than memory: chunks in, sums out (paper Eq. 8–14).

Both calibration stages reduce to sums over samples: the Gauss–Newton normal equations
``JᵀJ, Jᵀr, rᵀr`` of Eq. (10) at each iterate, the residual spread of the 2σ rule (§V-A), the
error statistics, and the covariance statistics ``G, h, c`` of Eq. (13–14). Each pass maps one
function over the chunks of the recording (:mod:`solver.executors`: in-process, local processes
or Dask) and adds the per-chunk sums in chunk order, so the numbers do not depend on where a
chunk ran. A worker holds one chunk at a time (plus an optional, bounded cache of prepared
chunks), so memory does not grow with the number of samples.

The maths is the in-memory code's: the iteration is :func:`solver.calibration.gauss_newton`,
its normal equations :func:`solver.calibration.normal_equations`, the outlier rule
:func:`solver.calibration.within_spread` of a merged :class:`~solver.calibration.ResidualSpread`,
the covariance statistics :func:`solver.covariance.statistics.build_moment_statistics` per
chunk, merged by ``+``. Per chunk, FK, Jacobians and residuals come from
:mod:`solver.batch_chain` (the batch-last sweep, equal to :mod:`solver.kinematics` to rounding)
and gravity loads from :mod:`solver.gravity` (equal to the RNEA loads to 1e-10 N·m).

What differs from the in-memory pipeline, and why:

- **Warm start and pruning.** The closed-form alignment pairs samples across the whole
  recording, and the column-pivoted QR needs the stacked Jacobian; neither streams. Both run,
  unchanged, on the first ``warm_start_rows`` rows (:func:`solver.calibration.fit_deterministic`
  there), whose fitted parameters start the streamed iteration and whose kept columns are the
  streamed fit's. More data only adds to the Gram, so every kept column stays identifiable;
  a column the first rows cannot see is reported as removed. The condition number is the
  full recording's (from its normal equations). With at most ``warm_start_rows`` rows the
  start and the pruning are exactly the in-memory ones.
- **Outliers (2σ rule).** The first fit's final pass also sums the residual spread
  (mean, M2 per component, merged exactly); the rule (first fit's parameters, mean, σ) is then
  applied per chunk in every later pass (the per-chunk keep mask is cached, else recomputed from
  one forward pass). The refit and the "before" fit are warm-started, and pruned, like the
  first fit, on the head rows the rule keeps — as the in-memory pipeline refits the kept rows.
- **Covariances.** Moment matching (Eq. 13–14) streams exactly: one pass for ``G, h, c`` (and
  the Jacobian range for the constant-Jacobian warning), the solve, one pass for the sandwich
  ``Σ K̃ᵀK̃`` of the standard errors (over every s-th row beyond 50 000 used rows, scaled).
  ML/REML need a pass per scoring step and line-search trial; a streamed calibration uses the
  moment estimator and says so in its warnings (at 10⁵⁺ samples the REML correction is
  O(p/N)).
- **Deterministic standard errors** come from the final pass's ``JᵀJ`` and ``rᵀr`` exactly as
  in memory.
"""

from __future__ import annotations

import functools
import operator
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from solver import lie
from solver.batch_chain import joint_motions, pose_residuals, quaternion_rotation, sweep_chain
from solver.calibration import (
    FitOptions,
    GaussNewtonRun,
    NormalEquations,
    ResidualSpread,
    check_sample_count,
    fit_deterministic,
    gauss_newton,
    normal_equations,
    parameter_standard_errors,
    removed_names,
    within_spread,
)
from solver.covariance.estimate import (
    _SE_METHOD,
    CovarianceEstimate,
    SolverName,
    _fixed_frame,
    _frames,
)
from solver.covariance.identifiability import (
    RANK_RTOL,
    WEAK_RTOL,
    analyse_identifiability,
    resolve_null_space,
)
from solver.covariance.layout import CovarianceLayout, Structure, make_layout
from solver.covariance.likelihood import moment_sandwich_meat
from solver.covariance.solvers import PGD_STABLE, concrete_solver, solve_moment
from solver.covariance.statistics import (
    MomentStatistics,
    build_moment_statistics,
    empty_statistics,
)
from solver.covariance.uncertainty import theta_covariance, theta_uncertainty
from solver.errors import CalibrationError, SolverError
from solver.executors import Executor
from solver.gravity import StaticGravityModel, static_gravity_loads
from solver.kinematics import ChainParameters, parameter_names
from solver.model import STANDARD_GRAVITY_BASE, KinematicChain

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

MiB = 1024 * 1024
STREAMED_ESTIMATOR_NOTE = (
    "streamed calibration: covariances by moment matching (Eq. 13-14), which streams exactly; "
    "ML/REML need a pass over the data per scoring step (at this many samples the REML "
    "correction is O(p/N))"
)


# --- data: chunks of a recording -----------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ChunkArrays:
    """One chunk of a recording, as arrays (DESIGN.md §3 dataset contract).

    ``joint_positions`` (n, k) rad (m if prismatic), chain order; ``position_m`` (n, 3) marker
    position and ``quaternion_xyzw`` (n, 4) its orientation (scalar last) in the measurement
    frame, None if position-only; ``payload_kg`` (n,) or None; ``first_row``: 0-based index of
    the chunk's first row in the recording.
    """

    joint_positions: FloatArray
    position_m: FloatArray
    quaternion_xyzw: FloatArray | None
    payload_kg: FloatArray | None
    first_row: int

    @property
    def n_rows(self) -> int:
        return int(self.joint_positions.shape[0])


ChunkLoader = Callable[[Any], ChunkArrays]
"""Picklable callable: chunk reference -> :class:`ChunkArrays` (e.g. a Parquet row-group
reader from :mod:`schemas.dataset`; the solver never opens files itself)."""


def row_ranges(n_rows: int, chunk_rows: int) -> tuple[tuple[int, int], ...]:
    """``(start, stop)`` of consecutive chunks of at most ``chunk_rows`` rows."""
    if chunk_rows < 1:
        raise CalibrationError(f"chunk_rows must be positive, got {chunk_rows}")
    return tuple((a, min(a + chunk_rows, n_rows)) for a in range(0, n_rows, chunk_rows))


@dataclass(frozen=True, eq=False)
class ArrayChunks:
    """A :data:`ChunkLoader` over arrays already in memory; references are ``(start, stop)``.

    It carries the arrays, so other processes receive all of them with every pass: for tests
    and small data; large recordings go through a file loader."""

    joint_positions: FloatArray
    position_m: FloatArray
    quaternion_xyzw: FloatArray | None
    payload_kg: FloatArray | None = None

    def __call__(self, ref: tuple[int, int]) -> ChunkArrays:
        a, b = ref
        return ChunkArrays(
            self.joint_positions[a:b],
            self.position_m[a:b],
            None if self.quaternion_xyzw is None else self.quaternion_xyzw[a:b],
            None if self.payload_kg is None else self.payload_kg[a:b],
            a,
        )


@dataclass(frozen=True, eq=False)
class StreamProblem:
    """A recording to calibrate chunk by chunk, and how.

    ``refs``: chunk references in row order for ``load``; ``gravity_base_m_s2`` (3,) in the
    base frame; ``payload_kg`` for chunks without a payload column; ``block_rows``: samples per
    vectorised block inside a chunk (cache-sized working arrays); ``cache_bytes``: prepared
    chunks (joint motions, loads, measured poses, ~290 B/sample for 6 joints) each worker
    process may keep between passes, 0 = re-read every pass (memory then independent of N).
    """

    chain: KinematicChain
    load: ChunkLoader
    refs: tuple[Any, ...]
    position_only: bool
    gravity_base_m_s2: FloatArray = field(default_factory=lambda: STANDARD_GRAVITY_BASE.copy())
    payload_kg: float = 0.0
    block_rows: int = 8192
    cache_bytes: int = 512 * MiB
    token: str = field(default_factory=lambda: uuid.uuid4().hex)

    @property
    def residual_dim(self) -> int:
        return 3 if self.position_only else 6


# --- per-process caches (one per worker; never shared between processes) -------------------


@dataclass(frozen=True, eq=False)
class _Block:
    """A block of prepared samples, batch-last: everything that does not depend on the
    parameters. ``rotation`` (3, 3, b) / ``translation`` (3, b): measured pose."""

    first_row: int
    motions: list[lie.ScrewMotion]
    loads_nm: FloatArray
    rotation: FloatArray | None
    translation: FloatArray

    @property
    def n(self) -> int:
        return int(self.translation.shape[1])

    @property
    def nbytes(self) -> int:
        arrays = [self.loads_nm, self.translation]
        arrays += [self.rotation] if self.rotation is not None else []
        for m in self.motions:
            arrays += [m.angle, m.cos, m.sin]
            arrays += [m.translation] if m.translation is not None else []
        return sum(a.nbytes for a in arrays)


_PREPARED: OrderedDict[tuple[str, Any], list[_Block]] = OrderedDict()
_MASKS: dict[tuple[str, Any, str], list[BoolArray]] = {}
_GRAVITY: dict[str, StaticGravityModel] = {}
_LOCK = threading.Lock()  # Dask may run several tasks of one process in threads


def forget(token: str) -> None:
    """Drop this process's caches of the problem ``token`` (call on every worker when done)."""
    with _LOCK:
        for key in [k for k in _PREPARED if k[0] == token]:
            del _PREPARED[key]
        for mask_key in [k for k in _MASKS if k[0] == token]:
            del _MASKS[mask_key]
        _GRAVITY.pop(token, None)


def _gravity(problem: StreamProblem) -> StaticGravityModel:
    with _LOCK:
        model = _GRAVITY.get(problem.token)
        if model is None:
            model = _GRAVITY[problem.token] = StaticGravityModel.from_chain(problem.chain)
        return model


def _prepare(problem: StreamProblem, ref: Any) -> list[_Block]:
    """Load a chunk and prepare its blocks (from this process's cache when possible)."""
    key = (problem.token, ref)
    with _LOCK:
        cached = _PREPARED.get(key)
        if cached is not None:
            _PREPARED.move_to_end(key)
            return cached
    chunk = problem.load(ref)
    gravity = _gravity(problem)
    blocks = []
    for a in range(0, chunk.n_rows, problem.block_rows):
        b = min(a + problem.block_rows, chunk.n_rows)
        q = np.ascontiguousarray(chunk.joint_positions[a:b])
        motions = joint_motions(problem.chain, q)
        payload = problem.payload_kg if chunk.payload_kg is None else chunk.payload_kg[a:b]
        loads = static_gravity_loads(
            gravity, q, gravity_base=problem.gravity_base_m_s2, payload_kg=payload, motions=motions
        )
        quaternion = chunk.quaternion_xyzw
        rotation = None if quaternion is None else quaternion_rotation(quaternion[a:b])
        translation = np.ascontiguousarray(chunk.position_m[a:b].T)
        blocks.append(_Block(chunk.first_row + a, motions, loads, rotation, translation))
    size = sum(block.nbytes for block in blocks)
    if size <= problem.cache_bytes:
        with _LOCK:
            _PREPARED[key] = blocks
            held = sum(block.nbytes for value in _PREPARED.values() for block in value)
            while held > problem.cache_bytes and len(_PREPARED) > 1:
                _, dropped = _PREPARED.popitem(last=False)
                held -= sum(block.nbytes for block in dropped)
    return blocks


# --- sums per chunk ------------------------------------------------------------------------


@dataclass(frozen=True)
class ErrorSums:
    """Sums of per-sample pose errors: translation (mm) and rotation (deg), and squares."""

    n: int = 0
    translation_mm: float = 0.0
    translation_mm2: float = 0.0
    rotation_deg: float = 0.0
    rotation_deg2: float = 0.0

    @classmethod
    def of(cls, translation_mm: FloatArray, rotation_deg: FloatArray | None) -> ErrorSums:
        rot = np.zeros(0) if rotation_deg is None else rotation_deg
        return cls(
            int(translation_mm.size),
            float(translation_mm.sum()),
            float(translation_mm @ translation_mm),
            float(rot.sum()),
            float(rot @ rot),
        )

    def __add__(self, other: ErrorSums) -> ErrorSums:
        return ErrorSums(
            self.n + other.n,
            self.translation_mm + other.translation_mm,
            self.translation_mm2 + other.translation_mm2,
            self.rotation_deg + other.rotation_deg,
            self.rotation_deg2 + other.rotation_deg2,
        )

    def summary(self, position_only: bool) -> tuple[float, float, float | None, float | None]:
        """Mean and RMS translation error (mm), mean and RMS rotation error (deg or None)."""
        n = max(self.n, 1)
        rotation = (
            (None, None)
            if position_only
            else (self.rotation_deg / n, float(np.sqrt(self.rotation_deg2 / n)))
        )
        return self.translation_mm / n, float(np.sqrt(self.translation_mm2 / n)), *rotation


@dataclass(frozen=True)
class FitSums:
    """What one fit pass returns per chunk (and, added, for the recording): the normal
    equations over the kept columns (weighted), the spread of the unweighted residuals and
    the pose errors of the used samples, and the 0-based rows the outlier rule dropped."""

    normal: NormalEquations
    spread: ResidualSpread
    errors: ErrorSums
    removed_rows: NDArray[np.int64]

    def __add__(self, other: FitSums) -> FitSums:
        return FitSums(
            self.normal + other.normal,
            self.spread + other.spread,
            self.errors + other.errors,
            np.concatenate([self.removed_rows, other.removed_rows]),
        )


@dataclass(frozen=True, eq=False)
class OutlierRule:
    """Paper §V-A as a fixed rule: residuals at ``params`` within ``sigma`` standard deviations
    ``std`` of ``mean`` (d,) in every component; ``token`` names it in the mask cache."""

    params: ChainParameters
    mean: FloatArray
    std: FloatArray
    sigma: float
    token: str = field(default_factory=lambda: uuid.uuid4().hex)


@dataclass(frozen=True, eq=False)
class _FitPass:
    problem: StreamProblem
    params: ChainParameters
    keep: IntArray
    rotation_weight: float
    column_links: tuple[int, ...] | None
    compliance_columns: bool
    rule: OutlierRule | None
    collect_removed: bool


def _row_weights(d: int, rotation_weight: float) -> FloatArray:
    """Weights of the residual rows (d,): rotation rows times the weight (full pose only)."""
    weights = np.ones(d)
    weights[3:] = rotation_weight
    return weights


def rule_mask(
    problem: StreamProblem,
    rule: OutlierRule,
    motions: list[lie.ScrewMotion],
    loads_nm: FloatArray,
    rotation: FloatArray | None,
    translation: FloatArray,
) -> BoolArray:
    """Samples kept by ``rule`` (b,): residuals at ``rule.params`` from one forward pass."""
    sweep = sweep_chain(
        problem.chain,
        rule.params,
        motions,
        loads_nm,
        residual_dim=problem.residual_dim,
        with_columns=False,
    )
    residual = pose_residuals(sweep, rotation, translation).residual
    return within_spread(residual.T, rule.mean, rule.std, rule.sigma)


def _used(
    problem: StreamProblem,
    rule: OutlierRule | None,
    ref: Any,
    index: int,
    blocks: list[_Block],
) -> BoolArray:
    """Keep mask of block ``index`` of chunk ``ref`` (prepared as ``blocks``) under ``rule``
    (cached per process)."""
    if rule is None:
        return np.ones(blocks[index].n, dtype=bool)
    key = (problem.token, ref, rule.token)
    with _LOCK:
        masks = _MASKS.get(key)
    if masks is None:
        masks = [
            rule_mask(problem, rule, b.motions, b.loads_nm, b.rotation, b.translation)
            for b in blocks
        ]
        with _LOCK:
            _MASKS[key] = masks
    return masks[index]


def fit_chunk(request: _FitPass, ref: Any) -> FitSums:
    """Eq. (9–10) sums of one chunk at ``request.params``: FK, Jacobian columns, residuals."""
    problem = request.problem
    d = problem.residual_dim
    weights = _row_weights(d, request.rotation_weight)
    parts = []
    blocks = _prepare(problem, ref)
    for index, block in enumerate(blocks):
        used = _used(problem, request.rule, ref, index, blocks)
        sweep = sweep_chain(
            problem.chain,
            request.params,
            block.motions,
            block.loads_nm,
            residual_dim=d,
            with_columns=True,
            column_links=request.column_links,
            compliance_columns=request.compliance_columns,
        )
        assert sweep.columns is not None
        res = pose_residuals(sweep, block.rotation, block.translation)
        residual, columns = res.residual, sweep.columns[request.keep]
        translation_mm, rotation = 1e3 * res.translation_error_m, res.rotation_error_rad
        removed = np.zeros(0, dtype=np.int64)
        if not used.all():
            residual, columns = residual[:, used], columns[:, :, used]
            translation_mm = translation_mm[used]
            rotation = None if rotation is None else rotation[used]
            if request.collect_removed:
                removed = block.first_row + np.flatnonzero(~used).astype(np.int64)
        if request.rotation_weight != 1.0:
            residual_w, columns = residual * weights[:, None], columns * weights[None, :, None]
        else:
            residual_w = residual
        normal = normal_equations(
            columns.reshape(columns.shape[0], -1).T, np.ascontiguousarray(residual_w).reshape(-1)
        )
        errors = ErrorSums.of(translation_mm, None if rotation is None else np.degrees(rotation))
        parts.append(FitSums(normal, ResidualSpread.of(residual.T), errors, removed))
    return functools.reduce(operator.add, parts)


# --- streamed deterministic fit ----------------------------------------------------------


@dataclass(frozen=True)
class StreamedFit:
    """A deterministic fit (Eq. 8–10) over a streamed recording; the fields shared with
    :class:`solver.calibration.DeterministicFit` mean the same. ``sums``: normal equations,
    residual spread and errors at the solution over the used samples; ``passes``: passes over
    the data."""

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


def scaled_condition_number(gram: FloatArray) -> float:
    """Condition number of the unit-norm-scaled columns from their Gram (p, p)."""
    norms = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
    eigenvalues = np.linalg.eigvalsh(gram / np.outer(norms, norms))
    return float(np.sqrt(eigenvalues[-1] / max(eigenvalues[0], 1e-300)))


def streamed_fit_sums(
    problem: StreamProblem,
    executor: Executor,
    params: ChainParameters,
    keep: IntArray,
    options: FitOptions,
    *,
    rule: OutlierRule | None = None,
    collect_removed: bool = False,
) -> FitSums:
    """One pass: the Eq. (10) normal equations over the columns ``keep`` at ``params`` (and the
    residual spread and errors), summed over the chunks in order; samples failing ``rule`` are
    left out (and listed when ``collect_removed``)."""
    request = _FitPass(
        problem,
        params,
        keep,
        options.rotation_weight_m_per_rad,
        None if options.free_links is None else tuple(options.free_links),
        options.fit_compliance,
        rule,
        collect_removed,
    )
    total: FitSums = functools.reduce(operator.add, executor.map(fit_chunk, request, problem.refs))
    return total


def fit_streamed(
    problem: StreamProblem,
    executor: Executor,
    *,
    start: ChainParameters,
    keep: IntArray,
    options: FitOptions,
    rule: OutlierRule | None = None,
) -> StreamedFit:
    """Gauss–Newton (Eq. 10, :func:`solver.calibration.gauss_newton`) over the columns
    ``keep`` from ``start``, each iterate's normal equations summed over the chunks; samples
    failing ``rule`` are left out (their rows are collected on the first pass)."""
    started = time.perf_counter()
    passes = [0]

    def evaluate(params: ChainParameters, collect: bool = False) -> tuple[NormalEquations, FitSums]:
        total = streamed_fit_sums(
            problem, executor, params, keep, options, rule=rule, collect_removed=collect
        )
        passes[0] += 1
        return total.normal, total

    first_normal, first_sums = evaluate(start, collect=rule is not None)
    run: GaussNewtonRun[FitSums] = gauss_newton(
        problem.chain, start, keep, (first_normal, first_sums), evaluate, options
    )
    names = parameter_names(problem.chain)
    sums = FitSums(
        run.payload.normal, run.payload.spread, run.payload.errors, first_sums.removed_rows
    )
    return StreamedFit(
        params=run.params,
        estimated=[names[i] for i in keep],
        removed=removed_names(names, keep),
        standard_errors=parameter_standard_errors(run.normal),
        rank=int(keep.size),
        condition_number=scaled_condition_number(run.normal.gram),
        iterations=run.iterations,
        converged=run.converged,
        cost_history=run.cost_history,
        sums=sums,
        passes=passes[0],
        elapsed_s=time.perf_counter() - started,
    )


# --- warm start ---------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class HeadSample:
    """The first rows of a recording, in memory, as the in-memory fit takes them."""

    joint_positions: FloatArray
    measured_pose: FloatArray
    loads_nm: FloatArray

    def kept_by(self, problem: StreamProblem, rule: OutlierRule) -> HeadSample:
        """The rows ``rule`` keeps (the same computation as on streamed chunks)."""
        keep = rule_mask(
            problem,
            rule,
            joint_motions(problem.chain, self.joint_positions),
            self.loads_nm,
            None if problem.position_only else self.measured_pose[:, :3, :3].transpose(1, 2, 0),
            np.ascontiguousarray(self.measured_pose[:, :3, 3].T),
        )
        return HeadSample(self.joint_positions[keep], self.measured_pose[keep], self.loads_nm[keep])


def read_head(problem: StreamProblem, n_rows: int) -> HeadSample:
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
        None
        if problem.position_only
        else np.concatenate([c.quaternion_xyzw for c in chunks if c.quaternion_xyzw is not None])
    )
    payload: FloatArray | float = problem.payload_kg
    if chunks and chunks[0].payload_kg is not None:
        payload = np.concatenate([c.payload_kg for c in chunks if c.payload_kg is not None])
        payload = payload[:n_rows]
    loads = static_gravity_loads(
        _gravity(problem), q, gravity_base=problem.gravity_base_m_s2, payload_kg=payload
    )
    pose = lie.pose_matrix(position, None if quaternion is None else quaternion[:n_rows])
    return HeadSample(q, pose, loads)


def warm_start(
    problem: StreamProblem, head: HeadSample, options: FitOptions
) -> tuple[ChainParameters, IntArray]:
    """In-memory fit of the head rows (closed-form alignment, pivoted-QR pruning, Eq. 10):
    its parameters start the streamed fit and its kept columns are the streamed fit's."""
    fit = fit_deterministic(
        problem.chain,
        head.joint_positions,
        head.measured_pose,
        head.loads_nm,
        position_only=problem.position_only,
        options=options,
    )
    names = parameter_names(problem.chain)
    keep = np.array([names.index(name) for name in fit.estimated], dtype=np.intp)
    return fit.params, keep


# --- streamed covariance calibration (moment matching, Eq. 13–14) ---------------------------


@dataclass(frozen=True, eq=False)
class _CovariancePass:
    problem: StreamProblem
    params: ChainParameters
    frames: tuple[int, ...]
    layout: CovarianceLayout
    known: FloatArray | None
    rule: OutlierRule | None
    theta: FloatArray | None  # None: statistics pass; else the sandwich pass at θ
    stride: int = 1  # sandwich pass: every stride-th row of the recording


@dataclass(frozen=True)
class CovarianceSums:
    """Per chunk (and added): moment statistics (Eq. 14) or the sandwich meat Σ 2K̃ᵀK̃, and the
    sum, minimum and maximum of the frame Jacobians (F, d, 6) for the constant-Jacobian check.
    """

    stats: MomentStatistics | None
    meat: FloatArray | None
    jacobian_sum: FloatArray
    jacobian_min: FloatArray
    jacobian_max: FloatArray
    n: int

    def __add__(self, other: CovarianceSums) -> CovarianceSums:
        def add(a: Any, b: Any) -> Any:
            return b if a is None else a if b is None else a + b

        return CovarianceSums(
            add(self.stats, other.stats),
            add(self.meat, other.meat),
            self.jacobian_sum + other.jacobian_sum,
            np.minimum(self.jacobian_min, other.jacobian_min),
            np.maximum(self.jacobian_max, other.jacobian_max),
            self.n + other.n,
        )


def covariance_chunk(request: _CovariancePass, ref: Any) -> CovarianceSums:
    """Residuals and frame Jacobians ``A_f = Ad_{B_f}⁻¹`` (rows d) of one chunk at the
    calibrated parameters, reduced to Eq. (14) statistics or, given θ, the sandwich meat."""
    problem = request.problem
    d = problem.residual_dim
    n_frames = len(request.frames)
    theta = request.theta
    total = CovarianceSums(
        empty_statistics(request.layout, request.known) if theta is None else None,
        None if theta is None else np.zeros((request.layout.n_params,) * 2),
        np.zeros((n_frames, d, 6)),
        np.full((n_frames, d, 6), np.inf),
        np.full((n_frames, d, 6), -np.inf),
        0,
    )
    blocks = _prepare(problem, ref)
    for index, block in enumerate(blocks):
        used = _used(problem, request.rule, ref, index, blocks)
        if theta is not None and request.stride > 1:
            rows = block.first_row + np.arange(block.n)
            used = used & (rows % request.stride == 0)
        sweep = sweep_chain(
            problem.chain,
            request.params,
            block.motions,
            block.loads_nm,
            residual_dim=d,
            with_columns=True,
            column_links=request.frames,
            compliance_columns=False,
        )
        assert sweep.columns is not None
        if not used.any():
            continue
        residual = pose_residuals(sweep, block.rotation, block.translation).residual[:, used]
        stacked = np.stack([sweep.columns[6 * f : 6 * f + 6] for f in request.frames])
        jacobians = np.ascontiguousarray(stacked[..., used].transpose(3, 0, 2, 1))  # (b,F,d,6)
        if theta is None:
            stats = build_moment_statistics(
                np.ascontiguousarray(residual.T),
                jacobians,
                request.layout,
                known_covariance=request.known,
            )
            meat = None
        else:
            stats = None
            meat = moment_sandwich_meat(
                theta, jacobians, request.layout, known_covariance=request.known
            )
        part = CovarianceSums(
            stats,
            meat,
            jacobians.sum(axis=0),
            jacobians.min(axis=0),
            jacobians.max(axis=0),
            int(jacobians.shape[0]),
        )
        total = total + part
    return total


def streamed_covariance_sums(
    problem: StreamProblem,
    executor: Executor,
    params: ChainParameters,
    frame_index: Sequence[int],
    layout: CovarianceLayout,
    known: FloatArray | None = None,
    rule: OutlierRule | None = None,
    *,
    theta: FloatArray | None = None,
    stride: int = 1,
) -> CovarianceSums:
    """One pass: Eq. (13–14) statistics (``theta`` None) or the sandwich meat at ``theta`` (of
    every ``stride``-th row), and the Jacobian range, of the frames ``frame_index`` at
    ``params``, summed over chunks."""
    request = _CovariancePass(
        problem, params, tuple(frame_index), layout, known, rule, theta, stride
    )
    total: CovarianceSums = functools.reduce(
        operator.add, executor.map(covariance_chunk, request, problem.refs)
    )
    return total


def estimate_covariances_streamed(
    problem: StreamProblem,
    executor: Executor,
    params: ChainParameters,
    frame_names: Sequence[str],
    frame_index: Sequence[int],
    *,
    structure: Structure = "diag",
    solver: SolverName = "auto",
    noise_covariance: FloatArray | None = None,
    rule: OutlierRule | None = None,
    confidence: float = 0.95,
    noise_name: str = "noise",
    notes: Sequence[str] = (),
    sandwich_rows: int = 50_000,
) -> CovarianceEstimate:
    """Moment-matching covariance calibration (paper §IV-C, Eq. 13–14) of a streamed recording:
    the same steps as :func:`solver.covariance.estimate.estimate_covariances` with
    ``estimator="moment"``, its sums over samples taken chunk by chunk.

    ``frame_index``: chain joint of each perturbed frame (``frame_names``); residuals and
    Jacobians in the end-effector frame ([v; w], m and rad) at ``params``; ``rule``: the outlier
    rule of the deterministic fit (the same samples are used); ``notes`` start the warnings.

    Standard errors need the sandwich ``Σ_n 2K̃ᵀK̃`` at θ̂, a second pass with a 6×6 whitening
    per sample; beyond ``sandwich_rows`` samples it is summed over every s-th row of the
    recording (s fixed by the row number, so independent of the chunking) and scaled by the
    ratio of counts — an unbiased estimate of the sum, for errors that need 2 digits, not 10.
    """
    d = problem.residual_dim
    known = None
    include_noise = True
    if noise_covariance is not None:
        known = np.asarray(noise_covariance, dtype=float)
        if known.shape not in ((6, 6), (d, d)):
            raise SolverError(f"noise_covariance must be 6×6 or {d}×{d}, got {known.shape}")
        known = 0.5 * (known + known.T)[:d, :d]
        include_noise = False
    layout = make_layout(
        frame_names, d, structure=structure, include_noise=include_noise, noise_name=noise_name
    )
    sums = streamed_covariance_sums(problem, executor, params, frame_index, layout, known, rule)
    if sums.n < 2:
        raise CalibrationError(f"covariance calibration needs at least 2 samples, got {sums.n}")
    assert sums.stats is not None
    stats = sums.stats
    if not (np.all(np.isfinite(stats.gram)) and np.all(np.isfinite(stats.cross))):
        raise CalibrationError("residuals or frame Jacobians contain NaN or inf")
    report = analyse_identifiability(
        stats, rank_rtol=RANK_RTOL, weak_rtol=WEAK_RTOL, frame_jacobians=_jacobian_range(sums)
    )
    solver_used = concrete_solver(solver, structure)
    moment = solve_moment(stats, solver_used, pgd_settings=PGD_STABLE)
    if not np.all(np.isfinite(moment.theta)):
        raise SolverError(
            f"moment solver {solver_used!r} failed ({moment.status}): {moment.message}"
        )
    notes = [*notes, *report.warnings]
    if not moment.converged:
        notes.append(
            f"moment solver {solver_used!r} ended with status {moment.status!r}"
            + (f": {moment.message}" if moment.message else "")
        )
    theta = resolve_null_space(moment.theta, report, layout)
    cov, unc = None, None
    stride = max(1, -(-sums.n // sandwich_rows))  # ceil
    meat_sums = streamed_covariance_sums(
        problem, executor, params, frame_index, layout, known, rule, theta=theta, stride=stride
    )
    try:
        assert meat_sums.meat is not None
        meat = meat_sums.meat * (sums.n / meat_sums.n)  # a sum over all samples
        cov = theta_covariance(meat, report, bread=stats.gram)
        unc = theta_uncertainty(
            theta,
            cov,
            report,
            layout.is_variance,
            confidence=confidence,
            method=_SE_METHOD["moment"],
        )
    except CalibrationError as exc:
        notes.append(f"no standard errors: {exc}")
    frames = _frames(layout, theta, unc)
    noise = None
    if layout.noise_frame is not None:
        noise, frames = frames[-1], frames[:-1]
    elif known is not None:
        full = np.zeros((6, 6))
        full[:d, :d] = known
        noise = _fixed_frame(noise_name, full)
    return CovarianceEstimate(
        "moment",
        structure,
        solver_used,
        sums.n,
        tuple(frames),
        noise,
        theta,
        layout,
        report,
        moment,
        moment,
        stats,
        cov,
        unc,
        tuple(notes),
    )


def _jacobian_range(sums: CovarianceSums) -> FloatArray:
    """Two pseudo-samples (2, F, d, 6) with the recording's mean Jacobian and, per entry, its
    largest deviation from the mean: the constant-Jacobian check sees the same mean and
    spread as on all samples."""
    mean = sums.jacobian_sum / sums.n
    deviation = np.maximum(sums.jacobian_max - mean, mean - sums.jacobian_min)
    return np.stack([mean + deviation, mean - deviation])


# --- the streamed calibration -------------------------------------------------------------


@dataclass(frozen=True)
class StreamSettings:
    """How a recording is streamed: ``warm_start_rows`` in-memory rows for the start and the
    pruning; ``outlier_sigma`` the §V-A rule (None: off)."""

    warm_start_rows: int = 10_000
    outlier_sigma: float | None = 2.0


@dataclass(frozen=True)
class StreamedCalibration:
    """Everything a streamed calibration produced; ``stage_s``: wall time per stage."""

    n_rows: int
    first: StreamedFit
    fit: StreamedFit
    baseline: StreamedFit
    rule: OutlierRule | None
    removed_rows: NDArray[np.int64]
    stage_s: dict[str, float]


def _count_chunk(problem: StreamProblem, ref: Any) -> int:
    return sum(block.n for block in _prepare(problem, ref))


def scan(problem: StreamProblem, executor: Executor) -> int:
    """Read and prepare every chunk once (filling the caches); the number of rows."""
    return int(sum(executor.map(_count_chunk, problem, problem.refs)))


def release(problem: StreamProblem, executor: Executor) -> None:
    """Free the problem's cached chunks and masks in every worker."""
    executor.run_on_workers(functools.partial(forget, problem.token))


def calibrate_streamed_fits(
    problem: StreamProblem,
    executor: Executor,
    options: FitOptions,
    baseline_options: FitOptions,
    settings: StreamSettings = StreamSettings(),
) -> StreamedCalibration:
    """Deterministic calibration of a streamed recording: warm start on the head rows, the
    first fit, the 2σ rule, the refit on the kept samples and the "before" fit (measurement
    frame and tool on the nominal robot), as :func:`service.pipeline.calibrate` does in memory.
    """
    clock = time.perf_counter()
    n_rows = scan(problem, executor)
    check_sample_count(problem.chain, n_rows, position_only=problem.position_only, options=options)
    stage = {"read": time.perf_counter() - clock}
    clock = time.perf_counter()
    head = read_head(problem, settings.warm_start_rows)
    start, keep = warm_start(problem, head, options)
    stage["warm_start"] = time.perf_counter() - clock
    clock = time.perf_counter()
    first = fit_streamed(problem, executor, start=start, keep=keep, options=options)
    rule = None
    fit = first
    used_head = head
    if settings.outlier_sigma is not None:
        spread = first.sums.spread
        rule = OutlierRule(first.params, spread.mean, spread.std, settings.outlier_sigma)
        used_head = head.kept_by(problem, rule)
        refit_start, refit_keep = warm_start(problem, used_head, options)
        fit = fit_streamed(
            problem, executor, start=refit_start, keep=refit_keep, options=options, rule=rule
        )
    baseline_start, baseline_keep = warm_start(problem, used_head, baseline_options)
    baseline = fit_streamed(
        problem,
        executor,
        start=baseline_start,
        keep=baseline_keep,
        options=baseline_options,
        rule=rule,
    )
    stage["deterministic"] = time.perf_counter() - clock
    removed = fit.sums.removed_rows if rule is not None else np.zeros(0, dtype=np.int64)
    return StreamedCalibration(n_rows, first, fit, baseline, rule, np.sort(removed), stage)
