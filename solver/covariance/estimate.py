"""The covariance calibration (paper §IV-C): :func:`estimate_from_samples` on samples in memory
or streamed (:mod:`.samples`), :func:`estimate_covariances` for arrays.

Pipeline: sufficient statistics (Eq. 13–14) → identifiability → moment solution (Eq. 14, by
clarabel / pgd / nnls) → optionally ML (Eq. 16–17) or REML started from it → the
unidentifiable part fixed by the rule of :mod:`identifiability` → standard errors.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from solver.arrays import BoolArray, FloatArray
from solver.covariance.fitting import METRIC_SAMPLES, Estimator, fit_likelihood, noise_floor
from solver.covariance.identifiability import (
    RANK_RTOL,
    WEAK_RTOL,
    IdentifiabilityReport,
    analyse_identifiability,
    resolve_null_space,
    unseen_axes,
)
from solver.covariance.layout import CovarianceLayout, Structure, make_layout
from solver.covariance.likelihood import (
    ee_covariance_batch,
    fisher_information_ml,
    fisher_information_reml,
    fit_basis_transform,
    moment_sandwich_meat,
)
from solver.covariance.samples import (
    ArraySamples,
    CovarianceSamples,
    SampleChunk,
    every_kth,
    subsample,
    total,
)
from solver.covariance.solvers import (
    PGD_STABLE,
    ConcreteSolver,
    CovarianceSolution,
    PGDSettings,
    SolverName,
    concrete_solver,
    solve_moment,
)
from solver.covariance.statistics import (
    DEFAULT_CHUNK_SIZE,
    JacobianRange,
    MomentStatistics,
    build_moment_statistics,
)
from solver.covariance.uncertainty import ThetaUncertainty, theta_covariance, theta_uncertainty
from solver.errors import CalibrationError, SolverError

EstimatorName = Literal["moment", "ml", "reml"]


@dataclass(frozen=True)
class FrameCovariance:
    """Σ of one source (6×6, [v; w], m² / m·rad / rad²) and per-axis σ with intervals.

    ``std`` (6,) = sqrt(diag Σ) in m, m, m, rad, rad, rad; ``std_se``, ``std_ci_low/high`` from
    :mod:`uncertainty` (NaN where unknown); ``at_boundary``: σ ≈ 0, the interval is one-sided;
    ``identifiable``: the entry is determined by the data on its own; ``estimated``: the axis
    was free (False: fixed at 0 by the caller); ``fixed``: the whole Σ was given (known noise).
    """

    name: str
    covariance: FloatArray
    std: FloatArray
    std_se: FloatArray
    std_ci_low: FloatArray
    std_ci_high: FloatArray
    at_boundary: BoolArray
    identifiable: BoolArray
    estimated: BoolArray
    fixed: bool = False
    unseen: tuple[str | None, ...] = (None,) * 6
    """Per axis: why the data cannot see its variance (:func:`.identifiability.unseen_axes`),
    None where they can; such an axis is not ``identifiable`` either."""


@dataclass(frozen=True)
class CovarianceEstimate:
    """Result of :func:`estimate_covariances`.

    ``frames``: chain frames in the caller's order; ``noise``: Σ_n (estimated, or the known one
    with ``fixed=True``; None if the noise was neither). ``theta`` (Q,) after the null-space
    rule, labelled by ``layout.labels()``; ``theta_covariance`` (Q, Q) or None.
    ``moment_solution`` is the Eq. (14) solver's raw answer, ``solution`` the final stage's.
    """

    estimator: EstimatorName
    structure: Structure
    solver: ConcreteSolver
    n_samples: int
    frames: tuple[FrameCovariance, ...]
    noise: FrameCovariance | None
    theta: FloatArray
    layout: CovarianceLayout
    identifiability: IdentifiabilityReport
    moment_solution: CovarianceSolution
    solution: CovarianceSolution
    statistics: MomentStatistics = field(repr=False)
    theta_covariance: FloatArray | None = field(default=None, repr=False)
    uncertainty: ThetaUncertainty | None = field(default=None, repr=False)
    warnings: tuple[str, ...] = ()

    @property
    def converged(self) -> bool:
        return self.solution.converged

    def frame(self, name: str) -> FrameCovariance:
        for frame in (*self.frames, *((self.noise,) if self.noise else ())):
            if frame.name == name:
                return frame
        raise KeyError(name)

    def frame_covariances(self) -> FloatArray:
        """Σ_f of the chain frames, (F_chain, 6, 6)."""
        return np.stack([f.covariance for f in self.frames])

    def noise_covariance(self) -> FloatArray:
        """Σ_n (6, 6), zeros if there is none."""
        return np.zeros((6, 6)) if self.noise is None else self.noise.covariance

    def residual_noise(self) -> FloatArray:
        """The noise part of Eq. (12) in the residual's rows, (d, d): ``Σ_k U_k Σ_n U_kᵀ``
        over the placements of the noise (one on rows 0..d−1 for a pose or position)."""
        placements = self.layout.noise_jacobians()  # (K, d, 6)
        return np.einsum("kia,ab,kjb->ij", placements, self.noise_covariance(), placements)

    def ee_covariance(self, frame_jacobians: FloatArray, *, include_noise: bool) -> FloatArray:
        """Eq. (12) at new configurations: (N, d, d) from frame Jacobians (N, F_chain, d, 6)."""
        noise = self.residual_noise() if include_noise else None
        return ee_covariance_batch(frame_jacobians, self.frame_covariances(), noise)


def estimate_covariances(
    residuals: FloatArray,
    frame_jacobians: FloatArray,
    frame_names: Sequence[str],
    *,
    structure: Structure = "diag",
    estimator: EstimatorName = "moment",
    solver: SolverName = "auto",
    fit_jacobian: FloatArray | None = None,
    noise_covariance: FloatArray | None = None,
    include_noise: bool = True,
    noise_name: str = "noise",
    free_axes: Mapping[str, Sequence[str]] | None = None,
    pgd_settings: PGDSettings = PGD_STABLE,
    standard_errors: bool = True,
    confidence: float = 0.95,
    rank_rtol: float = RANK_RTOL,
    weak_rtol: float = WEAK_RTOL,
    chunk_size: int = DEFAULT_CHUNK_SIZE,
    max_likelihood_iterations: int = 200,
) -> CovarianceEstimate:
    """Calibrate the covariances of random perturbations in the chain (paper §IV-C) from
    arrays in memory (:func:`estimate_from_samples` does the work).

    ``residuals`` (N, d): end-effector-frame residuals after the deterministic fit ([v; w] or
    [v], m and rad). ``frame_jacobians`` (N, F, d, 6): A_f(q_n) = rows of Ad_{B_f}^-1 for each
    frame that carries randomness, named by ``frame_names``. The measurement noise is one more
    frame (Jacobian I, named ``noise_name``) unless ``noise_covariance`` (6×6 or d×d, known,
    e.g. measured separately) is given or ``include_noise`` is False.

    ``estimator``: "moment" (Eq. 13–15), "ml" (Eq. 16–17) or "reml" (needs ``fit_jacobian``
    (N, d, p), the deterministic fit's Jacobian in the same residual space, e.g. the rows of
    the stacked calibration Jacobian; only its column space matters). ``solver`` solves the
    moment problem, which also starts ML/REML (projected Fisher scoring, :mod:`.fitting`);
    "auto" is NNLS for diagonal and Clarabel for full Σ (:func:`.solvers.concrete_solver`).
    ``free_axes`` restricts frames to some axes (names from ``POSE_AXES``); ``structure``
    "full" needs ``solver`` "auto", "clarabel" or "pgd".
    """
    residuals = np.asarray(residuals, dtype=float)
    frame_jacobians = np.asarray(frame_jacobians, dtype=float)
    _check_inputs(residuals, frame_jacobians, frame_names, estimator, fit_jacobian)
    d = residuals.shape[1]
    known = known_noise_covariance(noise_covariance, d)
    layout = make_layout(
        frame_names,
        d,
        structure=structure,
        include_noise=include_noise and known is None,
        noise_name=noise_name,
        free_axes=free_axes,
    )
    samples = ArraySamples(
        residuals,
        frame_jacobians,
        None if fit_jacobian is None else np.asarray(fit_jacobian, dtype=float),
        chunk_size=chunk_size,
    )
    return estimate_from_samples(
        samples,
        layout,
        known=known,
        estimator=estimator,
        solver=solver,
        noise_name=noise_name,
        pgd_settings=pgd_settings,
        standard_errors=standard_errors,
        confidence=confidence,
        rank_rtol=rank_rtol,
        weak_rtol=weak_rtol,
        max_likelihood_iterations=max_likelihood_iterations,
    )


FULL_LIKELIHOOD_SAMPLES = 50_000
"""Up to this many samples ML and REML use every sample in each evaluation (iterated to
convergence up to :data:`STEPPED_SAMPLES`, then refined one-step); beyond, they take one Fisher-
scoring step from the moment solution (each evaluation being a pass over a large recording):
from a √N-consistent start that step is as efficient as the converged estimator up to O(1/N),
far below its standard error (measured at 10⁵ simulated Jaco2 poses: every σ within 0.03 of
its standard error of the converged REML's, for a third of the covariance stage's time);
REML's restriction terms (O(p) of the gradient against O(N)) are then taken on the
:data:`SE_SAMPLES` subsample, so each evaluation costs one pass, not two. The streamed
calibration keeps up to this many samples in memory, where iterating costs no pass."""

STEPPED_SAMPLES = 5_000
"""Above this many samples (up to :data:`FULL_LIKELIHOOD_SAMPLES`) ML and REML take the
one-step estimator from the moment solution refined by full average-information scoring steps
(:func:`_stepped`) instead of iterating to convergence with two starts (issue 29: a 10⁴-pose
recording spent 3.1 of its 7.6 s there), unless those steps do not converge
(:func:`_converging`). Measured on simulated Jaco2 poses against the converged REML: the one
step alone is off by up to 0.32 (5 000 samples) and 0.31 (10⁴) standard errors, after two more
steps by 0.001 — in a fifth of the time."""

SUBSET_STEPS = 3
"""Scoring steps of :func:`_stepped`: the one-step estimator and two refinements."""

SE_SAMPLES = 10_000
"""Standard errors (and the scoring metric, at most :data:`~.fitting.METRIC_SAMPLES` of them)
come from at most this many samples, evenly spaced over the recording, the information scaled
to all samples: an unbiased estimate of the sum, for errors that need 2 digits, not 10."""


def moment_statistics(
    samples: CovarianceSamples, layout: CovarianceLayout, known: FloatArray | None
) -> tuple[MomentStatistics, JacobianRange]:
    """Eq. (13–14) statistics and the frame-Jacobian range of the samples (one pass)."""
    parts = samples.map(_moment_chunk, (layout, known))
    stats = total([p[0] for p in parts])
    return stats, total([p[1] for p in parts])


def _moment_chunk(
    argument: tuple[CovarianceLayout, FloatArray | None], chunk: SampleChunk
) -> tuple[MomentStatistics, JacobianRange]:
    layout, known = argument
    stats = build_moment_statistics(
        chunk.residuals, chunk.frame_jacobians, layout, known_covariance=known
    )
    return stats, JacobianRange.of(chunk.frame_jacobians)


def estimate_from_samples(
    samples: CovarianceSamples,
    layout: CovarianceLayout,
    *,
    known: FloatArray | None = None,
    estimator: EstimatorName = "moment",
    solver: SolverName = "auto",
    noise_name: str = "noise",
    statistics: tuple[MomentStatistics, JacobianRange] | None = None,
    sample_subset: ArraySamples | None = None,
    pgd_settings: PGDSettings = PGD_STABLE,
    standard_errors: bool = True,
    confidence: float = 0.95,
    rank_rtol: float = RANK_RTOL,
    weak_rtol: float = WEAK_RTOL,
    max_likelihood_iterations: int = 200,
    likelihood_tolerance: float = 1e-10,
    start_theta: FloatArray | None = None,
    notes: Sequence[str] = (),
) -> CovarianceEstimate:
    """The covariance calibration (paper §IV-C) of ``samples`` (:mod:`.samples`: in memory or
    streamed; every step reduces to passes over them) for the θ ``layout``.

    ``known`` (d, d): a known part of every Σ_E (then the layout has no noise frame);
    ``statistics``: the Eq. (14) statistics and Jacobian range when a pass already took them
    (a streamed fit's last pass), else one pass takes them; ``sample_subset``: the
    :func:`~.samples.subsample` of at most :data:`SE_SAMPLES` when the caller has it (e.g.
    with the fit Jacobian that ``samples`` need not carry), else one pass takes it. Then:
    identifiability → moment
    solution → ML or REML by projected Fisher scoring (at most ``max_likelihood_iterations``
    steps, or once the predicted NLL decrease per sample is below ``likelihood_tolerance``;
    each a pass over the samples, two for REML; started from ``start_theta`` when given, e.g.
    the estimate of a superset of the samples, else from the moment solution) → the
    unidentifiable part fixed by the rule of :mod:`.identifiability` → standard errors from at
    most :data:`SE_SAMPLES` evenly spaced samples. ``notes`` start the warnings.

    Unidentifiable combinations are reported in words in ``identifiability``; ``warnings``
    collects noise confusions and solver trouble.
    """
    stats, jacobian_range = (
        statistics if statistics is not None else moment_statistics(samples, layout, known)
    )
    if stats.n_samples < 2:
        raise CalibrationError(
            f"covariance calibration needs at least 2 samples, got {stats.n_samples}"
        )
    if not (np.all(np.isfinite(stats.gram)) and np.all(np.isfinite(stats.cross))):
        raise CalibrationError("residuals or frame Jacobians contain NaN or inf")
    report = analyse_identifiability(
        stats,
        rank_rtol=rank_rtol,
        weak_rtol=weak_rtol,
        frame_jacobians=jacobian_range.pseudo_samples(),
    )
    solver_used = concrete_solver(solver, layout.structure)
    moment = solve_moment(stats, solver_used, pgd_settings=pgd_settings)
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
    if start_theta is None or estimator == "moment":
        theta = resolve_null_space(moment.theta, report, layout)
    else:  # the likelihood fit starts elsewhere: the rule is applied to its answer only
        theta = moment.theta
    solution = moment
    sub = sample_subset
    if sub is None and (estimator != "moment" or standard_errors):
        sub = subsample(samples, SE_SAMPLES)
    large = stats.n_samples > FULL_LIKELIHOOD_SAMPLES
    stepped = not large and start_theta is None and stats.n_samples > STEPPED_SAMPLES
    transform = None
    if estimator == "reml":
        transform = fit_basis_transform(sub if large and sub is not None else samples)
    if estimator != "moment":
        assert sub is not None
        try:
            steps = (
                _stepped(estimator, theta, samples, stats, report, sub, transform, known)
                if stepped
                else []
            )
            if _converging(steps):
                solution = steps[-1]
            else:
                solution = fit_likelihood(
                    estimator,
                    theta if start_theta is None else start_theta,
                    samples,
                    stats,
                    report.scaling,
                    every_kth(sub, METRIC_SAMPLES),
                    transform=transform,
                    restriction_samples=sub if large else None,
                    known_covariance=known,
                    max_iterations=max_likelihood_iterations,
                    one_step=large,
                    tolerance=likelihood_tolerance,
                    null_basis=report.null_basis,
                )
        except CalibrationError as exc:  # Σ_E singular from every start
            solution = replace(moment, status="error", objective=np.nan, message=str(exc))
        if solution.status == "error" or not np.isfinite(solution.objective):
            notes.append(
                f"{estimator} fit failed ({solution.status}: {solution.message}); the moment "
                "estimate (Eq. 14) is carried instead"
            )
            estimator, solution = "moment", moment
            theta = resolve_null_space(moment.theta, report, layout)
        else:
            if not solution.converged:
                notes.append(
                    f"{estimator} fit ended with status {solution.status!r}: {solution.message}"
                )
            theta = resolve_null_space(solution.theta, report, layout, noise_floor(stats))
    cov, unc = None, None
    if sub is not None and standard_errors:
        try:
            cov = _theta_covariance(
                estimator, theta, sub, stats, report, transform, known, scale=stats.n_samples
            )
            unc = theta_uncertainty(
                theta,
                cov,
                report,
                layout.is_variance,
                confidence=confidence,
                method=SE_METHOD[estimator],
            )
        except CalibrationError as exc:
            notes.append(f"no standard errors: {exc}")
    seen_on = sub if sub is not None else subsample(samples, SE_SAMPLES)
    unseen = unseen_axes(seen_on.frame_jacobians, layout)
    frames, noise = frame_results(layout, theta, unc, known, noise_name, unseen)
    return CovarianceEstimate(
        estimator,
        layout.structure,
        solver_used,
        stats.n_samples,
        frames,
        noise,
        theta,
        layout,
        report,
        moment,
        solution,
        stats,
        cov,
        unc,
        tuple(notes),
    )


def subset_estimate(
    reference: CovarianceEstimate,
    samples: ArraySamples,
    *,
    known: FloatArray | None = None,
) -> CovarianceEstimate:
    """The covariance calibration of ``samples`` — a held-out split's training rows, or a fold
    of them — with ``reference``'s estimator, at the cost of a few likelihood evaluations
    (issue 29): the samples' own moment solution (Eq. 14), the one-step estimator from it and
    two average-information steps (:func:`_stepped`, the path of a mid-size recording). Where
    those steps do not behave as near an optimum (:func:`_converging`; a split keeping gross
    errors) the estimate is iterated to convergence instead, with a note. ``reference`` — the
    calibration of every row — lends its identifiability report (the scaling, and the null
    directions, along which Σ_E does not change), not its θ: started there, the held-out rows'
    residuals that θ fitted stayed in the split's covariances (the FR3's 10-fold coverage
    through ``kincal calibrate``: 99 of 111 poses inside the 95 % ellipsoid, against 100 of 111
    iterated and from the moments). Checked against the iterated estimate in
    tests/solver/test_one_step_heldout.py. No standard errors. ``known`` (d, d): the known part
    of every Σ_E, as for ``reference``. A moment ``reference``: the samples' moment solution."""
    layout = reference.layout
    noise_name = reference.noise.name if reference.noise is not None else "noise"

    def iterated(estimator: EstimatorName) -> CovarianceEstimate:
        return estimate_from_samples(
            samples,
            layout,
            known=known,
            estimator=estimator,
            solver=reference.solver,
            noise_name=noise_name,
            standard_errors=False,
        )

    if reference.estimator == "moment":
        return iterated("moment")
    stats, _ = moment_statistics(samples, layout, known)
    report = reference.identifiability
    moment = solve_moment(stats, reference.solver)
    transform = fit_basis_transform(samples) if reference.estimator == "reml" else None
    steps = _stepped(
        reference.estimator, moment.theta, samples, stats, report, samples, transform, known
    )
    if not _converging(steps):
        fallback = iterated(reference.estimator)
        message = steps[-1].message if steps else "no step"
        note = f"the scoring steps did not converge ({message}); iterated instead"
        return replace(fallback, warnings=(*fallback.warnings, note))
    solution = steps[-1]
    frames, noise = frame_results(layout, solution.theta, None, known, noise_name)
    return replace(
        reference,
        n_samples=stats.n_samples,
        frames=frames,
        noise=noise,
        theta=solution.theta,
        moment_solution=moment,
        solution=solution,
        statistics=stats,
        theta_covariance=None,
        uncertainty=None,
        warnings=(solution.message,),
    )


