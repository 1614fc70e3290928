"""A discovery's findings for people: the summary printed after ``kincal discover``, the sizes
in display units, the solver's results as the findings JSON schema, and the residual figures."""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from schemas.discovery import (
    Ambiguity,
    Candidate,
    Dependence,
    Detectability,
    DetectableSize,
    DiscoveredModel,
    DiscoveryOptions,
    ErrorPair,
    Finding,
    FindingsResult,
    Health,
    Heldout,
    ModelTerm,
    Unexplained,
)
from solver import discovery as solver_discovery
from solver import lie
from solver.discovery.carry import (
    is_correction,
)
from solver.discovery.explain import describe, reported_parameters
from solver.discovery.health import HealthReport
from solver.discovery.library import UNEXPLAINED
from solver.discovery.results import HeldoutError, PlotPanel, TermEstimate

PROTOCOL = "{k}-fold cross-validation (seed {seed}), the same folds before and after"


def summary(findings: FindingsResult) -> str:
    """What a user reads after ``kincal discover``."""
    lines = [
        f"tested {findings.n_candidates} library terms on {findings.dataset.n_samples} samples "
        f"({len(findings.outliers.removed_rows)} gross outliers left out)"
    ]
    for f in findings.findings:
        lines.append(f"found: {f.explanation}")
    for a in findings.ambiguous:
        lines.append(f"ambiguous: {a.explanation}")
    for u in findings.unexplained:
        text = u.explanation
        lines.append(text if text.startswith("unexplained") else f"unexplained: {text}")
    for r in findings.random_effects:
        lines.append(f"random: {r.explanation}")
    unseen = [] if findings.measurement is None else findings.measurement.not_candidates
    if unseen:
        joints = sorted({u.joint for u in unseen if u.joint}, key=findings.robot.joint_names.index)
        lines.append(
            f"not candidates: {len(unseen)} library terms "
            f"{'on ' + ', '.join(joints) + ' ' if joints else ''}whose effect cancels in what is "
            "measured (each with the reason in measurement.not_candidates)"
        )
    if not (findings.findings or findings.ambiguous or findings.unexplained):
        lines.append("nothing missing: no library term or structure is significant")
    if findings.detectability is not None and findings.detectability.sizes:
        lines += detectability_lines(findings.detectability)
    elif findings.detectability is None:
        lines.append("smallest detectable sizes: not computed (--no-detectability)")
    before, after = findings.heldout.before, findings.heldout.after
    rot = (
        ""
        if before.rot_deg is None or after.rot_deg is None
        else f", {before.rot_deg:.3g} → {after.rot_deg:.3g} deg"
    )
    lines.append(f"held-out error: {before.trans_mm:.3g} → {after.trans_mm:.3g} mm{rot}")
    return "\n".join(lines)


# Display scale and unit of a size by the end of its parameter name (first match wins).
DISPLAY_UNITS = (
    ("_rad_per_nm", 1e6, "µrad/N·m"),
    ("_rad_per_s", 3.6e6, "mrad/h"),
    ("_rad_per_sample", 1e5, "mrad/100 samples"),
    ("_m_per_s", 3.6e6, "mm/h"),
    ("_m_per_sample", 1e5, "mm/100 samples"),
    ("_rad", 1e3, "mrad"),
    ("_m", 1e3, "mm"),
    ("_kg", 1.0, "kg"),
    ("scale", 1e3, "mm/m"),
    ("scale_error", 1e3, "mm/m"),
)


def display_size(
    value: float | None,
    parameter: str,
    reason: str | None = None,
    separated_from: str | None = None,
) -> str:
    """A detectable size in an engineer's unit, e.g. ``0.12 mrad``; ``–`` when none, with the
    reason when one is given, and the term it must be told from when that set the size."""
    if value is None:
        return f"– ({reason})" if reason else "–"
    shown = f"{value:.2g}"
    for suffix, scale, unit in DISPLAY_UNITS:
        if parameter.endswith(suffix):
            shown = f"{value * scale:.2g} {unit}"
            break
    return f"{shown} (to tell from {separated_from})" if separated_from else shown


def detectability_groups(
    detectability: Detectability,
) -> dict[str, list[DetectableSize]]:
    """Detectable sizes by term label (effect, variant, size parameter when it is not the
    only one), in report order."""
    groups: dict[str, list[DetectableSize]] = {}
    for size in detectability.sizes:
        variant = f" ({size.variant})" if size.variant else ""
        part = (
            size.parameter.split("_")[0]
            if size.parameter.startswith(("translation", "rotation"))
            else ""
        )
        label = f"{size.effect}{variant}" + (f" {part}" if part else "")
        groups.setdefault(label, []).append(size)
    return groups


