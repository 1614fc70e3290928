"""Evaluation and Gauss–Newton fit of a model = geometry + a set of library terms.

The pose model extends paper Eq. (7)::

    X(q) = Exp(Σ_d f_d(t) δ_d) · Π_i [ L_i · V_i · Exp(s_i (q_i + Σ_a c_a φ_a)) ] · L_{k+1}

with deflection axes ``a`` (joint axis or virtual axes V_i ⟂ it) driven by features ``φ_a``
(:mod:`solver.discovery.features`), an optional drift ``δ_d`` of the measurement frame (left,
measurement-frame twist), and the sensor's depth reading scaled last. Gravity features depend
on the gravity direction (base tilt) and payload mass, which are terms too.

Every column is analytic: link corrections ``J_i = Ad(B_i)^-1`` and deflection axes come from
:func:`solver.kinematics.evaluate_chain` on the chain with the term axes as compliance axes
(zero-coefficient axes give candidate columns without changing the pose); payload and tilt
columns are ``Σ_a c_a g_a ∂φ_a/∂θ``, obtained the same way with the derivative features; the
drift column is ``Ad(X)^-1 f(t)``; the depth column is the EE-frame image of the position shift.
Rows are whitened by a per-block noise scale (translation, rotation) estimated from the
residuals with the degrees of freedom the fit used (hat-matrix trace per block).

Measurement models (issue 15; :mod:`solver.measurement.models`): the residual of a row is the
model's at the predicted tip pose and its own unknowns (socket points, marker offsets), and
every column above — a tip-local twist (6 rows) — goes through the model's map
``M`` (d, 6) of :meth:`~solver.measurement.models.MeasurementModel.at_tip`; the model's unknowns
are nuisance columns beside the link corrections, the links it cannot see are left out, and
its extra equations (known socket distances) hold exactly in every Gauss–Newton step (the
step is taken in the null space of their Jacobian). For pose and position rows ``M`` is the
first d rows of I₆ (Eq. 9): exactly the columns above, in every test and every reported
covariance. Only the Gauss–Newton step of pose rows is taken on the residual's exact Jacobian,
``J_l⁻¹(r)`` times those columns (:func:`fit_model`): Eq. 9's columns are it to O(|r|), and
near the minimum their step promised ~1e-8 of the cost that the cost did not deliver.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
import scipy.linalg

from solver import lie
from solver.arrays import BoolArray, FloatArray, IntArray
from solver.calibration import frame_columns
from solver.discovery.features import DiscoveryData, FeatureBank, axis_of
from solver.discovery.library import Term, drift_feature
from solver.errors import CalibrationError
from solver.kinematics import ChainParameters, evaluate_chain, pose_residual_map
from solver.measurement.models import ModelParameters as MeasuredParameters
from solver.measurement.models import chain_column_count, seen_from_sensor
from solver.measurement.pose import initial_parameters
from solver.model import ComplianceAxis, KinematicChain
from solver.pivoting import tiered_pivoted_qr
from solver.simulate import depth_direction

RANK_TOLERANCE = 1e-7
# A nuisance direction (link correction, socket point, marker offset) the recording pins down
# no better than this (standard error, rad or m) stays at its start: Gauss–Newton's
# linearisation does not hold over such a range (e.g. the tilt of the last joint's axis when
# a ball in a socket sits on that axis).
NUISANCE_RANGE = 0.1


@dataclass(frozen=True, eq=False)
class Context:
    """Everything fixed during one discovery: the probe chain, the data, the features."""

    chain: KinematicChain
    data: DiscoveryData
    bank: FeatureBank

    @classmethod
    def build(cls, probe: KinematicChain, data: DiscoveryData) -> Context:
        return cls(probe, data, FeatureBank(probe, data))

    @property
    def all_rows(self) -> IntArray:
        return np.arange(self.data.n_samples)


@dataclass(frozen=True)
class ModelParameters:
    """Link placements (k+1, 4, 4), the concatenated term coefficients θ (p,) and the
    measurement model's own unknowns ``extra`` (E,) (none for pose and position rows)."""

    links: FloatArray
    theta: FloatArray
    extra: FloatArray = field(default_factory=lambda: np.zeros(0))

    def with_terms(self, terms: tuple[Term, ...], values: dict[str, FloatArray]) -> ModelParameters:
        """θ laid out for ``terms``; coefficients taken from ``values`` by key, zero otherwise."""
        theta = np.concatenate(
            [np.asarray(values.get(t.key, np.zeros(t.size)), dtype=float) for t in terms]
            or [np.zeros(0)]
        )
        return replace(self, theta=theta)