def _converging(steps: list[CovarianceSolution]) -> bool:
    """Full scoring steps that behave as near an optimum: every θ and NLL finite, the NLL
    (each step's ``objective``, taken at its start) falling from step to step, and each
    step's predicted decrease (``kkt_residual``) smaller than the one before. Far from the
    quadratic region — a split keeping gross errors (the FR3 without its outlier rule) — the
    predicted decrease grows instead (100, 4 190, 2 029 in total NLL on one split)."""
    if not steps or not all(np.all(np.isfinite(s.theta)) for s in steps):
        return False
    values = [s.objective for s in steps]
    decreases = [s.kkt_residual for s in steps]
    return (
        all(np.isfinite(values))
        and all(b < a for a, b in itertools.pairwise(values))
        and all(b < a for a, b in itertools.pairwise(decreases))
    )


def _stepped(
    estimator: Estimator,
    start: FloatArray,
    samples: CovarianceSamples,
    stats: MomentStatistics,
    report: IdentifiabilityReport,
    sub: ArraySamples,
    transform: FloatArray | None,
    known: FloatArray | None,
) -> list[CovarianceSolution]:
    """:data:`SUBSET_STEPS` full projected scoring steps from the moment solution ``start``:
    the classical one-step estimator (expected information, Eq. 16), then average-information
    steps (:func:`~.fitting.fit_likelihood` with ``refine``); each step's solution, the last
    one's ``iterations`` and ``message`` saying what was done. Stops at a non-finite θ."""
    steps: list[CovarianceSolution] = []
    theta = start
    for step in range(SUBSET_STEPS):
        if not np.all(np.isfinite(theta)):
            break
        steps.append(
            fit_likelihood(
                estimator,
                theta,
                samples,
                stats,
                report.scaling,
                every_kth(sub, METRIC_SAMPLES),
                transform=transform,
                known_covariance=known,
                null_basis=report.null_basis,
                one_step=step == 0,
                refine=step > 0,
            )
        )
        theta = steps[-1].theta
    if steps:
        steps[-1] = replace(
            steps[-1],
            iterations=len(steps),
            wall_time_s=sum(s.wall_time_s for s in steps),
            message=f"one Fisher-scoring step from the moment solution, then {len(steps) - 1} "
            "average-information scoring steps (the one-step estimator refined)",
        )
    return steps


