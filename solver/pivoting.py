"""Column-pivoted QR whose choice of columns does not depend on rounding.

Which parameters a fit keeps and which it reports as unidentifiable comes from column-pivoted
QR: at each step the column with the largest norm left after projecting out the ones chosen
(Businger & Golub 1965). LAPACK's ``geqp3`` takes the exact largest, so among columns whose norms
agree to rounding — every column at the first step once they are scaled to unit norm, and any
two columns that play the same role in the chain — the choice is decided by the last bits of
the arithmetic: another BLAS kernel, or inputs changed by 1e-12, chose other columns, so other
parameters were reported and the fit moved by up to 6 % of its residuals (a position recording
of the Panda, 34 of 47 columns kept either way, 12 names exchanged).

Here norms within :data:`TIE_RTOL` of the largest count as equal and the first such column in
the caller's order is taken, which is what ``geqp3`` does for exactly equal norms. The
arithmetic runs on the R factor of an unpivoted Householder QR, which carries every column norm
and inner product of the design (``AᵀA = RᵀR``), so the O(m·P²) work is done once by LAPACK and
the choices on a P × P matrix.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from solver.arrays import FloatArray, IntArray

TIE_RTOL = 1e-6
"""Column norms within this fraction of the largest are a tie (rounding moves them by ~1e-13)."""


def pivoted_qr(design: FloatArray, *, tie_rtol: float = TIE_RTOL) -> tuple[FloatArray, IntArray]:
    """|R_jj| (P,) in pivot order and the pivots (P,) of a column-pivoted QR of ``design`` (m, P).

    Greedy: each step takes the column whose norm orthogonal to the ones taken is largest, the
    first in column order among those within ``tie_rtol`` of it. Pivots after the numerical
    rank come with diagonals at rounding level, as LAPACK's do.
    """
    m, p = design.shape
    if p == 0:
        return np.zeros(0), np.zeros(0, dtype=np.intp)
    # columns orthogonal to the pivots taken so far, as rows of R (AᵀA = RᵀR)
    left = np.array(np.linalg.qr(design, mode="r") if m > p else design, dtype=float)
    remaining = np.ones(p, dtype=bool)
    pivots = np.zeros(p, dtype=np.intp)
    diagonal = np.zeros(p)
    for step in range(p):
        norms = np.where(remaining, np.linalg.norm(left, axis=0), -1.0)
        largest = float(norms.max())
        chosen = int(np.flatnonzero(norms >= (1.0 - tie_rtol) * largest)[0])
        pivots[step], diagonal[step] = chosen, max(float(norms[chosen]), 0.0)
        remaining[chosen] = False
        if diagonal[step] > 0.0:
            unit = left[:, chosen] / diagonal[step]
            for _ in range(2):  # twice is enough (Kahan–Parlett)
                left -= np.outer(unit, unit @ left)
        left[:, chosen] = 0.0
    return diagonal, pivots


def tiered_pivoted_qr(
    design: FloatArray, first: NDArray[np.bool_] | None, rank_rtol: float
) -> tuple[FloatArray, IntArray]:
    """:func:`pivoted_qr` of ``design`` (m, P) with the ``first`` columns (P,) pivoted before
    the others, which are then taken orthogonal to the independent ``first`` columns: a
    direction both can carry is carried by a ``first`` column. |R_jj| (P,) and pivots (P,):
    the independent pivots of each tier (|R_jj| above ``rank_rtol`` of the first pivot's), then
    every dependent one. The same as :func:`pivoted_qr` when ``first`` is None, empty or every
    column."""
    if first is None or not np.any(first) or np.all(first):
        return pivoted_qr(design)
    first = np.asarray(first, dtype=bool)
    independent: list[IntArray] = []
    dependent: list[IntArray] = []
    diagonals: tuple[list[FloatArray], list[FloatArray]] = ([], [])
    basis = np.zeros((design.shape[0], 0))
    largest: float | None = None
    for members in (np.flatnonzero(first), np.flatnonzero(~first)):
        left = design[:, members]
        for _ in range(2):  # orthogonal to the columns taken (twice: Kahan–Parlett)
            left = left - basis @ (basis.T @ left)
        diagonal, pivots = pivoted_qr(left)
        largest = float(diagonal[0]) if largest is None else largest
        rank = int(np.sum(diagonal > rank_rtol * largest))
        independent.append(members[pivots[:rank]])
        dependent.append(members[pivots[rank:]])
        diagonals[0].append(diagonal[:rank])
        diagonals[1].append(diagonal[rank:])
        taken = np.concatenate(independent)
        basis = np.linalg.qr(design[:, taken])[0] if taken.size else basis
    return (
        np.concatenate(diagonals[0] + diagonals[1]),
        np.concatenate(independent + dependent),
    )