def slices(terms: tuple[Term, ...]) -> list[slice]:
    out, start = [], 0
    for t in terms:
        out.append(slice(start, start + t.size))
        start += t.size
    return out


def by_key(terms: tuple[Term, ...], theta: FloatArray) -> dict[str, FloatArray]:
    return {t.key: theta[s] for t, s in zip(terms, slices(terms), strict=True)}


@dataclass(frozen=True, eq=False)
class Design:
    """Residuals and columns at one parameter point, for ``rows`` of the recording.

    ``residual`` (n, d) unweighted, m and rad, EE frame (the measurement model's frame for
    other rows). Columns (n, d, ·): ``links`` the 6 local twist components of every L_i, then
    the measurement model's own unknowns (the nuisance columns); ``terms`` θ in model order;
    ``candidates`` per key; ``unit`` the column per unit angle of a requested axis (plots,
    pose design).
    """

    rows: IntArray
    pose: FloatArray
    residual: FloatArray
    links: FloatArray
    terms: FloatArray
    candidates: dict[str, FloatArray] = field(default_factory=dict)
    unit: dict[tuple[int, str], FloatArray] = field(default_factory=dict)

    def restricted(self, rows: IntArray) -> Design | None:
        """This design on ``rows`` (sorted), a subset of its own sorted rows, without
        evaluating again; None when one of ``rows`` is not among them. Valid where each
        sample is evaluated on its own (pose rows: :func:`design_on`)."""
        at = np.searchsorted(self.rows, rows)
        if np.any(at >= self.rows.size) or not np.array_equal(
            self.rows[np.minimum(at, self.rows.size - 1)], rows
        ):
            return None
        return Design(
            rows=rows,
            pose=self.pose[at],
            residual=self.residual[at],
            links=self.links[at],
            terms=self.terms[at],
            candidates={k: v[at] for k, v in self.candidates.items()},
            unit={k: v[at] for k, v in self.unit.items()},
        )


def _globals(
    terms: tuple[Term, ...], theta: FloatArray, data: DiscoveryData
) -> tuple[FloatArray, float]:
    """Gravity vector (base frame) and extra payload implied by the model's global terms."""
    gravity = np.asarray(data.gravity_base, dtype=float)
    payload = 0.0
    for t, s in zip(terms, slices(terms), strict=True):
        if t.effect == "gravity_direction":
            tilt = np.r_[theta[s], 0.0]
            gravity = lie.so3_exp(tilt) @ gravity
        elif t.effect == "payload_mass":
            payload += float(theta[s][0])
    return gravity, payload


