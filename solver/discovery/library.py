"""The library of physically named candidate terms (issue 5).

Every term has analytic Jacobian columns (see :mod:`solver.discovery.fitting`):

=================  ======================================================================
effect             columns
=================  ======================================================================
joint_compliance   joint axis × gravity torque τ_j (paper Eq. 6), rad/N·m
base_flex          two axes ⟂ the first joint axis × the gravity moment about them (§V-A)
link_bending       the same at a later joint: the structure carrying it tilts under load
gear_periodic      joint axis × (sin h q_j, cos h q_j), h = 1..3, rad
backlash           joint axis × ½ sign(τ_j) ("load") or −½ sign(Δq_j) ("direction": the link
                   lags a motor-side reading), rad
joint_scale        joint axis × (q_j − mean q_j): gear-ratio / encoder-scale error
thermal_drift      joint axis, or the measurement frame (6 columns), × a time shape
                   (linear, or warm-up 1 − exp(−t/T) with two time constants)
payload_mass       extra tip mass: Σ_a c_a ∂τ_a/∂m over the gravity-driven axes modelled
                   (a candidate only when the user's model declares a gravity-driven term)
gravity_direction  base tilt about x and y: Σ_a c_a ∂τ_a/∂tilt (same condition)
depth_scale        the sensor's depth reading off by a factor, along the measurement-frame z
                   (fixed camera) or the marker-frame z (camera on the flange)
=================  ======================================================================

Isotropic range scale is not a candidate: with every link length free it is exactly a scaling
of the robot, so the data can never separate it from geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from solver.arrays import FloatArray
from solver.discovery.effects import EFFECTS
from solver.discovery.features import FLEX_LABELS, FeatureBank, deadzone_sign, deadzones
from solver.model import KinematicChain

UNEXPLAINED = "unexplained"  # generic structure kept in the model, never reported as found
HARMONICS = (1, 2, 3)
DEPTH_AXES = ("measurement_z", "marker_z")
# Floating zones of load-sign backlash tested as candidates (quantiles of |τ|; refined later).
CANDIDATE_DEADZONES = (0.0, 0.1, 0.2)
TWIST_NAMES = ("tx", "ty", "tz", "rx", "ry", "rz")
# Warm-up time constants tried, as fractions of the recording's duration.
WARMUP_FRACTIONS = (1.0 / 8.0, 1.0 / 3.0)


@dataclass(frozen=True)
class AxisSpec:
    """One deflection axis of a term: the joint axis or a virtual axis ⟂ to it, and its feature."""

    joint_index: int
    direction: str  # "joint", "flex_a" or "flex_b"
    feature: str  # key understood by FeatureBank.column

    @property
    def gravity_driven(self) -> bool:
        return self.feature.startswith("tau:")


@dataclass(frozen=True)
class Term:
    """A named physical effect with ``len(parameters)`` coefficients.

    ``variant`` distinguishes members of one effect on one joint (harmonic, backlash trigger,
    time shape, depth axis). ``declared``: part of the user's model, never reported as found.
    """

    effect: str
    joint_index: int | None
    variant: str
    parameters: tuple[str, ...]
    axes: tuple[AxisSpec, ...] = ()
    declared: bool = False

    @property
    def key(self) -> str:
        joint = "-" if self.joint_index is None else str(self.joint_index)
        return f"{self.effect}:{joint}:{self.variant}"

    @property
    def size(self) -> int:
        return len(self.parameters)

    @property
    def family(self) -> str:
        """What the term's deflection is a function of: angle, load, direction, time, global
        (and generic, for the unnamed structure of :func:`generic_term`)."""
        if self.effect == UNEXPLAINED:
            return "generic"
        if self.effect in ("gear_periodic", "joint_scale"):
            return "angle"
        if self.effect in ("joint_compliance", "base_flex", "link_bending") or (
            self.effect == "backlash" and self.variant.startswith("load")
        ):
            return "load"
        if self.effect == "backlash":
            return "direction"
        if self.effect == "thermal_drift":
            return "time"
        return "global"

    @property
    def gravity_driven(self) -> bool:
        return any(a.gravity_driven for a in self.axes)

    def deadzone(self) -> float | None:
        """Floating-zone half width τ0 (N·m) of load-sign backlash, None for other terms."""
        if self.effect != "backlash" or not self.variant.startswith("load"):
            return None
        _, _, zone = self.variant.partition(":")
        return float(zone) if zone else 0.0

    def time_constant(self) -> float | None:
        """Warm-up time constant (clock units) of a drift term, None for linear drift."""
        shape = self.variant.split(":")
        return float(shape[-1]) if "warmup" in shape else None


def compliance_term(chain: KinematicChain, j: int, *, declared: bool = False) -> Term:
    name = chain.joint_names[j]
    return Term(
        "joint_compliance",
        j,
        "",
        ("compliance_rad_per_nm",),
        (AxisSpec(j, "joint", f"tau:{name}"),),
        declared,
    )


def flex_term(chain: KinematicChain, j: int, *, declared: bool = False) -> Term:
    """Virtual axes ⟂ joint j: base flex at the first joint, link bending further out."""
    name = chain.joint_names[j]
    axes = tuple(AxisSpec(j, label, f"tau:{name}.{label}") for label in FLEX_LABELS)
    effect = "base_flex" if j == 0 else "link_bending"
    return Term(effect, j, "", tuple(f"{lab}_rad_per_nm" for lab in FLEX_LABELS), axes, declared)


def backlash_load_term(chain: KinematicChain, j: int, zone: float = 0.0) -> Term:
    """Backlash taken up by the sign of the gravity load; floating where |τ| < ``zone``."""
    name = chain.joint_names[j]
    if zone <= 0.0:
        return Term(
            "backlash", j, "load", ("backlash_rad",), (AxisSpec(j, "joint", f"sign_tau:{name}"),)
        )
    return Term(
        "backlash",
        j,
        f"load:{zone:.6g}",
        ("backlash_rad",),
        (AxisSpec(j, "joint", f"deadzone_tau:{name}:{zone:.6g}"),),
    )


def gear_term(chain: KinematicChain, j: int, harmonic: int) -> Term:
    """Periodic transmission error of joint j: a·sin(h q_j) + b·cos(h q_j) about its axis."""
    name = chain.joint_names[j]
    return Term(
        "gear_periodic",
        j,
        f"h{harmonic}",
        ("sin_rad", "cos_rad"),
        (
            AxisSpec(j, "joint", f"sin{harmonic}:{name}"),
            AxisSpec(j, "joint", f"cos{harmonic}:{name}"),
        ),
    )


def direction_backlash_term(chain: KinematicChain, j: int) -> Term:
    """Backlash taken up by the direction joint j was approached from (execution order): the
    link lags the motor-side reading by half the backlash, against the motion."""
    name = chain.joint_names[j]
    return Term(
        "backlash", j, "direction", ("backlash_rad",), (AxisSpec(j, "joint", f"lag:{name}"),)
    )


def scale_term(chain: KinematicChain, j: int) -> Term:
    """Gear-ratio / encoder-scale error of joint j: deflection ∝ q_j."""
    name = chain.joint_names[j]
    return Term("joint_scale", j, "", ("scale_error",), (AxisSpec(j, "joint", f"q:{name}"),))


def drift_term(chain: KinematicChain, j: int | None, shape: str, clock_unit: str) -> Term:
    """Thermal drift of joint j's zero (``j`` None: of the measurement frame, 6 twist
    components) with time shape ``linear`` or ``warmup:<T>`` (see :func:`drift_variants`)."""
    if j is None:
        names = measurement_drift_parameters(shape, clock_unit)
        return Term("thermal_drift", None, f"measurement_frame:{shape}", names)
    feature = f"time:{shape}"
    unit = f"rad_{_rate(clock_unit)}" if shape == "linear" else "rad"
    return Term("thermal_drift", j, shape, (f"drift_{unit}",), (AxisSpec(j, "joint", feature),))


def measurement_drift_parameters(shape: str, clock_unit: str) -> tuple[str, ...]:
    """Names of the measurement frame's drift twist [v; w] (m and rad; per clock unit for the
    ``linear`` shape), e.g. ``tx_m_per_s`` … ``rz_rad_per_s``."""
    suffix = f"_{_rate(clock_unit)}" if shape == "linear" else ""
    return tuple(f"{c}_{'m' if c.startswith('t') else 'rad'}{suffix}" for c in TWIST_NAMES)


def _rate(clock_unit: str) -> str:
    return "per_s" if clock_unit == "s" else "per_sample"


def global_term(effect: str, variant: str = "") -> Term:
    """A whole-robot term: payload_mass, gravity_direction or depth_scale (variant: axis)."""
    parameters = {
        "payload_mass": ("payload_kg",),
        "gravity_direction": ("tilt_x_rad", "tilt_y_rad"),
        "depth_scale": ("scale",),
    }[effect]
    return Term(effect, None, variant, parameters)


def library_term(
    chain: KinematicChain, effect: str, j: int | None, variant: str, clock_unit: str
) -> Term:
    """The library term with this (effect, joint, variant): the inverse of its ``key``.

    Used to carry a discovered model (findings JSON) back into the solver.
    """
    if effect == "joint_compliance" and j is not None:
        return compliance_term(chain, j)
    if effect in ("base_flex", "link_bending") and j is not None:
        return flex_term(chain, j)
    if effect == "gear_periodic" and j is not None and variant.startswith("h"):
        return gear_term(chain, j, int(variant[1:]))
    if effect == "backlash" and j is not None:
        if variant == "direction":
            return direction_backlash_term(chain, j)
        if variant.startswith("load"):
            _, _, zone = variant.partition(":")
            return backlash_load_term(chain, j, float(zone) if zone else 0.0)
    if effect == "joint_scale" and j is not None:
        return scale_term(chain, j)
    if effect == "thermal_drift":
        shape = variant.removeprefix("measurement_frame:")
        if shape == "linear" or shape.startswith("warmup:"):
            return drift_term(chain, j if shape == variant else None, shape, clock_unit)
    if effect in ("payload_mass", "gravity_direction") and j is None and not variant:
        return global_term(effect)
    if effect == "depth_scale" and j is None and variant in DEPTH_AXES:
        return global_term(effect, variant)
    where = "no joint" if j is None else f"joint {chain.joint_names[j]}"
    raise ValueError(f"no library term {effect} ({variant}) on {where}")


def generic_term(chain: KinematicChain, bank: FeatureBank, j: int, family: str) -> Term:
    """Unnamed structure of joint j: a rotation about its axis by a generic function of its
    angle or load (library and extra basis). Kept in the model so it cannot leak into other
    terms' evidence; reported as unexplained, never as a finding."""
    name = chain.joint_names[j]
    width = bank.generic_basis(family, name).shape[1]
    axes = tuple(AxisSpec(j, "joint", f"basis:{family}:{name}:{i}") for i in range(width))
    return Term(UNEXPLAINED, j, family, tuple(f"basis_{i}_rad" for i in range(width)), axes)


