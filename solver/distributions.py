"""Tail probabilities and quantiles of the test statistics' distributions, each the formula
scipy.stats uses for it (``scipy.stats.<distribution>._sf`` and friends), computed with
scipy.special: importing scipy.stats would cost ~0.5 s at every start of ``kincal discover``
(``check`` and ``calibrate`` do not load it either), and the numbers are the same to the last
bit (tests/solver/test_distributions.py compares them with scipy.stats)."""

from __future__ import annotations

import scipy.special

# scipy.stats.ncf.sf evaluates this private ufunc of scipy.special (Boost's non-central F); the
# public ``ncfdtr`` is another implementation, which differs in the last bits of 1 − CDF. A SciPy
# without it (the lock file pins one with it) falls back on scipy.stats itself.
_NCF_SF = getattr(scipy.special._ufuncs, "_ncf_sf", None)


def chi2_quantile(level: float, dof: float) -> float:
    """The ``level`` quantile of χ²_dof (``scipy.stats.chi2.ppf``; level 0.5: the median)."""
    return float(2.0 * scipy.special.gammaincinv(0.5 * dof, level))


def chi2_survival(statistic: float, dof: int) -> float:
    """``P(χ²_dof > statistic)`` (``scipy.stats.chi2.sf``); 1 with no degree of freedom."""
    if dof <= 0:
        return 1.0
    return float(scipy.special.gammaincc(0.5 * dof, 0.5 * max(statistic, 0.0)))


def chi2_isf(alpha: float, dof: float) -> float:
    """The value χ²_dof exceeds with probability ``alpha`` (``scipy.stats.chi2.isf``)."""
    return float(scipy.special.chdtri(dof, alpha))


def t_sf(t: float, dof: float) -> float:
    """``P(T_dof > t)`` of Student's t (``scipy.stats.t.sf``)."""
    return float(scipy.special.stdtr(dof, -t))


def f_isf(alpha: float, dfn: float, dfd: float) -> float:
    """The value F(dfn, dfd) exceeds with probability ``alpha`` (``scipy.stats.f.isf``)."""
    return float(scipy.special.fdtri(dfn, dfd, 1.0 - alpha))


def ncf_sf(x: float, dfn: float, dfd: float, noncentrality: float) -> float:
    """``P(F(dfn, dfd, λ) > x)`` of the non-central F with λ = ``noncentrality``
    (``scipy.stats.ncf.sf``)."""
    if _NCF_SF is None:
        import scipy.stats

        return float(scipy.stats.ncf.sf(x, dfn, dfd, noncentrality))
    return float(_NCF_SF(x, dfn, dfd, noncentrality))