SE_METHOD = {
    # how each estimator's standard errors are computed, as the result reports it
    "moment": "sandwich G⁺·2ΣK̃ᵀK̃·G⁺ (Gaussian fourth moments)",
    "ml": "inverse expected Fisher information of Eq. (16)",
    "reml": "inverse expected Fisher information of the restricted likelihood",
}


def known_noise_covariance(
    noise_covariance: FloatArray | None,
    residual_dim: int,
    placements: Sequence[Sequence[int]] | None = None,
) -> FloatArray | None:
    """A known measurement-noise covariance Σ_n as the (d, d) block of the residual space.

    ``noise_covariance``: 6×6 ([v; w], m² and rad², end-effector frame) or already d×d; it is
    symmetrised, and for position-only residuals (d = 3) its translational block is kept.
    With ``placements`` (the noise's placements, each the residual row of the six axes, −1:
    none, as in :func:`~.layout.make_layout`) a 6×6 Σ_n (or a 3×3 position noise) is
    placed on each: ``Σ_k U_k Σ_n U_kᵀ``.
    None stays None (Σ_n is then estimated as one more frame, Eq. 13).
    """
    if noise_covariance is None:
        return None
    d = residual_dim
    known = np.asarray(noise_covariance, dtype=float)
    if placements is not None and known.shape == (3, 3) and d != 3:  # a position noise
        known = np.pad(known, ((0, 3), (0, 3)))
    if placements is not None and known.shape == (6, 6):
        sym = 0.5 * (known + known.T)
        out = np.zeros((d, d))
        for rows in placements:
            axes = [a for a in range(6) if rows[a] >= 0]
            placed = [int(rows[a]) for a in axes]
            out[np.ix_(placed, placed)] += sym[np.ix_(axes, axes)]
        return out
    if known.shape not in ((6, 6), (d, d)):
        raise SolverError(f"noise_covariance must be 6×6 or {d}×{d}, got {known.shape}")
    return np.asarray(0.5 * (known + known.T)[:d, :d])