def declared_terms(chain: KinematicChain) -> tuple[Term, ...]:
    """The user's model: the compliance axes of ``chain`` as terms (declared, not discovered)."""
    terms: list[Term] = []
    flexed = sorted({a.joint_index for a in chain.compliance_axes if not a.is_joint_axis})
    terms += [flex_term(chain, j, declared=True) for j in flexed]
    own = sorted({a.joint_index for a in chain.compliance_axes if a.is_joint_axis})
    terms += [compliance_term(chain, j, declared=True) for j in own]
    return tuple(terms)


def drift_variants(span: float) -> list[tuple[str, float | None]]:
    """Time shapes: linear, and warm-up with time constants that are fractions of the span."""
    out: list[tuple[str, float | None]] = [("linear", None)]
    if span > 0:
        constants = [float(f"{f * span:.6g}") for f in WARMUP_FRACTIONS]
        out += [(f"warmup:{c:.6g}", c) for c in constants]
    return out


def candidate_library(
    chain: KinematicChain,
    bank: FeatureBank,
    model: tuple[Term, ...],
    effects: tuple[str, ...] = EFFECTS,
) -> list[Term]:
    """Every library term not yet in ``model`` that the recording could excite."""
    in_model = {t.key for t in model}
    out: list[Term] = []
    clock_unit = bank.clock_unit
    shapes = drift_variants(float(bank.clock.max()))
    revolute = [int(j) for j in np.flatnonzero(chain.is_revolute())]
    scale_nm = max([float(np.ptp(bank.nominal_tau(chain.joint_names[j]))) for j in revolute] or [0])
    for j in revolute:
        name = chain.joint_names[j]
        loaded = _load_varies(bank.nominal_tau(name), scale_nm)
        if loaded:
            out.append(compliance_term(chain, j))
            tau = bank.nominal_tau(name)
            out += [
                backlash_load_term(chain, j, zone)
                for zone in deadzones(tau, CANDIDATE_DEADZONES)
                if _varies(deadzone_sign(tau, zone))  # a load that never changes sign cannot
            ]
        if all(_load_varies(bank.nominal_tau(f"{name}.{lab}"), scale_nm) for lab in FLEX_LABELS):
            out.append(flex_term(chain, j))
        out += [gear_term(chain, j, h) for h in HARMONICS]
        out.append(direction_backlash_term(chain, j))
        out.append(scale_term(chain, j))
        out += [drift_term(chain, j, variant, clock_unit) for variant, _ in shapes]
    out += [drift_term(chain, None, variant, clock_unit) for variant, _ in shapes]
    if any(t.gravity_driven and t.declared for t in model):
        # A payload or tilt is seen only through the springs it loads. Through springs found
        # in this search it would reshape what was just found: its evidence is then the found
        # term's residue (on the real FR3 a 35° "tilt" reshaped a concealed panda_joint2
        # spring to fit the arm's own background), and the name would depend on what was
        # found first (issue 32). So only the user's declared springs make them candidates.
        out += [global_term("payload_mass"), global_term("gravity_direction")]
    out += [global_term("depth_scale", axis) for axis in DEPTH_AXES]
    # One load-sign backlash per joint: its floating zone is a refinement, not another term.
    loaded_backlash = {t.joint_index for t in model if t.deadzone() is not None}
    return [
        t
        for t in out
        if t.key not in in_model
        and t.effect in effects
        and not (t.deadzone() is not None and t.joint_index in loaded_backlash)
    ]


