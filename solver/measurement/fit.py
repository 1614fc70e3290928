"""Gauss–Newton (paper Eq. 8–10), outlier rule (§V-A) and held-out evaluation (DESIGN.md §4)
for any :class:`~solver.measurement.models.MeasurementModel`, rows in memory.

The same core as the pose fit (:func:`solver.calibration.levenberg_marquardt`, pivoted-QR pruning
:func:`solver.calibration.pivoted_columns`, standard errors, the compliance rule), over the
chain's columns and the model's own unknowns together.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
import scipy.linalg

from solver.arrays import BoolArray, FloatArray, IntArray
from solver.calibration import (
    DeterministicFit,
    FitOptions,
    NormalEquations,
    frame_columns,
    free_columns,
    implausible_columns,
    levenberg_marquardt,
    lower_cost_restart,
    normal_equations,
    outlier_mask,
    parameter_standard_errors,
    pivoted_columns,
    removed_names,
    scaled_condition_number,
    without_columns,
)
from solver.covariance.samples import ArraySamples
from solver.errors import CalibrationError
from solver.evaluation import split_indices
from solver.kinematics import ChainParameters, parameter_names
from solver.measurement.models import (
    MeasurementModel,
    MeasurementRows,
    ModelParameters,
    chain_column_count,
)
from solver.model import KinematicChain


@dataclass(frozen=True, kw_only=True)
class MeasurementFit(DeterministicFit):
    """Result of :func:`fit_measurement`: a :class:`solver.calibration.DeterministicFit`
    whose ``estimated``/``removed`` run over the chain's and the model's parameter names
    (``standard_errors`` aligned with ``estimated``), ``params`` carry the model's own
    unknowns, ``residuals`` (N, d) are unweighted in the model's frame and ``jacobian``
    (N, d, p) of the rows over the estimated columns, weighted like the fit; with the
    ``model`` and ``constraint_residuals`` (c,) of its known distances."""

    params: ModelParameters
    model: MeasurementModel
    constraint_residuals: FloatArray

    def standard_error(self, name: str) -> float:
        return float(self.standard_errors[self.estimated.index(name)])


def row_weights(model: MeasurementModel, options: FitOptions) -> FloatArray:
    """Weights of the residual rows (d,): rotation rows times the rotation weight."""
    weights = np.ones(model.dim)
    weights[list(model.rotation_rows)] = options.rotation_weight_m_per_rad
    return weights


def _stacked(
    chain: KinematicChain,
    model: MeasurementModel,
    params: ModelParameters,
    rows: MeasurementRows,
    weights: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Weighted design (N·d + c, P + E) and target (N·d + c,) of Eq. (10), and the rows'
    weighted Jacobian (N, d, P + E)."""
    residual, jacobian = model.linearise(chain, params, rows)
    assert jacobian is not None
    extra_r, extra_a = model.constraints(chain, params)
    if np.any(weights != 1.0):
        jacobian = jacobian * weights[None, :, None]
        residual = residual * weights
    design = jacobian.reshape(-1, jacobian.shape[2])
    target = residual.reshape(-1)
    if extra_r.size:
        return np.concatenate([design, extra_a]), np.concatenate([target, extra_r]), jacobian
    return design, target, jacobian


def weighted_system(
    chain: KinematicChain,
    model: MeasurementModel,
    params: ModelParameters,
    rows: MeasurementRows,
    options: FitOptions,
) -> tuple[FloatArray, FloatArray]:
    """The fit's weighted design (N·d + c, P + E) over every column of the chain and the
    model, and its target (N·d + c,) at ``params`` (rows as :func:`fit_measurement` weighs
    them, known distances last), e.g. to linearise a finished fit again."""
    design, target, _ = _stacked(chain, model, params, rows, row_weights(model, options))
    return design, target


