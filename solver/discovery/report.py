"""Entries of the discovery report: estimates, ambiguities, unexplained structure."""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from solver.arrays import FloatArray
from solver.discovery.checks import OutlierCluster, StructureTest
from solver.discovery.design import separating_poses
from solver.discovery.explain import describe, reported_parameters
from solver.discovery.fitting import Context, ModelFit
from solver.discovery.library import Term
from solver.discovery.results import Ambiguity, TermEstimate, Unexplained
from solver.discovery.scoring import NullModel, ScoreTest, canonical_correlation


@dataclass
class Misfit:
    """A joint whose structure in one family the library cannot describe (or only with the
    wrong sign)."""

    joint_index: int
    family: str
    p_value: float
    partial: list[str]
    modelled: bool = False
    wrong_sign: list[str] = field(default_factory=list)


def estimate_of(term: Term, test: ScoreTest, stability: float | None = None) -> TermEstimate:
    covariance = np.diag(test.stderr**2)
    params, errors = reported_parameters(term, test.estimate, covariance)
    return TermEstimate(term, params, errors, test.p_value, test.absorbed_fraction, stability)


def term_covariances(fit: ModelFit) -> dict[str, FloatArray]:
    out, start = {}, 0
    for t in fit.terms:
        out[t.key] = fit.covariance[start : start + t.size, start : start + t.size]
        start += t.size
    return out


def sign_note(term: Term, test: ScoreTest, names: tuple[str, ...]) -> str:
    params, errors = reported_parameters(term, test.estimate, np.diag(test.stderr**2))
    values = ", ".join(
        f"{k} = {v:.3g}" + (f" ± {errors[k]:.2g}" if k in errors else "")  # a harmonic is exact
        for k, v in params.items()
    )
    return f"{describe(term, names)} fits with the wrong sign ({values})"


def unexplained_entries(
    misfits: list[Misfit],
    structure: list[StructureTest],
    names: tuple[str, ...],
    cluster: OutlierCluster | None = None,
    clock_unit: str = "s",
) -> list[Unexplained]:
    """One entry per joint (and per global variable), misfit evidence first; ``cluster``
    (screened-out samples bunched in time, an angle or a load) joins its joint's entry."""
    by_joint: dict[object, Unexplained] = {}
    for m in misfits:
        joint = names[m.joint_index]
        variable = "angle" if m.family == "angle" else "gravity torque"
        partial = f"; {', '.join(m.partial)} only partly describe it" if m.partial else ""
        if m.wrong_sign:
            partial += "; " + "; ".join(m.wrong_sign) + ", which no physical mechanism does"
        if m.modelled:
            partial += "; kept in the model as an unnamed function, so predictions include it"
        by_joint[m.joint_index] = Unexplained(
            joint_index=m.joint_index,
            variable=m.family,
            p_value=m.p_value,
            explained_fraction=float("nan"),
            distance_correlation=None,
            partial=list(m.partial),
            explanation=(
                f"unexplained, concentrated in {joint}: a deflection about its axis that "
                f"depends on its {variable} in a way no library term describes "
                f"(p = {m.p_value:.2g}){partial}; not named."
            ),
        )
    for s in structure:
        share = f"{100 * s.explained_fraction:.2g} % of the remaining residual"
        if s.joint_index is None:
            what = "acquisition time" if s.kind == "time" else "measured range (depth)"
            key: object = s.kind
            text = (
                f"unexplained: the residual follows the {what} in a way no library term "
                f"describes ({share}, p = {s.p_value:.2g})."
            )
        else:
            key = s.joint_index
            how = {
                "angle": "a deflection about its axis that is a function of its angle",
                "load": "a deflection about its axis that is a function of its gravity load",
                "components": "residuals that vary with its angle",
            }[s.kind]
            dcor = (
                ""
                if s.distance_correlation is None
                else f", distance correlation {s.distance_correlation:.2f}"
            )
            text = (
                f"unexplained, concentrated in {names[s.joint_index]}: {how} that no library "
                f"term explains ({share}, p = {s.p_value:.2g}{dcor})."
            )
        _merge(
            by_joint,
            key,
            Unexplained(
                s.joint_index,
                s.kind,
                s.p_value,
                s.explained_fraction,
                s.distance_correlation,
                [],
                text,
            ),
        )
    if cluster is not None:
        key = "time" if cluster.joint_index is None else cluster.joint_index
        text = _cluster_text(cluster, names, clock_unit)
        _merge(
            by_joint,
            key,
            Unexplained(
                cluster.joint_index, "outliers", cluster.p_value, float("nan"), None, [], text
            ),
        )
    return sorted(
        by_joint.values(),
        key=lambda u: (
            -(0.0 if math.isnan(u.explained_fraction) else u.explained_fraction),
            u.p_value,
        ),
    )


