"""Held-out confirmation and gross-outlier screening for the discovery loop."""

from __future__ import annotations

import numpy as np

from solver.arrays import BoolArray, FloatArray, IntArray
from solver.calibration import pose_errors
from solver.discovery.fitting import (
    Context,
    ModelFit,
    design_on,
    evaluate,
    fit_model,
    fit_with_noise,
    whitened,
)
from solver.discovery.library import Term
from solver.discovery.results import HeldoutError
from solver.distributions import chi2_isf, chi2_quantile
from solver.errors import CalibrationError
from solver.measurement.fit import row_errors


def kfold(n: int, folds: int, rng: np.random.Generator) -> list[tuple[IntArray, IntArray]]:
    """K random folds (sorted index arrays), every sample tested once."""
    order = rng.permutation(n)
    out = []
    for chunk in np.array_split(order, max(2, min(folds, n))):
        test = np.sort(chunk)
        out.append((np.setdiff1d(np.arange(n), test), test))
    return out


def cross_validate(
    ctx: Context,
    terms: tuple[Term, ...],
    fit: ModelFit,
    folds: list[tuple[IntArray, IntArray]],
    weights: FloatArray,
    rows: IntArray | None = None,
) -> HeldoutError:
    """Refit on each training fold (warm start at ``fit``), score the held-out fold.

    Folds are over the whole recording and restricted to ``rows`` (default: the fit's rows,
    i.e. without the samples screened out as gross outliers).
    """
    used = fit.rows if rows is None else rows
    translation, rotation, sse = [], [], 0.0
    per_sample = np.zeros(ctx.data.n_samples)
    for all_train, all_test in folds:
        train, test = np.intersect1d(all_train, used), np.intersect1d(all_test, used)
        if test.size == 0:
            continue
        try:
            # Gauss–Newton converges quadratically from the all-sample optimum: a few steps.
            start = design_on(ctx, fit.design, train) if fit.terms == terms else None
            fold_fit = fit_model(
                ctx, terms, fit.params, train, weights, max_iterations=4, design=start
            )
        except CalibrationError:
            fold_fit = fit
        design = evaluate(ctx, terms, fold_fit.params, test)
        errors = np.sum(whitened(design.residual, weights) ** 2, axis=1)
        per_sample[test] = errors
        sse += float(errors.sum())
        if ctx.data.is_pose:
            t_mm, r_deg = pose_errors(
                design.pose,
                ctx.data.measured_pose[test],
                rotation=ctx.data.pose_model.measures_rotation,
            )
        else:
            model = ctx.data.model
            t_mm, rotation_deg = row_errors(model, design.residual)
            r_deg = rotation_deg if model.rotation_rows else None
        translation.append(t_mm)
        if r_deg is not None:
            rotation.append(r_deg)
    return HeldoutError(
        float(np.concatenate(translation).mean()),
        float(np.concatenate(rotation).mean()) if rotation else None,
        sse,
        per_sample[used],
    )


def repeated_heldout(
    ctx: Context,
    terms: tuple[Term, ...],
    fit: ModelFit,
    partitions: list[list[tuple[IntArray, IntArray]]],
    weights: FloatArray,
) -> HeldoutError:
    """:func:`cross_validate` over several K-fold partitions of the same samples: mean
    translation / rotation error and whitened SSE, per-sample whitened SSE averaged over the
    partitions (a paired test on it is not at the mercy of one split), and the per-partition
    translation and rotation errors and SSEs (the split-to-split noise of
    :meth:`~solver.discovery.results.HeldoutError.confirmed_by`)."""
    runs = [cross_validate(ctx, terms, fit, folds, weights) for folds in partitions]
    rotations = [r.rotation_deg for r in runs if r.rotation_deg is not None]
    return HeldoutError(
        float(np.mean([r.translation_mm for r in runs])),
        float(np.mean(rotations)) if rotations else None,
        float(np.mean([r.whitened_sse for r in runs])),
        np.mean([r.per_sample for r in runs], axis=0),
        tuple(r.translation_mm for r in runs),
        tuple(rotations),
        tuple(r.whitened_sse for r in runs),
    )