def detectability_lines(detectability: Detectability) -> list[str]:
    """The CLI's statement of what this recording could have seen."""
    lines = [
        f"smallest detectable sizes (score test at {detectability.level:.2g} per term, "
        f"{detectability.power:.0%} power; at least the size at which it is told from the "
        "library term named) — nothing larger went unseen:"
    ]
    for label, sizes in detectability_groups(detectability).items():
        shown = ", ".join(
            f"{s.joint + ' ' if s.joint else ''}"
            f"{display_size(s.smallest, s.parameter, s.reason, s.separated_from)}"
            for s in sizes
        )
        lines.append(f"  {label}: {shown}")
    return lines


# --- conversion ------------------------------------------------------------------------------


def detectability_schema(
    result: solver_discovery.DiscoveryResult, names: tuple[str, ...]
) -> Detectability | None:
    if result.detectable is None:
        return None
    return Detectability(
        level=result.detection_level,
        power=result.detection_power,
        sizes=[
            DetectableSize(
                effect=d.term.effect,  # type: ignore[arg-type]
                joint=joint_name(d.term.joint_index, names),
                variant=d.term.variant,
                parameter=d.parameter,
                smallest=d.smallest if math.isfinite(d.smallest) else None,
                reason=d.reason or None,
                separated_from=None
                if d.separated_from is None
                else describe(d.separated_from, names),
            )
            for d in result.detectable
        ],
    )


def _pair(error: HeldoutError) -> ErrorPair:
    return ErrorPair(trans_mm=error.translation_mm, rot_deg=error.rotation_deg)


def heldout_schema(before: HeldoutError, after: HeldoutError, options: DiscoveryOptions) -> Heldout:
    return Heldout(
        before=_pair(before),
        after=_pair(after),
        protocol=PROTOCOL.format(k=options.folds, seed=options.seed),
    )


def _finite(values: dict[str, float]) -> dict[str, float]:
    return {k: float(v) for k, v in values.items() if math.isfinite(v)}


def joint_name(index: int | None, names: tuple[str, ...]) -> str | None:
    return None if index is None else names[index]


def finding_schema(
    f: solver_discovery.Finding,
    names: tuple[str, ...],
    options: DiscoveryOptions,
    plot: str | None,
) -> Finding:
    e = f.estimate
    return Finding(
        effect=e.term.effect,  # type: ignore[arg-type]
        joint=joint_name(e.term.joint_index, names),
        variant=e.term.variant,
        parameters=_finite(e.parameters),
        stderr=_finite(e.stderr),
        p_value=e.p_value,
        absorbed_fraction=e.absorbed_fraction,
        stability=e.stability,
        heldout=heldout_schema(f.heldout_before, f.heldout_after, options),
        explanation=f.explanation,
        plot=plot,
    )


def _candidate(e: TermEstimate, names: tuple[str, ...]) -> Candidate:
    return Candidate(
        effect=e.term.effect,  # type: ignore[arg-type]
        joint=joint_name(e.term.joint_index, names),
        variant=e.term.variant,
        parameters=_finite(e.parameters),
        stderr=_finite(e.stderr),
        p_value=e.p_value,
        absorbed_fraction=e.absorbed_fraction,
    )


def ambiguity_schema(a: solver_discovery.Ambiguity, names: tuple[str, ...]) -> Ambiguity:
    poses = a.poses
    return Ambiguity(
        candidates=[_candidate(c, names) for c in a.candidates],
        with_geometry=a.with_geometry,
        correlation=a.correlation,
        kept_in_model=None if a.kept is None else describe(a.kept, names),
        separating_poses=[]
        if poses is None
        else [dict(zip(names, map(float, q), strict=True)) for q in poses.configurations],
        separation_now_sigma=None if poses is None else poses.separation_now_sigma,
        separation_after_sigma=None if poses is None else poses.separation_after_sigma,
        explanation=a.explanation,
    )


def unexplained_schema(u: solver_discovery.Unexplained, names: tuple[str, ...]) -> Unexplained:
    return Unexplained(
        joint=joint_name(u.joint_index, names),
        variable=u.variable,
        p_value=None if math.isnan(u.p_value) else u.p_value,
        explained_fraction=None if math.isnan(u.explained_fraction) else u.explained_fraction,
        distance_correlation=u.distance_correlation,
        partially_described_by=u.partial,
        explanation=u.explanation,
    )