def _merge(by_joint: dict[object, Unexplained], key: object, entry: Unexplained) -> None:
    """Add ``entry`` under ``key``, or fold it into the entry already there (one per joint):
    the smaller p-value, the larger explained share, both explanations."""
    old = by_joint.get(key)
    if old is None:
        by_joint[key] = entry
        return
    by_joint[key] = replace(
        old,
        p_value=min(old.p_value, entry.p_value),
        explained_fraction=float(np.fmax(old.explained_fraction, entry.explained_fraction)),
        distance_correlation=old.distance_correlation or entry.distance_correlation,
        explanation=f"{old.explanation} {entry.explanation[0].upper()}{entry.explanation[1:]}",
    )


def _cluster_text(c: OutlierCluster, names: tuple[str, ...], clock_unit: str) -> str:
    """The report line of screened-out samples bunched in time, a joint's angle or its load."""
    if c.joint_index is None:
        where = f"rows acquired between {c.low:.4g} and {c.high:.4g} {clock_unit}"
        what = "unexplained: a disturbance during the recording"
    elif c.variable == "angle":
        joint = names[c.joint_index]
        where = f"{joint} between {np.degrees(c.low):.3g}° and {np.degrees(c.high):.3g}°"
        what = (
            f"unexplained, concentrated in {joint}: a local effect of its angle "
            "(e.g. a damaged gear tooth)"
        )
    else:
        joint = names[c.joint_index]
        where = f"a gravity torque on {joint} of {c.low:.3g} to {c.high:.3g} N·m"
        what = (
            f"unexplained, concentrated in {joint}: an effect of its load that no library "
            "term describes"
        )
    return (
        f"{what} — the {c.n_outliers} samples the model cannot fit at all (left out as "
        f"gross outliers) all lie at {where} (p = {c.p_value:.2g}); not named."
    )


def ambiguity_entry(
    ctx: Context,
    fit: ModelFit,
    weights: FloatArray,
    null: NullModel,
    pairs: list[tuple[Term, ScoreTest]],
    columns: dict[str, FloatArray],
    at: int,
    n_poses: int,
    pool_size: int,
    rng: np.random.Generator,
    names: tuple[str, ...],
) -> Ambiguity:
    """Ambiguity entry: the kept term first, its rivals, and poses that would separate them."""
    best, best_test = pairs[0]
    with_geometry = len(pairs) == 1
    reported = [estimate_of(t, test) for t, test in pairs]
    involved = [best] if with_geometry else [pairs[0][0], pairs[1][0]]
    if with_geometry:
        correlation = float(np.sqrt(best_test.absorbed_fraction))
        text = (
            f"{describe(best, names)} is significant, but the model's other parameters "
            f"reproduce {100 * best_test.absorbed_fraction:.0f} % of its signature: not named."
        )
    else:
        correlation = max(
            canonical_correlation(null, columns[best.key], columns[t.key]) for t, _ in pairs[1:]
        )
        labels = " or ".join(describe(t, names) for t, _ in pairs)
        text = (
            f"the data cannot tell {labels} apart (correlation {correlation:.2f} once the "
            "geometry is fitted); the first is kept in the model, none is named."
        )
    estimates = [test.estimate for _, test in pairs[: len(involved)]]
    poses = separating_poses(ctx, fit, involved, estimates, n_poses, rng, pool_size, weights)
    if poses is not None and poses.separation_after_sigma > max(
        3.0, 2.0 * poses.separation_now_sigma
    ):
        text += (
            f" Measuring the {len(poses.configurations)} suggested poses would set the "
            f"explanations {poses.separation_after_sigma:.2g} noise standard deviations apart "
            f"(now {poses.separation_now_sigma:.2g})."
        )
    elif poses is not None:
        poses = None
        text += " No pose within the joint limits separates them"
        text += ": record with a second, known payload." if best.effect == "payload_mass" else "."
    else:
        text += " Record in a shuffled order and approach poses from both sides to separate them."
    return Ambiguity(reported, with_geometry, correlation, at, best, poses, text)
