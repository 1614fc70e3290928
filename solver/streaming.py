"""Calibration of recordings larger than memory: chunks in, sums out (paper Eq. 8–14).

Both calibration stages reduce to sums over samples: the Gauss–Newton normal equations
``JᵀJ, Jᵀr, rᵀr`` of Eq. (10) at each iterate, the residual spread of the 2σ rule (§V-A), the
error statistics, and the covariance statistics ``G, h, c`` of Eq. (13–14). Each pass maps one
function over the chunks of the recording (:mod:`solver.executors`: in-process, local processes
or Dask) and adds the per-chunk sums in chunk order, so the numbers do not depend on where a
chunk ran. A worker holds one chunk at a time (plus an optional, bounded cache of prepared
chunks), so memory does not grow with the number of samples.

The maths is the in-memory code's: the iteration is
:func:`solver.calibration.gauss_newton_iteration`, the outlier rule
:func:`solver.calibration.within_spread` of a merged :class:`~solver.calibration.ResidualSpread`,
the covariance statistics those of :mod:`solver.covariance.statistics` per chunk, merged by
``+``. Per chunk, FK, Jacobians and residuals come from :mod:`solver.batch_chain` (the
batch-last sweep, equal to :mod:`solver.kinematics` to rounding; only the columns a pass needs)
and gravity loads from :mod:`solver.gravity` (equal to the RNEA loads to 1e-10 N·m). Samples
the outlier rule drops get zero rows (no gather), and the normal equations use the columns'
zero structure (:func:`_normal_equations`).

Passes over the data (a 10⁶-pose recording: 6, of which the last touches 5 % of the rows):
preparing the chunks (while the driver fits the head rows), the first fit's two, then the
refit and the "before" fit side by side (:func:`fit_streamed_together`: each of their passes
evaluates both), the refit's later passes also taking the covariance statistics along, and the
sandwich pass of the standard errors.

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
  (mean, M2 per component, merged exactly) and leaves each chunk's residuals in its worker;
  the rule (first fit's parameters, mean, σ) is applied to them (or, without the chunk cache,
  to one forward pass) and the per-chunk keep mask is cached for every later pass. The refit
  and the "before" fit are warm-started, and pruned, like the first fit, on the head rows the
  rule keeps — as the in-memory pipeline refits the kept rows.
- **Covariances.** Moment matching (Eq. 13–14) streams exactly: ``G, h, c`` (and the Jacobian
  range for the constant-Jacobian warning) at the refit's solution — taken along by its last
  pass, or by a pass of their own when the refit stopped at its start —, the solve, one pass
  for the sandwich ``Σ K̃ᵀK̃`` of the standard errors (over every s-th row beyond 50 000 used
  rows, scaled; only those rows are swept). ML/REML need a pass per scoring step and
  line-search trial; a streamed calibration uses the moment estimator and says so in its
  warnings (at 10⁵⁺ samples the REML correction is O(p/N)).
- **Deterministic standard errors** come from the final pass's ``JᵀJ`` and ``rᵀr`` exactly as
  in memory.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import itertools
import operator
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Generator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from solver import lie
from solver.batch_chain import (
    column_rows,
    is_unit_column,
    joint_motions,
    pose_residuals,
    quaternion_rotation,
    sweep_chain,
)
from solver.calibration import (
    FitOptions,
    GaussNewtonRun,
    NormalEquations,
    ResidualSpread,
    check_sample_count,
    fit_deterministic,
    gauss_newton_iteration,
    parameter_standard_errors,
    removed_names,
    within_spread,
)
from solver.covariance.estimate import (
    SE_METHOD,
    CovarianceEstimate,
    SolverName,
    frame_results,
    known_noise_covariance,
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
    diag_statistics_batch_last,
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

    def subset(self, index: IntArray) -> _Block:
        """The samples ``index`` of this block (their own first row is not kept)."""
        motions = [
            dataclasses.replace(
                m,
                angle=m.angle[index],
                cos=m.cos[index],
                sin=m.sin[index],
                translation=None if m.translation is None else m.translation[:, index],
            )
            for m in self.motions
        ]
        rotation = None if self.rotation is None else self.rotation[:, :, index]
        return _Block(-1, motions, self.loads_nm[index], rotation, self.translation[:, index])


_PREPARED: OrderedDict[tuple[str, Any], list[_Block]] = OrderedDict()
_MASKS: dict[tuple[str, Any, str], list[BoolArray]] = {}
_RESIDUALS: dict[tuple[str, Any], tuple[bytes, list[FloatArray]]] = {}
_GRAVITY: dict[str, StaticGravityModel] = {}
_LOCK = threading.Lock()  # Dask may run several tasks of one process in threads


def forget(token: str) -> None:
    """Drop this process's caches of the problem ``token`` (call on every worker when done)."""
    with _LOCK:
        for key in [k for k in _PREPARED if k[0] == token]:
            del _PREPARED[key]
        for mask_key in [k for k in _MASKS if k[0] == token]:
            del _MASKS[mask_key]
        for chunk_key in [k for k in _RESIDUALS if k[0] == token]:
            del _RESIDUALS[chunk_key]
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
                old, dropped = _PREPARED.popitem(last=False)
                _RESIDUALS.pop(old, None)
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