def _screen_limit(ctx: Context, level: float) -> tuple[float, float]:
    """(χ²_d quantile at ``level / N``, χ²_d median) of :func:`screen_outliers`."""
    d = ctx.data.rows
    return (
        chi2_isf(level / ctx.data.n_samples, d),
        chi2_quantile(0.5, d),
    )


def _passing(norm2: FloatArray, kept: IntArray, limit: float, median: float) -> BoolArray:
    """Samples whose whitened squared residual norm ``norm2`` (N,) passes the screen, the
    scale taken as the median over the ``kept`` samples."""
    scale = float(np.median(norm2[kept])) / median
    return norm2 <= limit * scale


def screen_outliers(
    ctx: Context, terms: tuple[Term, ...], fit: ModelFit, level: float | None
) -> ModelFit:
    """Refit without the samples the current model cannot explain at all (gross outliers).

    A sample is out when its whitened squared residual norm, scaled by the median over the
    fit's samples (robust to the outliers themselves), exceeds the χ²_d quantile at
    ``level / N``. Every sample is re-judged against the current model, so samples that
    only looked wrong before a missing effect was modelled come back.
    """
    if level is None:
        return fit
    all_rows = ctx.all_rows
    limit, median = _screen_limit(ctx, level)
    for _ in range(4):
        design = evaluate(ctx, terms, fit.params, all_rows)
        norm2 = np.sum(whitened(design.residual, fit.weights) ** 2, axis=1)
        rows = all_rows[_passing(norm2, fit.rows, limit, median)]
        if np.array_equal(rows, fit.rows):
            break
        start = design_on(ctx, design, rows)
        fit = fit_with_noise(ctx, terms, fit.params, rows, fit.weights, rounds=1, design=start)
    return fit


def corroborated(ctx: Context, fit: ModelFit, library: list[Term], level: float) -> IntArray:
    """The screened-out samples that vouch for each other under the library candidate whose
    model brings back the most of them (none: empty).

    Linearised at ``fit`` over the whole recording: each candidate's columns join the fit's
    (nuisance, then θ) and one least-squares step is taken on every sample. A screened-out
    sample comes back when, after that step, it passes the screen of :func:`screen_outliers`
    while every kept sample still passes — and when it also passes after the step taken
    without it (leave one out), i.e. when the other samples predict it. A gross outlier (a
    misread marker) has nothing that predicts it and stays out; samples that an unmodelled
    effect pushed out have one another: on the FR3 recording a 28 mrad load backlash on
    panda_joint5 pushes out all six samples on one side of that joint's load sign, so its
    column is constant on the samples kept and the term cannot even be tested there, while
    the UR10e's two screened samples, which a measurement-frame drift would bring back, are
    each predicted by no step fitted without it.
    """
    all_rows = ctx.all_rows
    out = np.setdiff1d(all_rows, fit.rows)
    if out.size == 0 or not library:
        return out[:0]
    n, d = ctx.data.n_samples, ctx.data.rows
    limit, median = _screen_limit(ctx, level)
    design = evaluate(ctx, fit.terms, fit.params, all_rows, candidates=tuple(library))
    residual = whitened(design.residual, fit.weights).reshape(-1)
    present = np.concatenate(
        [
            fit.nuisance(whitened(design.links, fit.weights)).reshape(n * d, -1),
            whitened(design.terms, fit.weights).reshape(n * d, -1),
        ],
        axis=1,
    )

    def passing(columns: FloatArray, samples: IntArray) -> BoolArray:
        """The screen after the step fitted on ``samples``."""
        chosen = np.zeros((n, d), dtype=bool)
        chosen[samples] = True
        on = chosen.reshape(-1)
        step, *_ = np.linalg.lstsq(columns[on], residual[on], rcond=None)
        norm2 = np.sum((residual - columns @ step).reshape(n, d) ** 2, axis=1)
        return _passing(norm2, fit.rows, limit, median)

    best = out[:0]
    for term in library:
        columns = np.concatenate(
            [present, whitened(design.candidates[term.key], fit.weights).reshape(n * d, -1)],
            axis=1,
        )
        ok = passing(columns, all_rows)
        back = out[ok[out]]
        if back.size <= best.size or not ok[fit.rows].all():
            continue
        both = np.union1d(fit.rows, back)
        vouched = np.array([i for i in back if passing(columns, both[both != i])[i]], dtype=np.intp)
        if vouched.size > best.size:
            best = vouched
    return best
