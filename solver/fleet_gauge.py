"""Parameters of several units of one robot model in one gauge (issue 31).

Unit u's deterministic fit (Eq. 10) moves the free columns F_u of its weighted stacked design
``A_u`` (rows: residual components, m and weighted rad; columns: local link twists δ_i in m and
rad — DESIGN.md §2, ``L_i ← L_i·Exp(δ_i)``, right-multiplied —, compliances in rad/N·m, the
measurement model's own unknowns in m). Pivoted QR keeps ``K_u ⊂ F_u``; the others ``R_u``
(unidentifiable, or pruned to nominal) stay at 0, and the kept columns absorb what they would
have done. Each ``r ∈ R_u`` is one gauge direction of the unit, with ``G = A_uᵀA_u``:

    n_r = e_r − E_K G_KK⁻¹ G_Kr        (A_u n_r ≈ 0 for an unidentifiable column)

— moving the parameters along ``n_r`` leaves the unit's residuals unchanged, so its estimate
is one representative of ``θ̂ + span{n_r}``. A function ``cᵀθ`` of the compared columns C
(inner-link twist components, named alike on every unit; the frames, compliances and
unknowns of the measurement are nuisance, ``c`` is 0 there) has the same value in every gauge
of the unit iff ``c ⊥ n_r|C`` for every r: then, in the linear model,
``E[cᵀθ̂_u] = cᵀθ_u`` whatever the unit chose to remove. The **common gauge** holds the
functions every unit identifies: with the columns scaled by ``s`` (each column's RMS
sensitivity over the units, residual per parameter unit, so that every column counts alike as
in the pivoted QR; ``D = diag(s)``),

    V = (span_{u, r} D n_r|C)^⊥,    P = orthogonal projector onto V (|C|, |C|).

Unit u's value of column j in the common gauge is the j-th coordinate of its scaled estimate
projected onto V, unscaled,

    v_uj = (P D θ̂_u|C)_j / s_j = c_jᵀ θ̂_u,    c_j = D P e_j / s_j,

and ``c_j`` annihilates every gauge direction of every unit: v_uj estimates the same function
of every robot. Its standard error goes through the same projection,
``se_uj = σ_u (c_j|Kᵀ G_KK⁻¹ c_j|K)^½`` with ``σ_u² = rᵀr / (rows − |K_u|)``.
``share_j = P_jj = ‖P e_j‖²`` says how much of column j the common gauge holds (1: every unit
identifies it alone, v_uj is its own estimate; 0: no unit-independent part of it).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from solver.arrays import BoolArray, FloatArray, IntArray

DIRECTION_TOLERANCE = 1e-2
"""Gauge directions (unit-norm, scaled) whose span adds less than this singular value to the
others' are the same direction. Each unit is linearised at its own geometry, so one structural
direction (e.g. a translation along two parallel joint axes) differs between units by about
the corrections over the link lengths (mm over decimetres); counted apart, they leave almost
nothing in common. A function within this angle of a unit's gauge direction picks up at most
this fraction of the held parameter's true value."""


@dataclass(frozen=True)
class UnitInformation:
    """One unit's linearised fit at its solution, over its free columns (f of them).

    ``gram`` (f, f): ``AᵀA`` of the weighted design (residual rows in m, rotation rows times
    the fit's rotation weight; known-distance rows included). ``kept`` (f,): columns the fit
    estimated (the others held at their start). ``compared`` (f,): index of the column among
    the fleet's compared columns C, −1 for a nuisance column. ``estimate_compared`` (|C|,): the
    unit's fitted value of every compared column (m, rad; 0 where held). ``sigma2``: residual
    variance per weighted row, ``rᵀr / (rows − |K|)``. ``n_rows``: weighted rows of ``A``.
    """

    gram: FloatArray
    kept: BoolArray
    compared: IntArray
    estimate_compared: FloatArray
    sigma2: float
    n_rows: int


