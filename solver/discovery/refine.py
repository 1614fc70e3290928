"""Refinement of shape parameters of an accepted term (profiled, not tested)."""

from __future__ import annotations

import math
from dataclasses import replace

from solver.discovery.features import deadzones
from solver.discovery.fitting import Context, ModelFit, fit_model, fit_with_noise
from solver.discovery.library import Term, backlash_load_term


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