def evaluate(
    ctx: Context,
    terms: tuple[Term, ...],
    params: ModelParameters,
    rows: IntArray,
    candidates: tuple[Term, ...] = (),
    unit_axes: tuple[tuple[int, str], ...] = (),
    *,
    from_sensor: bool = True,
) -> Design:
    """Residuals and all columns (see module docstring) in one chain sweep. A measurement
    whose sensor rides on the chain (:attr:`~solver.measurement.models.MeasurementModel.
    sensor_joint_index`) sees the tip from there (:func:`seen_from_sensor`), columns included;
    ``from_sensor=False`` gives the columns as a sensor fixed in the measurement frame would
    see them (the reference of :func:`unseen_terms`)."""
    data, bank, chain = ctx.data, ctx.bank, ctx.chain
    d = data.rows if data.is_pose else 6  # rows of the columns before the measurement map
    gravity, extra_payload = _globals(terms, params.theta, data)
    axes: list[ComplianceAxis] = []
    coefficients: list[float] = []
    features: list[FloatArray] = []

    def add(joint: int, direction: str, feature: str, coefficient: float) -> int:
        axes.append(axis_of(chain, joint, direction))
        coefficients.append(coefficient)
        features.append(bank.column(feature, gravity, extra_payload)[rows])
        return len(axes) - 1

    term_axes: list[list[int]] = []
    gravity_axes: list[tuple[int, float, str]] = []  # (axis index, coefficient, probe axis name)
    for t, s in zip(terms, slices(terms), strict=True):
        indices = []
        for spec, value in zip(t.axes, params.theta[s], strict=False):
            indices.append(add(spec.joint_index, spec.direction, spec.feature, float(value)))
            if spec.gravity_driven:
                gravity_axes.append((indices[-1], float(value), spec.feature[4:]))
        term_axes.append(indices)
    wants_derivatives = any(
        t.effect in ("payload_mass", "gravity_direction") for t in (*terms, *candidates)
    )
    derivative_axes: dict[str, list[tuple[int, float]]] = {"m": [], "x": [], "y": []}
    if wants_derivatives:
        for index, value, name in gravity_axes:
            axis = axes[index]
            direction = "joint" if axis.is_joint_axis else name.split(".")[-1]
            for label in derivative_axes:
                derivative_axes[label].append(
                    (add(axis.joint_index, direction, f"dtau_{label}:{name}", 0.0), value)
                )
    candidate_axes = {
        c.key: [add(s.joint_index, s.direction, s.feature, 0.0) for s in c.axes]
        for c in candidates
        if c.axes
    }
    unit_index = {u: add(u[0], u[1], "one", 0.0) for u in unit_axes}

    augmented = replace(chain, compliance_axes=tuple(axes))
    q = data.joint_positions[rows]
    loads = np.column_stack(features) if features else np.zeros((rows.size, 0))
    chain_params = ChainParameters(params.links, np.array(coefficients))
    evaluation = evaluate_chain(augmented, chain_params, q, loads)
    sensor = None if data.is_pose or not from_sensor else data.model.sensor_joint_index
    if sensor is not None:  # a sensor on the chain: the tip as it sees it, every column too
        evaluation = seen_from_sensor(augmented, chain_params, q, loads, sensor, evaluation)
    comp = evaluation.compliance_jacobians[:, :, :d]  # (n, n_axes, d)
    pose = evaluation.pose

    drift = np.zeros((rows.size, 6))
    for t, s in zip(terms, slices(terms), strict=True):
        if t.effect == "thermal_drift" and t.joint_index is None:
            drift += (
                bank.column(drift_feature(t), gravity, extra_payload)[rows, None] * params.theta[s]
            )
    if np.any(drift):
        pose = lie.se3_exp(drift) @ pose
    before_depth = pose
    depth_shift = np.zeros((rows.size, 3))
    for t, s in zip(terms, slices(terms), strict=True):
        if t.effect == "depth_scale":
            depth_shift += float(params.theta[s][0]) * depth_direction(before_depth, t.variant)
    if np.any(depth_shift):
        pose = pose.copy()
        pose[:, :3, 3] += depth_shift

    def global_columns(t: Term) -> FloatArray:
        if t.effect == "payload_mass":
            return _weighted_sum(comp, derivative_axes["m"])[..., None]
        if t.effect == "gravity_direction":
            return np.stack([_weighted_sum(comp, derivative_axes[a]) for a in ("x", "y")], axis=-1)
        if t.effect == "depth_scale":
            shift = depth_direction(before_depth, t.variant)
            local = np.einsum("nji,nj->ni", before_depth[:, :3, :3], shift)
            column = np.zeros((rows.size, 6))
            column[:, :3] = local
            return column[:, :d, None]
        if t.effect == "thermal_drift" and t.joint_index is None:
            shape = bank.column(drift_feature(t), gravity, extra_payload)[rows]
            return (lie.adjoint_inverse(before_depth) * shape[:, None, None])[:, :d, :]
        raise ValueError(f"term {t.key} has no global columns")

    def columns_of(t: Term, indices: list[int] | None) -> FloatArray:
        if t.axes:
            assert indices is not None
            return np.stack([comp[:, i] for i in indices], axis=-1)
        return global_columns(t)

    n_links = params.links.shape[0]
    link_cols = evaluation.link_jacobians[:, :, :d, :].transpose(0, 2, 1, 3)
    link_cols = link_cols.reshape(rows.size, d, 6 * n_links)
    term_cols = [columns_of(t, idx) for t, idx in zip(terms, term_axes, strict=True)]
    terms_all = np.concatenate(term_cols, axis=2) if term_cols else np.zeros((rows.size, d, 0))
    candidate_cols = {c.key: columns_of(c, candidate_axes.get(c.key)) for c in candidates}
    unit = {u: comp[:, i] for u, i in unit_index.items()}
    if data.is_pose:
        return Design(
            rows=rows,
            pose=pose,
            residual=data.pose_model.residuals(pose, data.measured_pose[rows]),
            links=link_cols,
            terms=terms_all,
            candidates=candidate_cols,
            unit=unit,
        )
    model = data.model
    residual, tip_map, extra_cols = model.at_tip(pose, params.extra, data.measurement_rows(rows))
    visible = model.visible_columns(chain)[: 6 * n_links]

    def mapped(columns: FloatArray) -> FloatArray:
        """Tip-twist columns (n, 6, ·) -> residual columns (n, d, ·)."""
        return np.asarray(tip_map @ columns, dtype=np.float64)

    return Design(
        rows=rows,
        pose=pose,
        residual=residual,
        links=np.concatenate([mapped(link_cols) * visible, extra_cols], axis=2),
        terms=mapped(terms_all),
        candidates={k: mapped(v) for k, v in candidate_cols.items()},
        unit={u: mapped(v[:, :, None])[:, :, 0] for u, v in unit.items()},
    )