def _theta_covariance(
    estimator: EstimatorName,
    theta: FloatArray,
    sub: ArraySamples,
    stats: MomentStatistics,
    report: IdentifiabilityReport,
    transform: FloatArray | None,
    known: FloatArray | None,
    *,
    scale: int,
) -> FloatArray:
    """Cov(θ̂) (Q, Q) from the information (or sandwich meat) of the subsample ``sub``, scaled
    to ``scale`` samples."""
    layout = stats.layout
    weight = scale / sub.n_samples
    if estimator == "moment":
        meat = moment_sandwich_meat(theta, sub.frame_jacobians, layout, known_covariance=known)
        return theta_covariance(weight * meat, report, bread=stats.gram)
    if estimator == "ml":
        info = fisher_information_ml(theta, sub.frame_jacobians, layout, known_covariance=known)
    else:
        assert transform is not None and sub.fit_jacobian is not None
        info = fisher_information_reml(
            theta, sub.frame_jacobians, sub.fit_jacobian @ transform, layout, known_covariance=known
        )
    return theta_covariance(weight * info, report)


def frame_results(
    layout: CovarianceLayout,
    theta: FloatArray,
    unc: ThetaUncertainty | None,
    known_noise: FloatArray | None,
    noise_name: str,
    unseen: Sequence[tuple[str | None, ...]] = (),
) -> tuple[tuple[FrameCovariance, ...], FrameCovariance | None]:
    """The estimated θ as per-frame covariances (6×6, [v; w], m² and rad², each frame's own
    axes) with their uncertainties, and the noise frame: estimated (the layout's last frame),
    the known (d, d) Σ_n read through the noise's first placement into 6×6, or None.
    ``unseen``: per chain frame, why the data cannot see each axis
    (:func:`.identifiability.unseen_axes`)."""
    frames = _frames(layout, theta, unc, unseen)
    if layout.noise_frame is not None:
        return tuple(frames[:-1]), frames[-1]
    if known_noise is None:
        return tuple(frames), None
    rows = np.array(layout.placements[0][0], dtype=np.intp)  # the first placement's rows
    axes = np.flatnonzero(rows >= 0)
    full = np.zeros((6, 6))
    full[np.ix_(axes, axes)] = known_noise[np.ix_(rows[axes], rows[axes])]
    return tuple(frames), _fixed_frame(noise_name, full)