def health_schema(report: HealthReport, names: tuple[str, ...]) -> Health:
    return Health(
        n_samples=report.n_samples,
        n_parameters=report.n_parameters,
        sigma_translation_mm=report.sigma_translation_mm,
        sigma_rotation_deg=report.sigma_rotation_deg,
        rms_translation_mm=report.rms_translation_mm,
        rms_rotation_deg=report.rms_rotation_deg,
        chi2_per_dof=report.chi2_per_dof,
        dependences=[
            Dependence(
                variable=d.variable,
                joint=joint_name(d.joint_index, names),
                p_value=d.p_value,
                explained_fraction=d.explained_fraction,
                components=d.components,
            )
            for d in report.dependences
        ],
    )


def model_schema(
    result: solver_discovery.DiscoveryResult, names: tuple[str, ...], options: DiscoveryOptions
) -> DiscoveredModel:
    """The final model; the compliance-like part maps onto ``kincal calibrate`` options."""
    values = {}
    start = 0
    for t in result.terms:
        values[t.key] = result.params.theta[start : start + t.size]
        start += t.size
    compliant = list(options.compliant_joints)
    virtual = list(options.virtual_axes_at)
    gravity = np.asarray(options.gravity_base_m_s2, dtype=float)
    payload = options.payload_kg
    terms, corrections, not_carried = [], [], []
    for t in result.terms:
        params, _ = reported_parameters(t, values[t.key], np.zeros((t.size, t.size)))
        label = describe(t, names) if t.effect != UNEXPLAINED else f"unexplained {t.variant}"
        terms.append(
            ModelTerm(
                effect=t.effect,
                joint=joint_name(t.joint_index, names),
                variant=t.variant,
                parameters=_finite(params),
            )
        )
        if t.declared:
            continue
        if t.effect == "joint_compliance" and t.joint_index is not None:
            compliant.append(names[t.joint_index])
        elif t.effect in ("base_flex", "link_bending") and t.joint_index is not None:
            virtual.append(names[t.joint_index])
        elif t.effect == "gravity_direction":
            tilt = np.r_[values[t.key], 0.0]
            gravity = lie.so3_exp(tilt) @ gravity
        elif t.effect == "payload_mass":
            payload += float(values[t.key][0])
        elif is_correction(t):
            corrections.append(label)
        else:
            not_carried.append(label)
    return DiscoveredModel(
        terms=terms,
        calibrate_compliant_joints=sorted(set(compliant), key=names.index),
        calibrate_virtual_axes_at=sorted(set(virtual), key=names.index),
        calibrate_gravity_base_m_s2=(float(gravity[0]), float(gravity[1]), float(gravity[2])),
        calibrate_payload_kg=max(payload, 0.0),
        corrections=corrections,
        not_carried=not_carried,
    )


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9]+", "_", text).strip("_")[:60]


# --- figures ---------------------------------------------------------------------------------


def finding_figure(panels: list[PlotPanel], title: str, path: Path) -> Path:
    """Residuals against the variable that drives a term: before (model without it) and after.

    Angles are shown in mrad; the fitted term is the line the "before" points should follow.
    """
    from matplotlib.figure import Figure  # plotting only: kept out of a calibration's start-up

    figure = Figure(figsize=(5.2 * len(panels), 3.6), layout="constrained")
    axes = figure.subplots(1, len(panels), squeeze=False)[0]
    for ax, panel in zip(axes, panels, strict=True):
        scale, unit = (1e3, "mrad") if "[rad]" in panel.value_label else (1e3, "mm / mrad")
        order = np.argsort(panel.driver)
        ax.scatter(
            panel.driver,
            panel.before * scale,
            s=9,
            alpha=0.55,
            color="tab:red",
            label="before (without the term)",
        )
        ax.scatter(
            panel.driver,
            panel.after * scale,
            s=9,
            alpha=0.65,
            color="tab:blue",
            label="after (with the term)",
        )
        ax.plot(
            panel.driver[order],
            panel.fitted[order] * scale,
            color="black",
            lw=1.2,
            label="fitted term",
        )
        ax.set_xlabel(panel.driver_label)
        ax.set_ylabel(
            panel.value_label.replace("[rad]", f"[{unit}]").replace("(m / rad)", f"[{unit}]")
        )
        ax.axhline(0.0, color="grey", lw=0.6)
    axes[0].legend(fontsize=7, loc="best")
    figure.suptitle(_wrap(title, 70 * len(panels)), fontsize=8)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=100)
    return path


def _wrap(text: str, width: int) -> str:
    words, lines, line = text.split(), [], ""
    for word in words:
        if len(line) + len(word) + 1 > width:
            lines.append(line)
            line = word
        else:
            line = f"{line} {word}".strip()
    lines.append(line)
    return "\n".join(lines)