UNSEEN_FRACTION = 1e-9
"""A library term is unseen by a measurement when at most this fraction of each of its columns
is left once the model's own columns are projected out: rounding of a cancellation (a sensor
on the chain and a term before it cancel to ~1e-15), not a small effect."""


@dataclass(frozen=True)
class Unseen:
    """A library term the rows cannot see (:func:`unseen_terms`): the largest fraction of one
    of its columns left after the model's own columns (``left``) and before them
    (``cancelled``: at most :data:`UNSEEN_FRACTION` when the measurement itself cancels it,
    e.g. a term before a sensor on the chain; larger when the model's own columns absorb it
    on these rows)."""

    term: Term
    left: float
    before_own_columns: float

    @property
    def cancelled(self) -> bool:
        return self.before_own_columns <= UNSEEN_FRACTION


def unseen_terms(ctx: Context, fit: ModelFit, library: list[Term]) -> dict[str, Unseen]:
    """Library terms the recording cannot see at all, by key.

    Judged on every sample of the recording, not only on the fit's rows: what the
    measurement can see is a property of the measurement, and a term the screen's rows
    cannot see may be what pushed the other samples out (a 2 mrad load backlash on the
    platonics Panda's panda_joint4 pushes out the three samples whose load has the other sign;
    on the rest its column is a constant offset).

    For each column ``c`` of a term: ``|P⊥ W c| / |W c₀|``, with ``W`` the fit's whitening,
    ``P⊥`` the projection off the fit's nuisance columns (link corrections the rows identify
    and the measurement's own unknowns: sensor mount, sockets, marker offsets) and ``c₀`` the
    same column as a sensor fixed in the measurement frame would see it
    (:func:`evaluate` with ``from_sensor=False``; ``c₀ = c`` for every measurement whose
    sensor does not ride on the chain). A term is unseen when that is at most
    :data:`UNSEEN_FRACTION` for every column: a term at or before a chain-borne sensor moves
    the sensor and the tip alike, so its ``c`` cancels — decided here by its columns, not by
    where it sits. Columns with ``c₀ = 0`` (not excited) are not judged; a term none of whose
    columns is excited is left to the library's own rules. Pose and position rows see every
    term's effect on the end effector (``M = I``): nothing is judged for them ({})."""
    if ctx.data.is_pose or not library:
        return {}
    candidates = tuple(library)
    rows = ctx.all_rows
    seen = evaluate(ctx, fit.terms, fit.params, rows, candidates)
    fixed = evaluate(ctx, fit.terms, fit.params, rows, candidates, from_sensor=False)
    n, d = rows.size, ctx.data.rows
    basis = orthonormal_basis(whitened(fit.nuisance(seen.links), fit.weights).reshape(n * d, -1))
    out: dict[str, Unseen] = {}
    for term in library:
        columns = whitened(seen.candidates[term.key], fit.weights).reshape(n * d, -1)
        left = np.linalg.norm(columns - basis @ (basis.T @ columns), axis=0)
        scale = np.linalg.norm(
            whitened(fixed.candidates[term.key], fit.weights).reshape(n * d, -1), axis=0
        )
        excited = scale > 0.0
        if not np.any(excited):
            continue
        fraction = float(np.max(left[excited] / scale[excited]))
        if fraction <= UNSEEN_FRACTION:
            before = np.linalg.norm(columns, axis=0)
            out[term.key] = Unseen(term, fraction, float(np.max(before[excited] / scale[excited])))
    return out


def _weighted_sum(comp: FloatArray, pairs: list[tuple[int, float]]) -> FloatArray:
    out = np.zeros((comp.shape[0], comp.shape[2]))
    for index, coefficient in pairs:
        out += coefficient * comp[:, index]
    return out