def _frames(
    layout: CovarianceLayout,
    theta: FloatArray,
    unc: ThetaUncertainty | None,
    unseen: Sequence[tuple[str | None, ...]],
) -> list[FrameCovariance]:
    covs = layout.frame_covariances(theta)
    out = []
    for f, name in enumerate(layout.frame_names):
        arrays = {key: np.full(6, np.nan) for key in ("std_se", "low", "high")}
        boundary, identifiable = np.zeros(6, bool), np.zeros(6, bool)
        for p in np.flatnonzero((layout.param_frame == f) & layout.is_variance):
            axis = layout.param_row[p]
            if unc is not None:
                arrays["std_se"][axis] = unc.std_se[p]
                arrays["low"][axis] = unc.std_ci_low[p]
                arrays["high"][axis] = unc.std_ci_high[p]
                boundary[axis] = unc.at_boundary[p]
            identifiable[axis] = _identifiable(layout, f, axis, unc)
        reasons = unseen[f] if f < len(unseen) else (None,) * 6
        identifiable &= np.array([r is None for r in reasons])
        out.append(
            FrameCovariance(
                name,
                covs[f],
                np.sqrt(np.clip(np.diag(covs[f]), 0.0, None)),
                arrays["std_se"],
                arrays["low"],
                arrays["high"],
                boundary,
                identifiable,
                np.array(layout.free_axes[f], dtype=bool),
                unseen=tuple(reasons),
            )
        )
    return out