def fit_measurement(
    chain: KinematicChain,
    model: MeasurementModel,
    rows: MeasurementRows,
    options: FitOptions | None = None,
    *,
    start: ModelParameters | None = None,
    columns: IntArray | None = None,
) -> MeasurementFit:
    """Paper Eq. (10) for ``model``: ``x = A⁺ y`` over the chain's columns the options free and
    the model sees, and the model's own unknowns, re-linearised until the cost settles;
    columns the data cannot identify removed up front by pivoted QR; a compliance no physical
    joint could have fixed at 0 and the fit repeated (as the pose fit does). ``columns``:
    fit exactly these columns (indices into the chain's and the model's parameter names)
    instead of choosing them by pivoted QR, e.g. those of another fit of the same rows."""
    started = time.perf_counter()
    options = options or FitOptions()
    model.check_rows(rows)
    params = start if start is not None else model.start(chain, rows)
    names = parameter_names(chain) + model.extra_names()
    weights = row_weights(model, options)
    design, target, jacobian = _stacked(chain, model, params, rows, weights)
    free = free_columns(chain, options, len(names))
    free[: chain_column_count(chain)] &= model.visible_columns(chain)
    frames = frame_columns(chain, len(names))
    if columns is None:
        keep, rank, condition = pivoted_columns(design, free, options.rank_tolerance, frames)
    else:
        keep, rank = np.sort(np.asarray(columns, dtype=np.intp)), len(columns)
        condition = scaled_condition_number(design[:, keep].T @ design[:, keep])
    if target.size <= keep.size:
        raise CalibrationError(
            f"measurement '{model.name}': {rows.n} rows give {target.size} equations for "
            f"{keep.size} identifiable parameters; record at least "
            f"{keep.size // model.dim + 1} configurations (3x that is advisable)"
        )

    def evaluate(p: ChainParameters) -> tuple[NormalEquations, tuple[FloatArray, FloatArray]]:
        """The normal equations at ``p`` and, as payload, the rows' weighted Jacobian over
        ``keep`` and their weighted target (the fit's residuals at its last point)."""
        assert isinstance(p, ModelParameters)
        a, y, j = _stacked(chain, model, p, rows, weights)
        kept = j[:, :, keep]
        if y.size == kept.size:  # no extra equations: the design is the rows' Jacobian
            return normal_equations(kept.reshape(-1, keep.size), y), (kept, y)
        return normal_equations(a[:, keep], y), (kept, y)

    def apply(p: ChainParameters, step: FloatArray, columns: IntArray) -> ChainParameters:
        return model.apply(chain, p, step, columns)

    kept = jacobian[:, :, keep]
    first = (
        normal_equations(kept.reshape(-1, keep.size), target)
        if target.size == kept.size
        else normal_equations(design[:, keep], target)
    )
    run = levenberg_marquardt(
        chain, params, keep, (first, (kept, target)), evaluate, options, apply
    )
    iterations, costs = run.iterations, list(run.cost_history)  # of every fit, refits included
    pruned: list[int] = []
    n_chain = chain_column_count(chain)
    while options.non_negative_compliance:
        errors = parameter_standard_errors(run.normal)
        in_chain = keep < n_chain
        negative = implausible_columns(chain, run.params, keep[in_chain], errors[in_chain])
        if negative.size == 0:
            break
        pruned += negative.tolist()
        restart = without_columns(
            chain,
            run.params,
            negative,
            at_optimum=(keep, run.normal) if run.converged else None,
            apply=apply,
        )
        fresh = without_columns(chain, params, np.asarray(pruned, dtype=np.intp))
        keep = np.setdiff1d(keep, negative)  # before evaluating: its columns are ``keep``'s
        restart, at_restart = lower_cost_restart(
            restart, fresh, lambda starts: [evaluate(start) for start in starts]
        )
        run = levenberg_marquardt(chain, restart, keep, at_restart, evaluate, options, apply)
        iterations, costs = iterations + run.iterations, costs + run.cost_history
    final = run.params
    assert isinstance(final, ModelParameters)
    jacobian_at_final, target_at_final = run.payload
    residual = target_at_final[: rows.n * model.dim].reshape(rows.n, model.dim) / weights
    return MeasurementFit(
        model=model,
        params=final,
        estimated=[names[i] for i in keep],
        removed=[n for n in removed_names(names, keep) if names.index(n) not in pruned],
        standard_errors=parameter_standard_errors(run.normal),
        rank=rank,
        condition_number=condition,
        iterations=iterations,
        converged=run.converged,
        cost_history=costs,
        residuals=residual,
        constraint_residuals=model.constraints(chain, final)[0],
        jacobian=jacobian_at_final,
        elapsed_s=time.perf_counter() - started,
        pruned=[names[i] for i in sorted(pruned)],
    )