# --- fitting -------------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class ModelFit:
    """A converged fit of ``terms`` on ``rows``.

    ``weights`` (d,) multiply residual components (1/σ per block); ``jacobian`` (n·d, p) the
    whitened columns estimated (kept nuisance columns — links and the measurement model's
    unknowns — times ``nuisance_map``, then θ); ``covariance`` (p_θ, p_θ) of θ, the larger
    (per entry) of the classical and the per-sample cluster-robust sandwich estimate.
    ``nuisance_map`` (kept, kept − c): a basis of the kept nuisance directions the model's c
    extra equations (known socket distances) leave free; None without such equations.
    """

    terms: tuple[Term, ...]
    params: ModelParameters
    rows: IntArray
    weights: FloatArray
    design: Design
    kept_links: IntArray
    jacobian: FloatArray
    residual_w: FloatArray
    rank: int
    cost: float
    iterations: int
    converged: bool
    covariance: FloatArray
    nuisance_map: FloatArray | None = None

    @property
    def n_nuisance(self) -> int:
        """Nuisance columns of ``jacobian`` (before θ)."""
        return self.kept_links.size if self.nuisance_map is None else self.nuisance_map.shape[1]

    def nuisance(self, links: FloatArray) -> FloatArray:
        """The nuisance columns of a design's ``links`` (n, d, ·) as in ``jacobian``."""
        kept = links[:, :, self.kept_links]
        return kept if self.nuisance_map is None else kept @ self.nuisance_map

    @property
    def dof(self) -> int:
        return int(self.residual_w.size - self.rank)

    def stderr(self) -> dict[str, FloatArray]:
        errors = np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))
        return by_key(self.terms, errors)

    def values(self) -> dict[str, FloatArray]:
        return by_key(self.terms, self.params.theta)


def whitened(values: FloatArray, weights: FloatArray) -> FloatArray:
    """Scale residual rows (axis 1) by ``weights`` (d,)."""
    return values * weights.reshape((1, -1) + (1,) * (values.ndim - 2))


def start_parameters(ctx: Context) -> ModelParameters:
    """Closed-form measurement frame and tool on the nominal geometry (solver.alignment); the
    measurement model's own start (:meth:`~solver.measurement.models.MeasurementModel.start`:
    socket points, marker offsets) for other rows."""
    data = ctx.data
    if not data.is_pose:
        model = data.model
        rows = data.measurement_rows(ctx.all_rows)
        model.check_rows(rows)
        own = model.start(ctx.chain, rows)
        return ModelParameters(own.links, np.zeros(0), own.extra)
    start = initial_parameters(
        ctx.chain,
        data.joint_positions,
        data.measured_pose,
        measurement=data.pose_model,
    )
    return ModelParameters(start.links, np.zeros(0))


def _kept_links(
    links_w: FloatArray,
    terms_w: FloatArray,
    residual_w: FloatArray,
    first: BoolArray,
    pin: bool = True,
) -> IntArray:
    """Link columns the data can identify once the term columns are in (terms take priority).

    Column-pivoted QR of the unit-norm link columns after projecting out the term columns;
    the POE redundancies (and geometry that a term explains exactly) drop out by name, and
    with ``pin`` (measurement models other than pose and position) so does a pivot whose
    standard error given the ones before it, ``s/|R_jj|`` with ``s`` the RMS whitened residual,
    exceeds :data:`NUISANCE_RANGE`. Pose and position rows keep every identifiable direction,
    as they always have: on the FR3 recording pinning a poorly determined one changes what
    discovery reports (a base flex of the wrong sign at panda_joint1 becomes visible).
    """
    norms = np.linalg.norm(links_w, axis=0)
    nonzero = np.flatnonzero(norms > 1e-12 * max(norms.max(), 1e-300))
    a = links_w[:, nonzero] / norms[nonzero]
    if terms_w.shape[1]:
        basis = orthonormal_basis(terms_w)
        a = a - basis @ (basis.T @ a)
    diagonal, pivots = tiered_pivoted_qr(a, first[nonzero], RANK_TOLERANCE)
    rank = int(np.sum(diagonal > RANK_TOLERANCE * max(diagonal[0], 1e-300)))
    scatter = np.sqrt(float(residual_w @ residual_w) / max(residual_w.size, 1))
    pinned = diagonal[:rank] * norms[nonzero][pivots[:rank]] * NUISANCE_RANGE > scatter
    return np.sort(nonzero[pivots[:rank][pinned | (not pin)]])