@dataclass(frozen=True, eq=False)
class CovarianceSpec:
    """What the covariance statistics (Eq. 13–14) are taken of: the perturbed frames (chain
    joint indices, in ``layout`` order), the θ layout, and a known part of every Σ_E (d, d),
    e.g. a measured noise covariance, or None."""

    frames: tuple[int, ...]
    layout: CovarianceLayout
    known: FloatArray | None = None
    noise_name: str = "noise"

    @property
    def frame_columns(self) -> list[int]:
        """Stacked-Jacobian columns ``6f + i`` of every frame f, frame by frame."""
        return [6 * f + i for f in self.frames for i in range(6)]

    def slots(self, position: dict[int, int]) -> IntArray:
        """For each chain-frame entry of θ, the position of its column ``A_f[:, i]`` in a
        stack whose column c sits at ``position[c]``."""
        layout = self.layout
        chain = np.flatnonzero(~layout.is_noise)
        return np.array(
            [position[6 * self.frames[layout.param_frame[p]] + layout.param_row[p]] for p in chain],
            dtype=np.intp,
        )


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

    @classmethod
    def empty(cls, spec: CovarianceSpec, *, sandwich: bool) -> CovarianceSums:
        shape = (len(spec.frames), spec.layout.residual_dim, 6)
        return cls(
            None if sandwich else empty_statistics(spec.layout, spec.known),
            np.zeros((spec.layout.n_params,) * 2) if sandwich else None,
            np.zeros(shape),
            np.full(shape, np.inf),
            np.full(shape, -np.inf),
            0,
        )

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


