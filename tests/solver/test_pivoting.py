"""Column-pivoted QR whose choices do not depend on rounding (solver.pivoting)."""

from __future__ import annotations

import numpy as np
import scipy.linalg
from hypothesis import given, settings
from hypothesis import strategies as st

from solver.pivoting import pivoted_qr, tiered_pivoted_qr

RANK_RTOL = 1e-9


def _design(seed: int, m: int, rank: int, p: int) -> np.ndarray:
    """(m, p) unit-norm columns of the given rank, some of them exact copies (ties)."""
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(m, rank)) @ rng.normal(size=(rank, p))
    a[:, -1] = a[:, 0]  # two columns with exactly the same norm at every step
    return a / np.linalg.norm(a, axis=0)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), rank=st.integers(1, 6), extra=st.integers(1, 5))
def test_greedy_pivots_with_ties_to_the_first_column(seed, rank, extra):
    """|R_jj| is the Householder QR's of the columns in pivot order, each pivot the largest
    norm left (within the tie tolerance), the first in column order among ties; inputs changed
    by 1e-12 give the same pivots."""
    a = _design(seed, 12, rank, rank + extra)
    diagonal, pivots = pivoted_qr(a)
    assert sorted(pivots) == list(range(a.shape[1]))
    r = scipy.linalg.qr(a[:, pivots], mode="r")[0]
    np.testing.assert_allclose(diagonal[:rank], np.abs(np.diag(r))[:rank], rtol=1e-8)
    q = np.zeros((a.shape[0], 0))
    for step in range(rank):
        left = a - q @ (q.T @ a)
        norms = np.linalg.norm(left, axis=0)
        norms[pivots[:step]] = -1.0
        ties = np.flatnonzero(norms >= (1 - 1e-6) * norms.max())
        assert pivots[step] == ties[0]
        q = np.linalg.qr(a[:, pivots[: step + 1]])[0]
    assert pivots[0] == 0  # every column has unit norm: the first in column order is taken
    rng = np.random.default_rng(seed)
    perturbed = pivoted_qr(a * (1 + 1e-12 * rng.normal(size=a.shape)))
    np.testing.assert_array_equal(perturbed[1][:rank], pivots[:rank])


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), rank=st.integers(2, 6), extra=st.integers(1, 5))
def test_first_columns_carry_every_direction_they_can(seed, rank, extra):
    """The independent pivots span the same space as plain pivoted QR's; the ``first`` columns
    are taken as far as they are independent, and a later column is taken only for a direction
    the first ones cannot produce."""
    a = _design(seed, 12, rank, rank + extra)
    first = np.zeros(a.shape[1], dtype=bool)
    first[-2:] = True
    diagonal, pivots = tiered_pivoted_qr(a, first, RANK_RTOL)
    kept = pivots[: int(np.sum(diagonal > RANK_RTOL * diagonal[0]))]
    assert kept.size == np.linalg.matrix_rank(a)
    first_rank = np.linalg.matrix_rank(a[:, first])
    assert np.all(first[kept[:first_rank]]) and not np.any(first[kept[first_rank:]])
    basis = np.linalg.qr(a[:, kept])[0]
    np.testing.assert_allclose(basis @ (basis.T @ a), a, atol=1e-9)
    assert sorted(pivots) == list(range(a.shape[1]))


def test_without_first_columns_it_is_plain_pivoted_qr():
    a = _design(3, 10, 4, 7)
    for first in (None, np.zeros(7, dtype=bool), np.ones(7, dtype=bool)):
        diagonal, pivots = tiered_pivoted_qr(a, first, RANK_RTOL)
        plain = pivoted_qr(a)
        np.testing.assert_array_equal(pivots, plain[1])
        np.testing.assert_array_equal(diagonal, plain[0])