def orthonormal_basis(matrix: FloatArray, tolerance: float = RANK_TOLERANCE) -> FloatArray:
    """Orthonormal basis of the column space (rank-revealing SVD, unit-norm columns first)."""
    norms = np.linalg.norm(matrix, axis=0)
    scaled = matrix[:, norms > 0] / norms[norms > 0]
    if scaled.shape[1] == 0:
        return np.zeros((matrix.shape[0], 0))
    u, s, _ = np.linalg.svd(scaled, full_matrices=False)
    return u[:, s > tolerance * s[0]]


def constraint_rows(
    ctx: Context, params: ModelParameters, kept: IntArray
) -> tuple[FloatArray, FloatArray] | None:
    """The measurement model's extra equations (known socket distances) at ``params``:
    residual (c,) and their Jacobian over the ``kept`` nuisance columns (c, kept), the sign
    convention of the rows (``c(θ ⊕ δ) ≈ c − C δ``); None without any."""
    if ctx.data.is_pose:
        return None
    chain = ctx.chain
    measured = MeasuredParameters(params.links, np.zeros(len(chain.compliance_axes)), params.extra)
    residual, jacobian = ctx.data.model.constraints(chain, measured)
    if residual.size == 0:
        return None
    n_link_cols = 6 * params.links.shape[0]
    p = chain_column_count(chain)
    nuisance = np.concatenate([jacobian[:, :n_link_cols], jacobian[:, p:]], axis=1)
    return residual, nuisance[:, kept]


def _constrained_step(
    a: FloatArray,
    r: FloatArray,
    constraint: tuple[FloatArray, FloatArray] | None,
    damping: float = 0.0,
) -> FloatArray:
    """Gauss–Newton step of ``r ≈ a δ``: without constraints the least-squares step; with
    ``C δ_nuisance = c`` the step ``δ = C⁺c + N z``, N a basis of the null space of C and z the
    least-squares step of the rows in those free directions. ``damping`` λ > 0: the
    Levenberg–Marquardt step instead, ``min |r − a δ|² + λ |D δ|²`` with D the column norms
    (the constraints still met)."""
    if constraint is None:
        particular, free, reduced, target = np.zeros(a.shape[1]), None, a, r
    else:
        c, jacobian = constraint
        k = jacobian.shape[1]
        free = scipy.linalg.null_space(jacobian)  # (k, k − c)
        particular = np.zeros(a.shape[1])
        particular[:k] = np.linalg.pinv(jacobian) @ c
        reduced = np.hstack([a[:, :k] @ free, a[:, k:]])
        target = r - a @ particular
    if damping > 0.0:
        scale = np.sqrt(damping) * np.linalg.norm(reduced, axis=0)
        reduced = np.vstack([reduced, np.diag(scale)])
        target = np.r_[target, np.zeros(scale.size)]
    z = np.asarray(np.linalg.lstsq(reduced, target, rcond=None)[0], dtype=np.float64)
    if free is None:
        return z
    k = free.shape[0]
    step = particular.copy()
    step[:k] += free @ z[: free.shape[1]]
    step[k:] += z[free.shape[1] :]
    return step


def _merit(cost: float, constraint: tuple[FloatArray, FloatArray] | None, weight: float) -> float:
    """The cost with the constraints' violation (m), each weighted as a residual of the
    translation noise 1/``weight``: the line search's measure of progress. Every step meets
    the linearised constraints exactly, so the violation left is of second order in the step
    and vanishes as the fit converges."""
    if constraint is None:
        return cost
    return cost + float(np.sum((weight * constraint[0]) ** 2))