@dataclass(frozen=True)
class CommonGauge:
    """The fleet's common gauge over the compared columns C (see the module docstring).

    ``scale`` (|C|,) s_j, residual per parameter unit (m/m, m/rad); ``projector`` (|C|, |C|) P
    in scaled coordinates; ``share`` (|C|,) P_jj; ``dimension``: rank of P;
    ``n_directions``: independent gauge directions over the units."""

    scale: FloatArray
    projector: FloatArray
    share: FloatArray
    dimension: int
    n_directions: int


def gauge_directions(unit: UnitInformation) -> FloatArray:
    """The unit's gauge directions ``n_r`` restricted to the compared columns, (|C|, |R|):
    ``n_r = e_r − E_K G_KK⁻¹ G_Kr`` for every free column r the fit held."""
    kept = np.flatnonzero(unit.kept)
    held = np.flatnonzero(~unit.kept)
    n_compared = unit.estimate_compared.size
    absorbed = scipy.linalg.lstsq(unit.gram[np.ix_(kept, kept)], unit.gram[np.ix_(kept, held)])[0]
    directions = np.zeros((unit.kept.size, held.size))
    directions[held, np.arange(held.size)] = 1.0
    directions[kept] = -absorbed
    out = np.zeros((n_compared, held.size))
    mask = unit.compared >= 0
    out[unit.compared[mask]] = directions[mask]
    return out


def column_scale(units: Sequence[UnitInformation]) -> FloatArray:
    """s_j (|C|,): RMS over the units of each compared column's norm per weighted row
    (residual per parameter unit); 1 for a column no unit moves."""
    n_compared = units[0].estimate_compared.size
    total, count = np.zeros(n_compared), np.zeros(n_compared)
    for unit in units:
        mask = unit.compared >= 0
        total[unit.compared[mask]] += np.diag(unit.gram)[mask] / unit.n_rows
        count[unit.compared[mask]] += 1
    scale = np.sqrt(np.divide(total, count, out=np.zeros_like(total), where=count > 0))
    return np.where(scale > 0.0, scale, 1.0)


def common_gauge(
    units: Sequence[UnitInformation], tolerance: float = DIRECTION_TOLERANCE
) -> CommonGauge:
    """The subspace of the compared columns every unit identifies and its projector (module
    docstring): the orthogonal complement of every unit's scaled gauge directions."""
    scale = column_scale(units)
    stacked = np.concatenate([scale[:, None] * gauge_directions(u) for u in units], axis=1)
    n_compared = scale.size
    norms = np.linalg.norm(stacked, axis=0)
    stacked = stacked[:, norms > 0.0] / norms[norms > 0.0]
    if stacked.shape[1] == 0:
        basis = np.zeros((n_compared, 0))
    else:
        left, singular, _ = np.linalg.svd(stacked, full_matrices=False)
        basis = left[:, singular > tolerance * max(1.0, float(singular[0]))]
    projector = np.eye(n_compared) - basis @ basis.T
    return CommonGauge(
        scale,
        projector,
        np.clip(np.diag(projector), 0.0, 1.0),
        n_compared - basis.shape[1],
        basis.shape[1],
    )


def common_gauge_values(gauge: CommonGauge, unit: UnitInformation) -> tuple[FloatArray, FloatArray]:
    """The unit's value of every compared column in the common gauge and its standard error,
    (|C|,) each, in the column's unit (m, rad): ``v_j = c_jᵀ θ̂``, ``se_j = σ (c_jᵀ Cov c_j)^½``
    with ``c_j = D P e_j / s_j`` (module docstring)."""
    s = gauge.scale
    functionals = (s[:, None] * gauge.projector) / s[None, :]  # column j: c_j over C
    values = functionals.T @ unit.estimate_compared
    kept = np.flatnonzero(unit.kept)
    kept_compared = unit.compared[kept]
    on_compared = kept_compared >= 0
    inverse = np.linalg.pinv(unit.gram[np.ix_(kept, kept)])
    c = np.zeros((kept.size, s.size))
    c[on_compared] = functionals[kept_compared[on_compared]]
    variance = unit.sigma2 * np.einsum("kj,kl,lj->j", c, inverse, c)
    return values, np.sqrt(np.clip(variance, 0.0, None))