def _identifiable(
    layout: CovarianceLayout, f: int, axis: int, unc: ThetaUncertainty | None
) -> bool:
    if unc is None:
        return False
    p = np.flatnonzero(
        (layout.param_frame == f) & (layout.param_row == axis) & (layout.param_col == axis)
    )
    return bool(unc.identifiable[p[0]]) if p.size else False


def _fixed_frame(name: str, covariance: FloatArray) -> FrameCovariance:
    nan = np.full(6, np.nan)
    return FrameCovariance(
        name,
        covariance,
        np.sqrt(np.clip(np.diag(covariance), 0.0, None)),
        nan,
        nan,
        nan,
        np.zeros(6, bool),
        np.zeros(6, bool),
        np.zeros(6, bool),
        fixed=True,
    )


def _check_inputs(
    residuals: FloatArray,
    frame_jacobians: FloatArray,
    frame_names: Sequence[str],
    estimator: str,
    fit_jacobian: FloatArray | None,
) -> None:
    if residuals.ndim != 2 or residuals.shape[1] not in (3, 6):
        raise SolverError(f"residuals must be (N, 6) or (N, 3), got {residuals.shape}")
    n, d = residuals.shape
    if (
        frame_jacobians.ndim != 4
        or frame_jacobians.shape[0] != n
        or frame_jacobians.shape[2:] != (d, 6)
    ):
        raise SolverError(f"frame_jacobians must be ({n}, F, {d}, 6), got {frame_jacobians.shape}")
    if frame_jacobians.shape[1] != len(frame_names):
        raise SolverError(f"{len(frame_names)} frame names for {frame_jacobians.shape[1]} frames")
    if estimator not in ("moment", "ml", "reml"):
        raise SolverError(f"unknown estimator {estimator!r}; use 'moment', 'ml' or 'reml'")
    if estimator == "reml":
        if fit_jacobian is None:
            raise CalibrationError("estimator 'reml' needs fit_jacobian (N, d, p)")
        if np.shape(fit_jacobian)[:2] != (n, d):
            raise SolverError(f"fit_jacobian must be ({n}, {d}, p), got {np.shape(fit_jacobian)}")
    if n < 2:
        raise CalibrationError(f"covariance calibration needs at least 2 samples, got {n}")
    if not (np.all(np.isfinite(residuals)) and np.all(np.isfinite(frame_jacobians))):
        raise CalibrationError("residuals or frame Jacobians contain NaN or inf")