@dataclass(frozen=True)
class FitSums:
    """What one fit pass returns per chunk (and, added, for the recording): the normal
    equations over the kept columns (weighted), the spread of the unweighted residuals and
    the pose errors of the used samples, the 0-based rows the outlier rule dropped, and —
    when asked for — the covariance statistics at the same point."""

    normal: NormalEquations
    spread: ResidualSpread
    errors: ErrorSums
    removed_rows: NDArray[np.int64]
    covariance: CovarianceSums | None = None

    def __add__(self, other: FitSums) -> FitSums:
        covariance = self.covariance
        if covariance is None or other.covariance is None:
            covariance = covariance or other.covariance
        else:
            covariance = covariance + other.covariance
        return FitSums(
            self.normal + other.normal,
            self.spread + other.spread,
            self.errors + other.errors,
            np.concatenate([self.removed_rows, other.removed_rows]),
            covariance,
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


def parameters_key(params: ChainParameters) -> bytes:
    """A digest of the parameter values: residuals kept from a pass are reused only at the
    very same point."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(np.ascontiguousarray(params.links).tobytes())
    digest.update(np.ascontiguousarray(params.compliance_rad_per_nm).tobytes())
    return digest.digest()


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
    rule: OutlierRule | None
    collect_removed: bool = False
    keep_residuals: bool = False
    covariance: CovarianceSpec | None = None


@dataclass(frozen=True, eq=False)
class _FitPass:
    problem: StreamProblem
    evaluations: tuple[_Evaluation, ...]


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
        problem.chain, rule.params, motions, loads_nm, residual_dim=problem.residual_dim
    )
    residual = pose_residuals(sweep, rotation, translation).residual
    return within_spread(residual.T, rule.mean, rule.std, rule.sigma)


def _used(
    problem: StreamProblem,
    rule: OutlierRule | None,
    ref: Any,
    index: int,
    blocks: list[_Block],
) -> BoolArray | None:
    """Keep mask of block ``index`` of chunk ``ref`` (prepared as ``blocks``) under ``rule``,
    None for every sample (cached per process). The residuals a pass at ``rule.params`` left
    behind are used when there are any (the rule's point is the first fit's last pass), else
    one forward sweep per block."""
    if rule is None:
        return None
    key = (problem.token, ref, rule.token)
    with _LOCK:
        masks = _MASKS.get(key)
        kept = _RESIDUALS.pop((problem.token, ref), None)
    if masks is None:
        if kept is not None and kept[0] == parameters_key(rule.params):
            masks = [within_spread(r.T, rule.mean, rule.std, rule.sigma) for r in kept[1]]
        else:
            masks = [
                rule_mask(problem, rule, b.motions, b.loads_nm, b.rotation, b.translation)
                for b in blocks
            ]
        with _LOCK:
            _MASKS[key] = masks
    mask = masks[index]
    return None if mask.all() else mask


def fit_chunk(request: _FitPass, ref: Any) -> tuple[FitSums, ...]:
    """Eq. (9–10) sums of one chunk at each evaluation's point: FK, Jacobian columns,
    residuals (and the covariance statistics where asked), block by block."""
    problem = request.problem
    blocks = _prepare(problem, ref)
    out = []
    for evaluation in request.evaluations:
        parts = []
        residuals = []
        for index, block in enumerate(blocks):
            used = _used(problem, evaluation.rule, ref, index, blocks)
            part, residual = _evaluate_block(problem, evaluation, block, used)
            parts.append(part)
            residuals.append(residual)
        if evaluation.keep_residuals and _PREPARED.get((problem.token, ref)) is blocks:
            with _LOCK:  # only beside a cached chunk: without the cache memory stays flat
                _RESIDUALS[(problem.token, ref)] = (parameters_key(evaluation.params), residuals)
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
    problem: StreamProblem, evaluation: _Evaluation, block: _Block, used: BoolArray | None
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
        frame_range = _frame_range(spec, columns, plan.position, used)
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
        covariance = _covariance_sums(
            spec, columns, plan.rows, plan.position, fitted, used, frame_range, n_used
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


def _frame_range(
    spec: CovarianceSpec, columns: FloatArray, position: dict[int, int], used: BoolArray | None
) -> tuple[FloatArray, FloatArray]:
    """Per entry of the frame Jacobians (F·6, d), the minimum and maximum over the used
    samples of a block (columns (C, d, b), not yet zeroed): the dropped samples' columns are
    first overwritten with a used sample's, so plain reductions give the answer."""
    frames = np.array([position[c] for c in spec.frame_columns], dtype=np.intp)
    if used is not None:
        if not used.any():
            shape = (frames.size, columns.shape[1])
            return np.full(shape, np.inf), np.full(shape, -np.inf)
        columns[:, :, ~used] = columns[:, :, [int(np.argmax(used))]]
    return columns.min(axis=2)[frames], columns.max(axis=2)[frames]


def _covariance_sums(
    spec: CovarianceSpec,
    columns: FloatArray,
    leading_rows: IntArray,
    position: dict[int, int],
    residual: FloatArray,
    used: BoolArray | None,
    frame_range: tuple[FloatArray, FloatArray],
    n_used: int,
) -> CovarianceSums:
    """Eq. (13–14) statistics and the frame-Jacobian range of one block from its batch-last
    Jacobian columns (C, d, b) (column c at ``position[c]``; the dropped samples' zeroed) and
    residuals (d, b), m and rad, zero where dropped; ``used`` (b,) or None for all;
    ``frame_range``: :func:`_frame_range`."""
    layout = spec.layout
    d = residual.shape[0]
    frames = np.array([position[c] for c in spec.frame_columns], dtype=np.intp)

    def frame_view(values: FloatArray) -> FloatArray:  # (F·6, d) -> (F, d, 6)
        return values.reshape(len(spec.frames), 6, d).transpose(0, 2, 1)

    total = columns.sum(axis=2)[frames]
    if layout.structure == "diag":
        slots = spec.slots(position)
        stats = diag_statistics_batch_last(
            columns,
            slots,
            layout,
            residuals=residual,
            known_covariance=spec.known,
            used=used,
            rows=leading_rows[slots],
            zeroed=True,
        )
    else:
        keep = slice(None) if used is None else used
        jacobians = columns[frames][:, :, keep].reshape(len(spec.frames), 6, d, -1)
        stats = build_moment_statistics(
            np.ascontiguousarray(residual[:, keep].T),
            np.ascontiguousarray(jacobians.transpose(3, 0, 2, 1)),
            layout,
            known_covariance=spec.known,
        )
    low, high = frame_range
    return CovarianceSums(stats, None, frame_view(total), frame_view(low), frame_view(high), n_used)


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


def scaled_condition_number(gram: FloatArray) -> float:
    """Condition number of the unit-norm-scaled columns from their Gram (p, p)."""
    norms = np.sqrt(np.clip(np.diag(gram), 1e-300, None))
    eigenvalues = np.linalg.eigvalsh(gram / np.outer(norms, norms))
    return float(np.sqrt(eigenvalues[-1] / max(eigenvalues[0], 1e-300)))


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
    rule: OutlierRule | None = None,
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
    rule: OutlierRule | None = None
    keep_residuals: bool = False
    covariance: CovarianceSpec | None = None


@dataclass
class PassCount:
    """Passes over the data so far (a pass may serve several fits)."""

    passes: int = 0


def fit_streamed_together(
    problem: StreamProblem,
    executor: Executor,
    requests: Sequence[FitRequest],
    count: PassCount | None = None,
) -> list[StreamedFit]:
    """Gauss–Newton (Eq. 10, :func:`solver.calibration.gauss_newton_iteration`) for each
    request, in lockstep: every pass over the data evaluates the next point of every fit
    still running, so fits that do not depend on each other (the refit and the "before" fit)
    share their passes. Each fit's iterates are exactly those it would take alone."""
    count = count if count is not None else PassCount()
    started = time.perf_counter()
    chain = problem.chain
    iterations: list[
        Generator[ChainParameters, tuple[NormalEquations, FitSums], GaussNewtonRun[FitSums]]
    ] = [gauss_newton_iteration(chain, r.start, r.keep, r.options) for r in requests]
    pending: list[ChainParameters | None] = [next(it) for it in iterations]
    runs: list[GaussNewtonRun[FitSums] | None] = [None] * len(requests)
    first_sums: list[FitSums | None] = [None] * len(requests)
    passes = [0] * len(requests)
    while any(p is not None for p in pending):
        active = [i for i, p in enumerate(pending) if p is not None]
        evaluations = []
        for i in active:
            request, point = requests[i], pending[i]
            assert point is not None
            evaluations.append(
                _Evaluation(
                    point,
                    request.keep,
                    request.options.rotation_weight_m_per_rad,
                    request.rule,
                    collect_removed=request.rule is not None and passes[i] == 0,
                    keep_residuals=request.keep_residuals,
                    covariance=request.covariance if passes[i] > 0 else None,
                )
            )
        results = _run_pass(problem, executor, evaluations)
        count.passes += 1
        for i, sums in zip(active, results, strict=True):
            passes[i] += 1
            if first_sums[i] is None:
                first_sums[i] = sums
            try:
                pending[i] = iterations[i].send((sums.normal, sums))
            except StopIteration as done:
                runs[i], pending[i] = done.value, None
    names = parameter_names(chain)
    fits = []
    for request, run, first, n_passes in zip(requests, runs, first_sums, passes, strict=True):
        assert run is not None and first is not None
        sums = dataclasses.replace(run.payload, removed_rows=first.removed_rows)
        fits.append(
            StreamedFit(
                params=run.params,
                estimated=[names[i] for i in request.keep],
                removed=removed_names(names, request.keep),
                standard_errors=parameter_standard_errors(run.normal),
                rank=int(request.keep.size),
                condition_number=scaled_condition_number(run.normal.gram),
                iterations=run.iterations,
                converged=run.converged,
                cost_history=run.cost_history,
                sums=sums,
                passes=n_passes,
                elapsed_s=time.perf_counter() - started,
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
    rule: OutlierRule | None = None,
) -> StreamedFit:
    """Gauss–Newton (Eq. 10) over the columns ``keep`` from ``start``, each iterate's normal
    equations summed over the chunks; samples failing ``rule`` are left out (their rows are
    collected on the first pass)."""
    return fit_streamed_together(problem, executor, [FitRequest(start, keep, options, rule)])[0]


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


def _warm_start_task(
    shared: tuple[StreamProblem, HeadSample], options: FitOptions
) -> tuple[ChainParameters, IntArray]:
    return warm_start(*shared, options)


def warm_starts(
    problem: StreamProblem,
    executor: Executor,
    head: HeadSample,
    options: Sequence[FitOptions],
) -> list[tuple[ChainParameters, IntArray]]:
    """:func:`warm_start` for each of ``options`` on the executor's workers, side by side
    (the same numbers as one after the other on the driver)."""
    return executor.map(_warm_start_task, (problem, head), list(options))


# --- streamed covariance calibration (moment matching, Eq. 13–14) ---------------------------


def covariance_spec(
    problem: StreamProblem,
    frame_names: Sequence[str],
    frame_index: Sequence[int],
    *,
    structure: Structure = "diag",
    noise_covariance: FloatArray | None = None,
    noise_name: str = "noise",
    free_axes: Mapping[str, Sequence[str]] | None = None,
) -> CovarianceSpec:
    """The covariance statistics to take of ``problem``: frames ``frame_names`` perturbing
    the chain joints ``frame_index``, the noise frame (or a known noise covariance, 6×6 or
    d×d), diagonal or full Σ; ``free_axes`` as in :func:`make_layout`."""
    d = problem.residual_dim
    known = known_noise_covariance(noise_covariance, d)
    layout = make_layout(
        frame_names,
        d,
        structure=structure,
        include_noise=known is None,
        noise_name=noise_name,
        free_axes=free_axes,
    )
    return CovarianceSpec(tuple(int(f) for f in frame_index), layout, known, noise_name)


@dataclass(frozen=True, eq=False)
class _CovariancePass:
    problem: StreamProblem
    params: ChainParameters
    spec: CovarianceSpec
    rule: OutlierRule | None
    theta: FloatArray | None  # None: statistics pass; else the sandwich pass at θ
    stride: int = 1  # sandwich pass: every stride-th row of the recording


def covariance_chunk(request: _CovariancePass, ref: Any) -> CovarianceSums:
    """Residuals and frame Jacobians ``A_f = Ad_{B_f}⁻¹`` (rows d) of one chunk at the
    calibrated parameters, reduced to Eq. (14) statistics or, given θ, the sandwich meat
    (of every ``stride``-th row: only those rows are swept)."""
    problem, spec = request.problem, request.spec
    d = problem.residual_dim
    total = CovarianceSums.empty(spec, sandwich=request.theta is not None)
    blocks = _prepare(problem, ref)
    columns = spec.frame_columns
    position = {c: s for s, c in enumerate(columns)}
    for index, block in enumerate(blocks):
        used = _used(problem, request.rule, ref, index, blocks)
        chosen = None
        if request.theta is not None:  # sandwich pass: only its rows are swept
            rows = block.first_row + np.arange(block.n)
            chosen = np.flatnonzero((rows % request.stride == 0) & (True if used is None else used))
            if not chosen.size:
                continue
            block = block.subset(chosen)
        sweep = sweep_chain(
            problem.chain,
            request.params,
            block.motions,
            block.loads_nm,
            residual_dim=d,
            columns=columns,
        )
        assert sweep.columns is not None and sweep.leading_rows is not None
        if request.theta is not None and chosen is not None:
            jacobians = sweep.columns.reshape(len(spec.frames), 6, d, -1).transpose(3, 0, 2, 1)
            meat = moment_sandwich_meat(
                request.theta,
                np.ascontiguousarray(jacobians),
                spec.layout,
                known_covariance=spec.known,
            )
            empty = CovarianceSums.empty(spec, sandwich=True)
            total = total + dataclasses.replace(empty, meat=meat, n=int(chosen.size))
            continue
        residual = pose_residuals(sweep, block.rotation, block.translation).residual
        frame_range = _frame_range(spec, sweep.columns, position, used)
        n_used = block.n
        if used is not None:
            residual[:, ~used] = 0.0
            sweep.columns[:, :, ~used] = 0.0
            n_used = int(np.count_nonzero(used))
        total = total + _covariance_sums(
            spec, sweep.columns, sweep.leading_rows, position, residual, used, frame_range, n_used
        )
    return total


def streamed_covariance_sums(
    problem: StreamProblem,
    executor: Executor,
    params: ChainParameters,
    spec: CovarianceSpec,
    rule: OutlierRule | None = None,
    *,
    theta: FloatArray | None = None,
    stride: int = 1,
) -> CovarianceSums:
    """One pass: Eq. (13–14) statistics (``theta`` None) or the sandwich meat at ``theta`` (of
    every ``stride``-th row), and the Jacobian range, of ``spec``'s frames at ``params``,
    summed over chunks."""
    request = _CovariancePass(problem, params, spec, rule, theta, stride)
    total: CovarianceSums = functools.reduce(
        operator.add, executor.map(covariance_chunk, request, problem.refs)
    )
    return total


def estimate_covariances_streamed(
    problem: StreamProblem,
    executor: Executor,
    params: ChainParameters,
    spec: CovarianceSpec,
    *,
    solver: SolverName = "auto",
    rule: OutlierRule | None = None,
    confidence: float = 0.95,
    notes: Sequence[str] = (),
    sandwich_rows: int = 50_000,
    sums: CovarianceSums | None = None,
    count: PassCount | None = None,
) -> CovarianceEstimate:
    """Moment-matching covariance calibration (paper §IV-C, Eq. 13–14) of a streamed recording:
    the same steps as :func:`solver.covariance.estimate.estimate_covariances` with
    ``estimator="moment"``, its sums over samples taken chunk by chunk.

    ``spec`` (:func:`covariance_spec`): frames, layout and known noise; residuals and
    Jacobians in the end-effector frame ([v; w], m and rad) at ``params``; ``rule``: the
    outlier rule of the deterministic fit (the same samples are used); ``notes`` start the
    warnings; ``sums``: the statistics at ``params`` when a fit pass already took them (the
    deterministic fit's last pass), else one pass takes them.

    Standard errors need the sandwich ``Σ_n 2K̃ᵀK̃`` at θ̂, a second pass with a 6×6 whitening
    per sample; beyond ``sandwich_rows`` samples it is summed over every s-th row of the
    recording (s fixed by the row number, so independent of the chunking) and scaled by the
    ratio of counts — an unbiased estimate of the sum, for errors that need 2 digits, not 10.
    Only those rows are swept.
    """
    count = count if count is not None else PassCount()
    layout = spec.layout
    if sums is None:
        sums = streamed_covariance_sums(problem, executor, params, spec, rule)
        count.passes += 1
    if sums.n < 2:
        raise CalibrationError(f"covariance calibration needs at least 2 samples, got {sums.n}")
    assert sums.stats is not None
    stats = sums.stats
    if not (np.all(np.isfinite(stats.gram)) and np.all(np.isfinite(stats.cross))):
        raise CalibrationError("residuals or frame Jacobians contain NaN or inf")
    report = analyse_identifiability(
        stats, rank_rtol=RANK_RTOL, weak_rtol=WEAK_RTOL, frame_jacobians=_jacobian_range(sums)
    )
    structure = layout.structure
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
        problem, executor, params, spec, rule, theta=theta, stride=stride
    )
    count.passes += 1
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
            method=SE_METHOD["moment"],
        )
    except CalibrationError as exc:
        notes.append(f"no standard errors: {exc}")
    frames, noise = frame_results(layout, theta, unc, spec.known, spec.noise_name)
    return CovarianceEstimate(
        "moment",
        structure,
        solver_used,
        sums.n,
        frames,
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
    """Everything a streamed calibration produced; ``stage_s``: wall time per stage
    ("read": preparing every chunk, beside the first warm start; "warm_start": the refit's
    and "before" fit's warm starts; "deterministic": the streamed fits); ``passes``: passes
    over the data; ``covariance``: the covariance statistics at ``fit.params`` when a fit
    pass took them along (None: the covariance stage needs a pass for them)."""

    n_rows: int
    first: StreamedFit
    fit: StreamedFit
    baseline: StreamedFit
    rule: OutlierRule | None
    removed_rows: NDArray[np.int64]
    stage_s: dict[str, float]
    passes: int
    covariance: CovarianceSums | None = None


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
    covariance: CovarianceSpec | None = None,
    progress: Callable[[str], None] | None = None,
) -> StreamedCalibration:
    """Deterministic calibration of a streamed recording: warm start on the head rows, the
    first fit, the 2σ rule, the refit on the kept samples and the "before" fit (measurement
    frame and tool on the nominal robot), as :func:`service.pipeline.calibrate` does in memory.

    Passes: one to prepare the chunks (while the driver fits the head rows), the first fit's
    (its last pass leaves the residuals the 2σ rule is applied to), then the refit's and the
    "before" fit's together; with ``covariance`` the refit's passes after the first also take
    the covariance statistics (:attr:`StreamedCalibration.covariance`). ``progress(stage)`` is
    called as "read", "fit" (the first fit) and "baseline" (the refit and the "before" fit)
    end.
    """
    report = progress or (lambda stage: None)
    count = PassCount()
    clock = time.perf_counter()
    scanning = executor.map_async(_count_chunk, problem, problem.refs)
    head = read_head(problem, settings.warm_start_rows)
    start, keep = warm_start(problem, head, options)
    if settings.outlier_sigma is None:
        baseline_start, baseline_keep = warm_start(problem, head, baseline_options)
    n_rows = int(sum(scanning.result()))
    count.passes += 1
    check_sample_count(problem.chain, n_rows, position_only=problem.position_only, options=options)
    stage = {"read": time.perf_counter() - clock, "warm_start": 0.0}
    report("read")
    clock = time.perf_counter()
    rule = None
    if settings.outlier_sigma is None:
        first, baseline = fit_streamed_together(
            problem,
            executor,
            [
                FitRequest(start, keep, options, covariance=covariance),
                FitRequest(baseline_start, baseline_keep, baseline_options),
            ],
            count,
        )
        fit = first
        report("fit")
    else:
        (first,) = fit_streamed_together(
            problem, executor, [FitRequest(start, keep, options, keep_residuals=True)], count
        )
        report("fit")
        spread = first.sums.spread
        rule = OutlierRule(first.params, spread.mean, spread.std, settings.outlier_sigma)
        warm = time.perf_counter()
        used_head = head.kept_by(problem, rule)
        (refit_start, refit_keep), (baseline_start, baseline_keep) = warm_starts(
            problem, executor, used_head, [options, baseline_options]
        )
        stage["warm_start"] = time.perf_counter() - warm
        fit, baseline = fit_streamed_together(
            problem,
            executor,
            [
                FitRequest(refit_start, refit_keep, options, rule, covariance=covariance),
                FitRequest(baseline_start, baseline_keep, baseline_options, rule),
            ],
            count,
        )
    stage["deterministic"] = time.perf_counter() - clock - stage["warm_start"]
    report("baseline")
    removed = fit.sums.removed_rows if rule is not None else np.zeros(0, dtype=np.int64)
    return StreamedCalibration(
        n_rows,
        first,
        fit,
        baseline,
        rule,
        np.sort(removed),
        stage,
        count.passes,
        fit.sums.covariance,
    )