def fit_model(
    ctx: Context,
    terms: tuple[Term, ...],
    start: ModelParameters,
    rows: IntArray,
    weights: FloatArray,
    *,
    max_iterations: int = 40,
    tolerance: float = 1e-10,
    design: Design | None = None,
) -> ModelFit:
    """Gauss–Newton on the whitened residuals (Eq. 10 with the extra term columns) over the
    nuisance columns :func:`_kept_links` keeps and θ, the measurement model's known distances
    met in every step (:func:`_constrained_step`). A step that does not lower the cost (with
    the constraints' violation, :func:`_merit`) is replaced by Levenberg–Marquardt steps damped
    tenfold each time, and the damping is relaxed tenfold after each accepted step until it is
    pure Gauss–Newton again; a fit whose Gauss–Newton steps all succeed is plain Gauss–Newton.
    Pose rows step on the residual's exact Jacobian (``step_columns``): on Eq. 9's columns, a
    refit from a converged model with new noise weights was retried with damping up to 20 times
    (evaluating the chain each time) for a step the real cost never took; the fit reports Eq. 9's
    columns (``jacobian``, ``covariance``) as before.
    ``design``: :func:`evaluate` of ``terms`` at ``start`` on ``rows``, when the caller has it
    (not evaluated again)."""
    d = ctx.data.rows
    params = start
    if design is None or not np.array_equal(design.rows, rows):
        design = evaluate(ctx, terms, params, rows)
    p_terms = design.terms.shape[2]
    if start.theta.size != p_terms:
        raise ValueError("start parameters do not match the terms")
    translation_weight = float(weights[ctx.data.noise_blocks()[0]][0])

    def stacked(des: Design) -> tuple[FloatArray, FloatArray, FloatArray]:
        n = des.rows.size
        return (
            whitened(des.residual, weights).reshape(-1),
            whitened(des.links, weights).reshape(n * d, -1),
            whitened(des.terms, weights).reshape(n * d, -1),
        )

    exact_steps = ctx.data.is_pose and ctx.data.pose_model.measures_rotation

    def step_columns(des: Design, a: FloatArray) -> FloatArray:
        """The whitened columns ``a`` (n·d, p) as the residual's exact Jacobian for the
        Gauss–Newton step of pose rows: ``W J_l⁻¹(r) W⁻¹ a`` per sample (W the weights); Eq. 9's
        columns (the identity for ``J_l⁻¹``) elsewhere, and in everything the fit reports."""
        if not exact_steps:
            return a
        scaled = weights[:, None] * pose_residual_map(des.residual) / weights[None, :]
        n = des.rows.size
        return np.asarray(scaled @ a.reshape(n, d, -1), dtype=np.float64).reshape(n * d, -1)

    r, links_w, terms_w = stacked(design)
    first = frame_columns(ctx.chain, links_w.shape[1], n_compliance=0)
    kept = _kept_links(links_w, terms_w, r, first, pin=not ctx.data.is_pose)
    constraint = constraint_rows(ctx, params, kept)
    n_pinned = 0 if constraint is None else constraint[0].size
    if r.size <= kept.size - n_pinned + p_terms:
        raise CalibrationError(
            f"{rows.size} samples give {r.size} equations for "
            f"{kept.size - n_pinned + p_terms} parameters; record more configurations"
        )
    cost = float(r @ r)
    merit = _merit(cost, constraint, translation_weight)
    converged, iterations = False, 0
    carried = 0.0  # Levenberg–Marquardt damping kept from the last step (0: Gauss–Newton)
    while iterations < max_iterations:
        iterations += 1
        a = step_columns(design, np.hstack([links_w[:, kept], terms_w]))
        step = _constrained_step(a, r, constraint, carried)
        predicted = a @ step
        if float(predicted @ predicted) <= tolerance * max(cost, 1e-300) and merit - cost <= (
            tolerance * max(cost, 1e-300)
        ):
            converged = True  # Gauss–Newton cannot lower the cost any further
            break
        damping = carried
        for _ in range(20):
            candidate = _apply(params, step, kept)
            trial = evaluate(ctx, terms, candidate, rows)
            r_new, links_new, terms_new = stacked(trial)
            new_cost = float(r_new @ r_new)
            new_constraint = constraint_rows(ctx, candidate, kept)
            new_merit = _merit(new_cost, new_constraint, translation_weight)
            if new_merit <= merit:
                break
            # the linearisation does not hold that far: a Levenberg–Marquardt step, damped
            # more each time (poorly identified nuisance directions stop running off)
            damping = max(10.0 * damping, 1e-8)
            step = _constrained_step(a, r, constraint, damping)
        else:
            converged = True
            break
        params, design, r, links_w, terms_w = candidate, trial, r_new, links_new, terms_new
        constraint = new_constraint
        carried = damping / 10.0 if damping >= 1e-7 else 0.0
        change = merit - new_merit
        cost, merit = new_cost, new_merit
        if change <= tolerance * max(merit, 1e-300):
            converged = True
            break
    nuisance_map = None if constraint is None else scipy.linalg.null_space(constraint[1])
    nuisance = links_w[:, kept] if nuisance_map is None else links_w[:, kept] @ nuisance_map
    a = np.hstack([nuisance, terms_w])
    basis = orthonormal_basis(a)
    return ModelFit(
        terms=terms,
        params=params,
        rows=rows,
        weights=weights,
        design=design,
        kept_links=kept,
        jacobian=a,
        residual_w=r,
        rank=basis.shape[1],
        cost=cost,
        iterations=iterations,
        converged=converged,
        covariance=_theta_covariance(a, r, nuisance.shape[1], d, basis),
        nuisance_map=nuisance_map,
    )


