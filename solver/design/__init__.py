"""Optimal calibration experiments: which K poses to record (``kincal design``).

The information each candidate pose brings comes from the calibration's own Jacobians
(:mod:`solver.design.information`); a criterion of the summed information (D, A, E, or I for a
task region, :mod:`solver.design.criteria`) is maximised over weights on the candidates — a convex
relaxation solved by Clarabel or a first-order method, which bounds every set of K poses
(:mod:`solver.design.relaxation`) — and rounded to K poses by a stated rule
(:mod:`solver.design.rounding`). Constraints on measurable poses live in
:mod:`solver.design.candidates`; predicted standard errors in :mod:`solver.design.prediction`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from solver.arrays import FloatArray, IntArray
from solver.design.criteria import SMOOTH_CRITERIA, DesignProblem, efficiency
from solver.design.relaxation import Relaxation, solve_clarabel, solve_first_order
from solver.design.rounding import round_design

Method = Literal["auto", "clarabel", "first_order"]
CLARABEL_MAX_CANDIDATES = 200
"""``auto`` solves the relaxation with Clarabel up to this many candidates (its second-order cone
program grows with candidates × parameters: about 5 s at 200 candidates and 35 parameters), with
the first-order method beyond."""


@dataclass(frozen=True)
class Design:
    """K chosen candidates (sorted indices), their criterion ``value``, the relaxation that
    bounds it and the ``efficiency`` of the choice against that bound (1 = provably optimal)."""

    chosen: IntArray
    value: float
    relaxation: Relaxation
    efficiency: float


def solve_relaxation(problem: DesignProblem, method: Method = "auto") -> Relaxation:
    """The relaxation by ``method``; ``auto``: Clarabel for E (not differentiable: the
    first-order method cannot) and for small candidate sets without nuisance parameters, the
    first-order method otherwise (:func:`auto_method`)."""
    if method == "clarabel" or (method == "auto" and auto_method(problem) == "clarabel"):
        return solve_clarabel(problem)
    return solve_first_order(problem)


def auto_method(problem: DesignProblem) -> Method:
    """What ``auto`` solves ``problem`` with: Clarabel for E, and for the smooth criteria up to
    :data:`CLARABEL_MAX_CANDIDATES` candidates when no block has nuisance parameters (the
    second-order cone program); the first-order method beyond, and for every block with
    nuisance parameters (a measurement model's own unknowns: Clarabel then needs the
    (p+e)² LMI of the Schur complement, minutes at 40 candidates and 47 columns where the
    first-order method takes a fraction of a second)."""
    if problem.criterion not in SMOOTH_CRITERIA:
        return "clarabel"
    if any(block.nuisance for block in problem.blocks):
        return "first_order"
    return "clarabel" if problem.n_candidates <= CLARABEL_MAX_CANDIDATES else "first_order"


def optimal_design(
    problem: DesignProblem,
    joint_positions: FloatArray,
    *,
    method: Method = "auto",
    spacing_rad: float = 0.0,
) -> Design:
    """Solve the relaxation, round it (:func:`solver.design.rounding.round_design`) and report
    the chosen poses against the relaxation's certified bound."""
    relaxation = solve_relaxation(problem, method)
    chosen = round_design(problem, relaxation.weights, joint_positions, spacing_rad=spacing_rad)
    value = problem.set_value(chosen)
    return Design(
        chosen, value, relaxation, efficiency(problem.criterion, value, relaxation.upper_bound)
    )


__all__ = [
    "CLARABEL_MAX_CANDIDATES",
    "Design",
    "Method",
    "auto_method",
    "optimal_design",
    "solve_relaxation",
]