def drift_feature(term: Term) -> str:
    """Feature key of a drift term's time shape."""
    constant = term.time_constant()
    return "time:linear" if constant is None else f"time:warmup:{constant:.6g}"


def _varies(values: np.ndarray) -> bool:
    """A driving signal that changes across the recording (e.g. not the vertical first joint)."""
    return bool(np.ptp(values) > 1e-9 * max(1.0, float(np.abs(values).max())))


LOAD_RANGE_FRACTION = 1e-6
"""A gravity moment (N·m) drives a term only if it ranges over more than this fraction of the
largest joint torque range of the recording: below, it is round-off of a moment that is zero
by the robot's geometry (the UR10e's upper arm about its own length, 5e-8 N·m against 222 N·m
at the shoulder), and a coefficient fitted to it comes out absurd (a bending of 7e4 rad/N·m)."""


def _load_varies(tau_nm: np.ndarray, scale_nm: float) -> bool:
    """Does a gravity moment (n,) change across the recording, on the robot's scale of loads
    ``scale_nm`` (the largest joint torque range)?"""
    return _varies(tau_nm) and bool(np.ptp(tau_nm) > LOAD_RANGE_FRACTION * scale_nm)


# Effects whose coefficients a physical mechanism makes non-negative (deflection along the load,
# backlash taken up in the direction of what drives it).
SIGNED = ("joint_compliance", "base_flex", "link_bending", "backlash")


def unphysical(term: Term, estimate: FloatArray, stderr: FloatArray) -> bool:
    """A significantly negative compliance, flex or backlash: no spring or gear does that."""
    if term.effect not in SIGNED:
        return False
    return bool(np.any(estimate < -2.0 * stderr))


def same_mechanism(first: Term, second: Term) -> bool:
    """Two shapes of one mechanism on one joint (drift time shapes, backlash floating zones):
    choosing between them refines a finding, it does not change its label."""
    if (first.effect, first.joint_index) != (second.effect, second.joint_index):
        return False
    if first.effect == "thermal_drift":
        return True
    return first.deadzone() is not None and second.deadzone() is not None