def _apply(params: ModelParameters, step: FloatArray, kept: IntArray) -> ModelParameters:
    n_links = params.links.shape[0]
    nuisance = np.zeros(6 * n_links + params.extra.size)
    nuisance[kept] = step[: kept.size]
    links = params.links @ lie.se3_exp(nuisance[: 6 * n_links].reshape(n_links, 6))
    return ModelParameters(
        links, params.theta + step[kept.size :], params.extra + nuisance[6 * n_links :]
    )


def _theta_covariance(
    a: FloatArray, r: FloatArray, n_link_cols: int, d: int, basis: FloatArray
) -> FloatArray:
    """Covariance of θ: max of classical s²(AᵀA)⁻¹ and the per-sample cluster sandwich."""
    p_terms = a.shape[1] - n_link_cols
    if p_terms == 0:
        return np.zeros((0, 0))
    dof = max(r.size - basis.shape[1], 1)
    bread = np.linalg.pinv(a.T @ a)
    classical = float(r @ r) / dof * bread
    leverage = np.sum(basis**2, axis=1).reshape(-1, d).mean(axis=1)
    adjusted = r.reshape(-1, d) / np.sqrt(np.clip(1.0 - leverage, 0.05, None))[:, None]
    scores = np.einsum("nrp,nr->np", a.reshape(-1, d, a.shape[1]), adjusted)
    robust = bread @ (scores.T @ scores) @ bread
    block = slice(n_link_cols, None)
    c, rb = classical[block, block], robust[block, block]
    classical_var, robust_var = np.diag(c), np.diag(rb)
    ratio = np.divide(
        robust_var, classical_var, out=np.ones_like(robust_var), where=classical_var > 0
    )
    scale = np.sqrt(np.maximum(ratio, 1.0))
    return c * np.outer(scale, scale)


def noise_weights(fit: ModelFit, blocks: list[slice | list[int]]) -> FloatArray:
    """New weights 1/σ (d,) from the fit's residuals, per block of residual rows
    (:meth:`~solver.discovery.features.DiscoveryData.noise_blocks`: translation, rotation),
    with the hat-matrix dof.

    σ_b² = Σ_{rows in b} r² / Σ_{rows in b} (1 − h), h the leverages of the whitened design.
    """
    d = fit.design.residual.shape[1]
    basis = orthonormal_basis(fit.jacobian)
    leverage = np.sum(basis**2, axis=1).reshape(-1, d)
    residual = fit.design.residual
    weights = np.empty(d)
    for b in blocks:
        sigma2 = float(np.sum(residual[:, b] ** 2) / max(np.sum(1.0 - leverage[:, b]), 1.0))
        weights[b] = 1.0 / np.sqrt(max(sigma2, 1e-30))
    return weights


def fit_with_noise(
    ctx: Context,
    terms: tuple[Term, ...],
    start: ModelParameters,
    rows: IntArray,
    weights: FloatArray | None = None,
    rounds: int = 2,
    design: Design | None = None,
) -> ModelFit:
    """Fit, re-estimate the per-block noise scale, refit (``rounds`` times); ``design`` as
    :func:`fit_model`'s, the later fits start from the design of the one before."""
    w = np.ones(ctx.data.rows) if weights is None else weights
    fit = fit_model(ctx, terms, start, rows, w, design=design)
    for _ in range(rounds):
        w = noise_weights(fit, ctx.data.noise_blocks())
        fit = fit_model(ctx, terms, fit.params, rows, w, design=fit.design)
    return fit


def design_on(ctx: Context, design: Design, rows: IntArray) -> Design | None:
    """``design`` on ``rows`` ⊂ its rows without evaluating again (:meth:`Design.restricted`)
    where the recording's samples are evaluated each on its own — pose rows; None for other
    measurement models (their rows may depend on one another) or when ``rows`` is not a
    subset."""
    return design.restricted(rows) if ctx.data.is_pose else None


def extend(
    params: ModelParameters, terms: tuple[Term, ...], new: Term, value: FloatArray | None = None
) -> tuple[tuple[Term, ...], ModelParameters]:
    """Add ``new`` to the model (coefficients start at ``value`` or zero)."""
    values = by_key(terms, params.theta)
    values[new.key] = np.zeros(new.size) if value is None else value
    extended = (*terms, new)
    return extended, params.with_terms(extended, values)
