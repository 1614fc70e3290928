"""Data for the before/after residual plot of a finding (drawn by the service)."""

from __future__ import annotations

import numpy as np

from solver.arrays import FloatArray, IntArray
from solver.discovery.fitting import Context, ModelFit, evaluate
from solver.discovery.library import AxisSpec, Term
from solver.discovery.results import PlotPanel


def term_panels(ctx: Context, term: Term, before: ModelFit, after: ModelFit) -> list[PlotPanel]:
    """Apparent deflection per sample from the residuals before and after the term."""
    rows = after.rows
    panels = []
    if term.axes:
        units = tuple(dict.fromkeys((a.joint_index, a.direction) for a in term.axes))
        design_after = evaluate(ctx, after.terms, after.params, rows, unit_axes=units)
        design_before = evaluate(ctx, before.terms, before.params, rows, unit_axes=units)
        values = after.values()[term.key]
        gravity, payload = ctx.data.gravity_base, 0.0
        for unit_key in units:
            specs = [
                (a, v)
                for a, v in zip(term.axes, values, strict=True)
                if (a.joint_index, a.direction) == unit_key
            ]
            fitted = sum(
                (v * ctx.bank.column(a.feature, gravity, payload)[rows] for a, v in specs),
                start=np.zeros(rows.size),
            )
            driver, label = _driver(ctx, term, specs[0][0])
            driver = driver[rows]
            weights = after.weights
            panels.append(
                PlotPanel(
                    driver=driver,
                    driver_label=label,
                    before=_apparent(design_before.unit[unit_key], design_before.residual, weights),
                    after=_apparent(design_after.unit[unit_key], design_after.residual, weights),
                    fitted=fitted,
                    value_label=_axis_label(ctx, unit_key),
                )
            )
        return panels
    design_after = evaluate(ctx, after.terms, after.params, rows)
    design_before = evaluate(ctx, before.terms, before.params, rows)
    values = after.values()[term.key]
    # Columns of a term already in the model are its slice of the term columns.
    start = 0
    for t in after.terms:
        if t.key == term.key:
            break
        start += t.size
    columns = design_after.terms[:, :, start : start + term.size]
    effect = columns @ values  # (n, d)
    norm = np.linalg.norm(effect, axis=1)
    direction = effect / np.where(norm > 0, norm, 1.0)[:, None]
    driver, label = _global_driver(ctx, term, rows, norm)
    panels.append(
        PlotPanel(
            driver=driver,
            driver_label=label,
            before=np.einsum("nd,nd->n", direction, design_before.residual),
            after=np.einsum("nd,nd->n", direction, design_after.residual),
            fitted=norm,
            value_label="residual along the term's correction (m / rad)",
        )
    )
    return panels


def _apparent(unit: FloatArray, residual: FloatArray, weights: FloatArray) -> FloatArray:
    """Per-sample weighted least-squares rotation (rad) about an axis explaining the residual."""
    g = unit * weights
    r = residual * weights
    denominator = np.einsum("nd,nd->n", g, g)
    return np.einsum("nd,nd->n", g, r) / np.where(denominator > 0, denominator, np.inf)


def _driver(ctx: Context, term: Term, spec: AxisSpec) -> tuple[FloatArray, str]:
    data = ctx.data
    j = spec.joint_index
    name = ctx.chain.joint_names[j]
    kind = spec.feature.split(":")[0]
    if kind == "tau":
        axis = spec.feature[4:]
        return ctx.bank.nominal_tau(axis), f"gravity moment about {axis} [N·m]"
    if kind == "sign_tau":
        return ctx.bank.nominal_tau(name), f"gravity torque on {name} [N·m]"
    if kind == "lag":
        return -2.0 * ctx.bank.lag[:, j], f"approach direction of {name} (−1 / +1)"
    if kind == "time":
        unit = "min" if ctx.bank.clock_unit == "s" else "sample"
        scale = 1.0 / 60.0 if ctx.bank.clock_unit == "s" else 1.0
        return ctx.bank.clock * scale, f"time since first sample [{unit}]"
    return np.degrees(data.joint_positions[:, j]), f"{name} angle [deg]"


def _global_driver(
    ctx: Context, term: Term, rows: IntArray, norm: FloatArray
) -> tuple[FloatArray, str]:
    if term.effect == "depth_scale":
        pose = ctx.data.measured_pose[rows]
        if term.variant == "measurement_z":
            return pose[:, 2, 3], "depth along the measurement frame's z [m]"
        depth = np.einsum("nji,nj->ni", pose[:, :3, :3], pose[:, :3, 3])[:, 2]
        return depth, "depth along the marker frame's z [m]"
    if term.effect == "thermal_drift":
        return ctx.bank.clock[rows], f"time since first sample [{ctx.bank.clock_unit}]"
    return norm, "predicted correction (m / rad)"


def _axis_label(ctx: Context, unit_key: tuple[int, str]) -> str:
    j, direction = unit_key
    name = ctx.chain.joint_names[j]
    where = f"{name} axis" if direction == "joint" else f"{direction} ⟂ {name}"
    return f"rotation about {where} [rad]"