ONE_STEP = 1
"""Gauss–Newton steps of :func:`refit_from`."""


def refit_from(
    chain: KinematicChain,
    model: MeasurementModel,
    rows: MeasurementRows,
    options: FitOptions,
    start: ModelParameters,
    estimated: Sequence[str],
) -> MeasurementFit:
    """The fit of ``rows`` — a subset of the rows the fit ``start`` (of the parameters
    ``estimated``) came from, such as a held-out split's training rows — as one Gauss–Newton
    step of Eq. (10) from ``start`` over the same parameters (issue 29). ``start`` is within
    O(1/√n) of the subset's optimum, so one step leaves an error of the order of that distance
    squared times the model's curvature: what the held-out errors need, at the cost of one
    linearisation instead of a fit (checked against exact refits in
    tests/solver/test_one_step_heldout.py)."""
    names = parameter_names(chain) + model.extra_names()
    columns = np.array([names.index(n) for n in estimated], dtype=np.intp)
    return fit_measurement(
        chain,
        model,
        rows,
        replace(options, max_iterations=ONE_STEP),
        start=start,
        columns=columns,
    )


def covariance_samples(
    chain: KinematicChain, fit: MeasurementFit, rows: MeasurementRows, frames: Sequence[int]
) -> ArraySamples:
    """The samples of the covariance calibration (paper Eq. 12–17) for a measurement model:
    at the fit, ``r_n ≈ Σ_f A_f(q_n) ξ_{n,f} + e_n`` with ``ξ_{n,f} ~ N(0, Σ_f)`` the random
    local twist right after link ``L_f`` (Eq. 7) and ``e_n`` the measurement noise, so
    ``Cov(r_n) = Σ_f A_f Σ_f A_fᵀ + Σ_e`` (Eq. 12). ``A_f`` (N, d, 6) are the model's own
    Jacobian columns of link f's twist ``<link>.tx..rz`` (the same derivative as a geometric
    correction ``L_f ← L_f·Exp(δ)``), unweighted, rotated with the residual into the tip frame
    where the model's residual is elsewhere (a ball in a socket: the robot base frame), so that
    the noise Σ_e is a tip-frame covariance as for a pose recording (DESIGN.md §2);
    ``frames``: the chain joints whose frames are perturbed.
    The REML restriction is the fit Jacobian over the fitted columns (the model's own unknowns
    included), ``X`` (N, d, p), times a basis ``N`` (p, p − c) of the directions the model's
    ``c`` extra equations leave free (e.g. a known socket distance, which pins the scale that
    the rows alone hardly see): those directions absorb residual, the pinned ones do not, and
    with them in ``X`` REML's ``log det XᵀΣ⁻¹X`` runs off to −∞ along with Σ."""
    names = parameter_names(chain) + fit.model.extra_names()
    residual, jacobian = fit.model.linearise(chain, fit.params, rows)
    assert jacobian is not None
    n, d, _ = jacobian.shape
    columns = [6 * f + i for f in frames for i in range(6)]
    frame_jacobians = jacobian[:, :, columns].reshape(n, d, len(frames), 6).transpose(0, 2, 1, 3)
    fitted = [names.index(name) for name in fit.estimated]
    restriction = jacobian[:, :, fitted]
    _, pinned = fit.model.constraints(chain, fit.params)
    if pinned.shape[0]:
        restriction = restriction @ scipy.linalg.null_space(pinned[:, fitted])
    rotation = fit.model.tip_frame_rotation(chain, fit.params, rows)
    if rotation is not None:  # residual, A_f and X alike: the same model, noise in the tip frame
        residual = np.einsum("nij,nj->ni", rotation, residual)
        frame_jacobians = np.einsum("nij,nfjk->nfik", rotation, frame_jacobians)
        restriction = rotation @ restriction
    return ArraySamples(
        residual, np.ascontiguousarray(frame_jacobians), np.ascontiguousarray(restriction)
    )


