"""Residual health report: where the model misses, before any physical hypothesis.

For a fitted model: the noise scale per block (translation, rotation) with the degrees of
freedom the fit used, χ²/dof against the sensor's stated noise (when given), and for every
joint the dependence of the residual on its angle, its gravity torque and its approach
direction, plus the dependence on acquisition time and on measured range (depth). Each is a
score test of "each residual component is a smooth function of the variable" (Legendre
polynomials of degree 1..3; a sign for the direction) against the model, with the share of
the residual sum of squares it would explain, overall and per residual component.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.arrays import FloatArray
from solver.discovery.checks import component_columns
from solver.discovery.features import legendre_basis
from solver.discovery.fitting import Context, ModelFit
from solver.discovery.scoring import NullModel, score_tests, unexplained_basis

COMPONENT_NAMES = ("x", "y", "z", "rx", "ry", "rz")


@dataclass(frozen=True)
class Dependence:
    """How much of the residual one variable explains (``components`` per residual row)."""

    variable: str  # "angle", "torque", "direction", "time", "range"
    joint_index: int | None
    p_value: float
    explained_fraction: float
    components: dict[str, float]


@dataclass(frozen=True)
class HealthReport:
    """Residual scale and structure of one fitted model (m and rad inside, mm/deg here)."""

    n_samples: int
    n_parameters: int
    sigma_translation_mm: float
    sigma_rotation_deg: float | None
    rms_translation_mm: float
    rms_rotation_deg: float | None
    chi2_per_dof: float | None
    dependences: list[Dependence]


def health_report(
    ctx: Context,
    fit: ModelFit,
    sensor_sigma: tuple[float, float] | None = None,
) -> HealthReport:
    """The report for ``fit``; ``sensor_sigma`` = (translation m, rotation rad) if known."""
    null = NullModel.from_fit(fit)
    d = null.d
    rows = fit.rows
    residual = fit.design.residual
    variables: list[tuple[str, int | None, FloatArray]] = []
    for j in range(ctx.chain.n_joints):
        name = ctx.chain.joint_names[j]
        q = ctx.data.joint_positions[rows, j]
        variables.append(("angle", j, legendre_basis(q, range(1, 4))))
        if name in ctx.bank.basis.axis_names:
            tau = ctx.bank.nominal_tau(name)[rows]
            if np.ptp(tau) > 1e-9:
                variables.append(("torque", j, legendre_basis(tau, range(1, 4))))
        direction = -2.0 * ctx.bank.lag[rows, j]
        if np.ptp(direction) > 0:
            variables.append(("direction", j, direction[:, None]))
    clock = ctx.bank.clock[rows]
    if np.ptp(clock) > 0:
        variables.append(("time", None, legendre_basis(clock, range(1, 4))))
    ranges = ctx.data.range_m()
    if ranges is not None:
        variables.append(("range", None, legendre_basis(ranges[rows], range(1, 4))))
    rss = float(null.residual @ null.residual)
    names = COMPONENT_NAMES if ctx.data.is_pose else ctx.data.model.components
    dependences = []
    tests = score_tests(
        null, {f"{v}:{j}": component_columns(basis, d) for v, j, basis in variables}
    )
    for variable, joint, basis in variables:
        result = tests.get(f"{variable}:{joint}")
        if result is None:
            continue
        dependences.append(
            Dependence(
                variable,
                joint,
                result.p_value,
                result.delta_ss / rss,
                _per_component(null, basis, d, names),
            )
        )
    dependences.sort(key=lambda dep: dep.p_value)
    weights = fit.weights
    sigma = 1.0 / weights
    blocks = ctx.data.noise_blocks()
    translation_rows, rotation_rows = blocks[0], blocks[1] if len(blocks) > 1 else None
    chi2 = None
    if sensor_sigma is not None:
        scale = np.full(d, sensor_sigma[0])
        if rotation_rows is not None:
            scale[rotation_rows] = sensor_sigma[1]
        chi2 = float(np.sum((residual / scale) ** 2) / max(fit.dof, 1))
    rotation = None if rotation_rows is None else residual[:, rotation_rows]
    translation = residual[:, translation_rows]
    return HealthReport(
        n_samples=int(rows.size),
        n_parameters=fit.rank,
        sigma_translation_mm=float(sigma[translation_rows][0] * 1e3),
        sigma_rotation_deg=None
        if rotation_rows is None
        else float(np.degrees(sigma[rotation_rows][0])),
        rms_translation_mm=float(
            np.sqrt(np.mean(np.sum(translation**2, axis=1) / max(translation.shape[1] // 3, 1)))
            * 1e3
        ),
        rms_rotation_deg=None
        if rotation is None
        else float(np.degrees(np.sqrt(np.mean(np.sum(rotation**2, axis=1))))),
        chi2_per_dof=chi2,
        dependences=dependences,
    )


def _per_component(
    null: NullModel, basis: FloatArray, d: int, names: tuple[str, ...]
) -> dict[str, float]:
    """Share of each residual component's sum of squares the variable explains."""
    residual = null.residual.reshape(-1, d)
    out = {}
    for c in range(d):
        columns = np.zeros((residual.shape[0], d, basis.shape[1]))
        columns[:, c, :] = basis
        q = unexplained_basis(null, columns.reshape(-1, basis.shape[1]))
        explained = float(np.sum((q.T @ null.residual) ** 2))
        total = float(residual[:, c] @ residual[:, c])
        out[names[c]] = explained / total if total > 0 else 0.0
    return out
