"""Refinement of shape parameters of an accepted term (profiled, not tested)."""

from __future__ import annotations

import math
from dataclasses import replace

from solver.discovery.features import deadzones
from solver.discovery.fitting import (
    Context,
    ModelFit,
    ModelParameters,
    extend,
    fit_model,
    fit_with_noise,
)
from solver.discovery.library import Term, backlash_load_term, drift_term
from solver.distributions import chi2_isf
from solver.errors import CalibrationError


def refine_deadzone(
    ctx: Context, terms: tuple[Term, ...], fit: ModelFit
) -> tuple[Term, tuple[Term, ...], ModelFit]:
    """Choose the floating zone of the last (load-sign backlash) term by the refitted cost.

    Candidates are quantiles of |τ| (features.DEADZONE_QUANTILES); zone 0 is plain sign(τ).
    """
    term = terms[-1]
    assert term.joint_index is not None
    tau = ctx.bank.nominal_tau(ctx.chain.joint_names[term.joint_index])
    best_term, best_fit = term, fit
    for zone in deadzones(tau):
        variant = backlash_load_term(ctx.chain, term.joint_index, zone)
        if variant.key == term.key:
            continue
        trial = fit_model(
            ctx, (*terms[:-1], variant), fit.params, fit.rows, fit.weights, max_iterations=15
        )
        if trial.cost < best_fit.cost:
            best_term, best_fit = variant, trial
    if best_term is term:
        return term, terms, fit
    new_terms = (*terms[:-1], best_term)
    refit = fit_with_noise(ctx, new_terms, best_fit.params, fit.rows, fit.weights, rounds=1)
    return best_term, new_terms, refit


def refine_time_constant(
    ctx: Context, terms: tuple[Term, ...], fit: ModelFit
) -> tuple[Term, tuple[Term, ...], ModelFit]:
    """Profile the warm-up time constant of the last term (golden section on log T).

    The library tries two time constants; the accepted one is refined between 1/40 and 2×
    the recording's duration by minimising the refitted cost.
    """
    term = terms[-1]
    span = float(ctx.bank.clock.max())

    def variant(constant: float) -> Term:
        shape = f"warmup:{constant:.6g}"
        prefix = "measurement_frame:" if term.joint_index is None else ""
        axes = tuple(replace(a, feature=f"time:{shape}") for a in term.axes)
        return replace(term, variant=prefix + shape, axes=axes)

    cache: dict[float, ModelFit] = {}

    def cost(log_t: float) -> float:
        constant = float(f"{math.exp(log_t):.6g}")
        if constant not in cache:
            candidate = (*terms[:-1], variant(constant))
            cache[constant] = fit_model(
                ctx, candidate, fit.params, fit.rows, fit.weights, max_iterations=15
            )
        return cache[constant].cost

    low, high = math.log(span / 40.0), math.log(2.0 * span)
    ratio = (math.sqrt(5.0) - 1.0) / 2.0
    a, b = low, high
    c, d = b - ratio * (b - a), a + ratio * (b - a)
    for _ in range(14):
        if cost(c) < cost(d):
            b, d = d, c
            c = b - ratio * (b - a)
        else:
            a, c = c, d
            d = a + ratio * (b - a)
    best_constant = min(cache, key=lambda k: cache[k].cost)
    if cache[best_constant].cost >= fit.cost:
        return term, terms, fit
    refined = variant(best_constant)
    new_terms = (*terms[:-1], refined)
    refit = fit_with_noise(
        ctx, new_terms, cache[best_constant].params, fit.rows, fit.weights, rounds=1
    )
    return refined, new_terms, refit


def linear_unless_warmup_earns_it(
    ctx: Context,
    base_terms: tuple[Term, ...],
    base_params: ModelParameters,
    terms: tuple[Term, ...],
    fit: ModelFit,
    alpha: float,
) -> tuple[Term, tuple[Term, ...], ModelFit]:
    """The time shape of an accepted warm-up drift (the last of ``terms``, fitted in ``fit``):
    the linear drift of the same joint (or measurement frame) unless the warm-up beats it.

    A warm-up 1 − exp(−t/T) tends to a linear drift as T grows, so it is the linear shape with
    one more parameter, T: it is kept only if it lowers the whitened cost (‖r‖², χ² under the
    fit's noise scale) by more than the χ²₁ quantile at ``alpha`` (a likelihood-ratio test
    in ``fit``'s weights). Otherwise the simpler shape is named: which of the library's
    variants happened to get the lowest p-value does not decide a shape (issue 32: a linear
    drift concealed in the real TIAGo and platonics recordings was named a warm-up).
    ``base_terms``/``base_params``: the model before the drift was added.
    """
    term = terms[-1]
    linear = drift_term(ctx.chain, term.joint_index, "linear", ctx.bank.clock_unit)
    if linear.key in {t.key for t in base_terms}:
        return term, terms, fit  # a warm-up on top of the same joint's linear drift
    linear_terms, start = extend(base_params, base_terms, linear)
    try:
        linear_fit = fit_model(ctx, linear_terms, start, fit.rows, fit.weights)
    except CalibrationError:
        return term, terms, fit  # no linear fit to compare with: the warm-up as fitted
    if linear_fit.cost - fit.cost > chi2_isf(alpha, 1):
        return term, terms, fit
    refit = fit_with_noise(ctx, linear_terms, linear_fit.params, fit.rows, fit.weights, rounds=1)
    return linear, linear_terms, refit