def row_errors(model: MeasurementModel, residuals: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per row: translation error (mm, norm of the translation rows; for several markers the
    mean of each marker's) and rotation error (deg, norm of the rotation rows; 0 without)."""
    translation = residuals[:, list(model.translation_rows)]
    per_point = (
        translation.reshape(residuals.shape[0], -1, 3) if translation.shape[1] % 3 == 0 else None
    )
    if per_point is not None and per_point.shape[1] > 1:
        translation_mm = 1e3 * np.linalg.norm(per_point, axis=2).mean(axis=1)
    else:
        translation_mm = 1e3 * np.linalg.norm(translation, axis=1)
    rotation = residuals[:, list(model.rotation_rows)]
    return translation_mm, np.degrees(np.linalg.norm(rotation, axis=1))


def screened_fit(
    chain: KinematicChain,
    model: MeasurementModel,
    rows: MeasurementRows,
    options: FitOptions,
    sigma: float | None,
) -> tuple[MeasurementFit, MeasurementFit, BoolArray]:
    """The paper's §V-A rule for any model: fit, keep the rows whose every residual component
    is within ``sigma`` standard deviations of its mean (None: keep all), refit on them.
    Returns the first fit, the refit and the kept mask (N,)."""
    first = fit_measurement(chain, model, rows, options)
    if sigma is None:
        return first, first, np.ones(rows.n, dtype=bool)
    kept = outlier_mask(first.residuals, sigma)
    return first, fit_measurement(chain, model, rows.take(np.flatnonzero(kept)), options), kept


@dataclass(frozen=True)
class HeldoutError:
    """One split of DESIGN.md §4 for a measurement model: mean and RMS of the test rows'
    translation errors (mm; for sockets the distance of the held-out ball centres from the
    socket point fitted on the training rows) and mean rotation error (deg; 0 without)."""

    method: str
    seed: int
    n_train: int
    n_test: int
    translation_mm: float
    translation_rms_mm: float
    rotation_deg: float
    component_rms: tuple[float, ...]
    """RMS of each residual component over the test rows (d,), m and rad."""


def heldout_errors(
    chain: KinematicChain,
    model: MeasurementModel,
    rows: MeasurementRows,
    methods: dict[str, FitOptions],
    seeds: Iterable[int],
    train_fraction: float = 0.9,
    starts: dict[str, MeasurementFit] | None = None,
) -> list[HeldoutError]:
    """Per seed and method (fit settings): fit on the training rows of
    :func:`solver.evaluation.split_indices`, score the test rows at that fit (the model's own
    unknowns — socket points, marker offsets — from the training rows too). ``starts``: per
    method, the fit of all ``rows`` each split's fit is one step from (:func:`refit_from`);
    None: iterated from the model's start."""
    out = []
    for seed in seeds:
        train, test = split_indices(rows.n, seed, train_fraction)
        for method, options in methods.items():
            if starts is None:
                fit = fit_measurement(chain, model, rows.take(train), options)
            else:
                start = starts[method]
                fit = refit_from(
                    chain, model, rows.take(train), options, start.params, start.estimated
                )
            residual, _ = model.linearise(chain, fit.params, rows.take(test), jacobian=False)
            translation_mm, rotation_deg = row_errors(model, residual)
            out.append(
                HeldoutError(
                    method,
                    seed,
                    int(train.size),
                    int(test.size),
                    float(translation_mm.mean()),
                    float(np.sqrt(np.mean(translation_mm**2))),
                    float(rotation_deg.mean()),
                    tuple(float(v) for v in np.sqrt(np.mean(residual**2, axis=0))),
                )
            )
    return out
