"""From relaxed weights to K poses, by a stated rule.

Rule (:func:`round_design`):

1. **Largest weights first.** Take candidates in decreasing relaxed weight (then decreasing
   directional derivative of the criterion at the relaxed optimum, which ranks the candidates
   the relaxation left at zero), skipping any closer than the minimum spacing to one already
   chosen, until K are chosen.
2. **Exchange.** Repeatedly replace the chosen pose whose swap gains most by one of the
   ``exchange_pool`` candidates with the largest directional derivative at the current design
   (respecting the spacing), while the criterion improves by more than 1e-9; at most
   ``max_passes`` swaps (Fedorov's exchange, restricted to a pool).

The relaxation's optimum bounds the result whatever the rule (every K-set is feasible for it).
"""

from __future__ import annotations

import numpy as np

from solver.arrays import FloatArray, IntArray
from solver.design.criteria import DesignProblem
from solver.errors import SolverError


def spaced(
    joint_positions: FloatArray, chosen: list[int], candidate: int, spacing_rad: float
) -> bool:
    """True if ``candidate`` is at least ``spacing_rad`` (Euclidean, joint space) from every
    chosen configuration."""
    if spacing_rad <= 0.0 or not chosen:
        return True
    distance = np.linalg.norm(joint_positions[chosen] - joint_positions[candidate], axis=1)
    return bool(np.all(distance >= spacing_rad))


def round_design(
    problem: DesignProblem,
    weights: FloatArray,
    joint_positions: FloatArray,
    *,
    spacing_rad: float = 0.0,
    exchange_pool: int = 50,
    max_passes: int = 50,
) -> IntArray:
    """K candidate indices (sorted) from relaxed ``weights`` (N,) by the rule above."""
    _, gradient = problem.value_and_gradient(weights)
    order = np.lexsort((-gradient, -weights))
    chosen: list[int] = []
    for n in order:
        if len(chosen) == problem.count:
            break
        if problem.distinct and n in chosen:
            continue
        if spaced(joint_positions, chosen, int(n), spacing_rad):
            chosen.append(int(n))
    if len(chosen) < problem.count:
        raise SolverError(
            f"only {len(chosen)} candidates are {spacing_rad:g} rad apart; lower the minimum "
            f"spacing or the number of poses ({problem.count}), or give more candidates"
        )
    return np.sort(
        exchange(problem, np.array(chosen), joint_positions, spacing_rad, exchange_pool, max_passes)
    )


def improvement_tolerance(problem: DesignProblem, value: float) -> float:
    """The least gain a swap must bring: for D (a log: a gain is relative in the
    geometric-mean eigenvalue) 1e-9 · max(1, |φ|); for A, I and E (variances and eigenvalues
    of any units: an I criterion in m² is ~1e-9 itself) 1e-9 · |φ|."""
    if problem.criterion == "D":
        return 1e-9 * max(1.0, abs(value))
    return 1e-9 * abs(value)


def exchange(
    problem: DesignProblem,
    chosen: IntArray,
    joint_positions: FloatArray,
    spacing_rad: float,
    pool_size: int,
    max_passes: int,
) -> IntArray:
    """Best single swaps against a pool of promising candidates while the criterion improves."""
    current = chosen.copy()
    value = problem.set_value(current)
    for _ in range(max_passes):
        weights = np.zeros(problem.n_candidates)
        np.add.at(weights, current, 1.0 / problem.count)
        _, gradient = problem.value_and_gradient(weights)
        gradient[current] = -np.inf
        pool = np.argsort(-gradient, kind="stable")[:pool_size]
        best = (value + improvement_tolerance(problem, value), -1, -1)
        pool = pool[np.isfinite(gradient[pool])]
        for i in range(current.size):
            others = [int(c) for j, c in enumerate(current) if j != i]
            keep = [spaced(joint_positions, others, int(n), spacing_rad) for n in pool]
            allowed = pool[np.array(keep, dtype=bool)]
            if allowed.size == 0:
                continue
            values = problem.swap_values(current, i, allowed)
            j = int(np.argmax(values))
            if values[j] > best[0]:
                best = (float(values[j]), i, int(allowed[j]))
        if best[1] < 0:
            break
        current[best[1]] = best[2]
        value = problem.set_value(current)
    return current
