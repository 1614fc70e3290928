"""Held-out confirmation and gross-outlier screening for the discovery loop."""

from __future__ import annotations

import numpy as np
import scipy.stats
from numpy.typing import NDArray

from solver.calibration import pose_errors
from solver.discovery.fitting import (
    Context,
    ModelFit,
    evaluate,
    fit_model,
    fit_with_noise,
    whitened,
)
from solver.discovery.library import Term
from solver.discovery.results import HeldoutError
from solver.errors import CalibrationError
from solver.measurement.fit import row_errors

FloatArray = NDArray[np.float64]
IndexArray = NDArray[np.intp]


def kfold(n: int, folds: int, rng: np.random.Generator) -> list[tuple[IndexArray, IndexArray]]:
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
    folds: list[tuple[IndexArray, IndexArray]],
    weights: FloatArray,
    rows: IndexArray | None = None,
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
            fold_fit = fit_model(ctx, terms, fit.params, train, weights, max_iterations=4)
        except CalibrationError:
            fold_fit = fit
        design = evaluate(ctx, terms, fold_fit.params, test)
        errors = np.sum(whitened(design.residual, weights) ** 2, axis=1)
        per_sample[test] = errors
        sse += float(errors.sum())
        if ctx.data.is_pose:
            t_mm, r_deg = pose_errors(
                design.pose, ctx.data.measured_pose[test], position_only=ctx.data.position_only
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
    d = ctx.data.rows
    all_rows = ctx.all_rows
    limit = float(scipy.stats.chi2.isf(level / all_rows.size, d))
    median = float(scipy.stats.chi2.median(d))
    for _ in range(4):
        design = evaluate(ctx, terms, fit.params, all_rows)
        norm2 = np.sum(whitened(design.residual, fit.weights) ** 2, axis=1)
        scale = float(np.median(norm2[fit.rows])) / median
        rows = all_rows[norm2 <= limit * scale]
        if np.array_equal(rows, fit.rows):
            break
        fit = fit_with_noise(ctx, terms, fit.params, rows, fit.weights, rounds=1)
    return fit
