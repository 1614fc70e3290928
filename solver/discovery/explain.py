"""Reported parameters and one-sentence explanations of findings, in an engineer's units."""

from __future__ import annotations

import math

import numpy as np

from solver.arrays import FloatArray
from solver.discovery.library import Term


def reported_parameters(
    term: Term, values: FloatArray, covariance: FloatArray
) -> tuple[dict[str, float], dict[str, float]]:
    """(parameters, standard errors) by name; derived quantities use the delta method."""
    stderr = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    params = {name: float(v) for name, v in zip(term.parameters, values, strict=True)}
    errors = {name: float(e) for name, e in zip(term.parameters, stderr, strict=True)}
    if term.effect == "gear_periodic":
        a, b = float(values[0]), float(values[1])
        amplitude = math.hypot(a, b)
        gradient_amp = np.array([a, b]) / max(amplitude, 1e-300)
        gradient_phase = np.array([-b, a]) / max(amplitude**2, 1e-300)
        params |= {
            "harmonic": float(term.variant[1:]),
            "amplitude_rad": amplitude,
            "phase_rad": math.atan2(b, a),
        }
        errors |= {
            "amplitude_rad": float(np.sqrt(gradient_amp @ covariance @ gradient_amp)),
            "phase_rad": float(np.sqrt(gradient_phase @ covariance @ gradient_phase)),
        }
    elif term.effect == "gravity_direction":
        tilt = math.hypot(float(values[0]), float(values[1]))
        gradient = np.asarray(values, dtype=float) / max(tilt, 1e-300)
        params["tilt_rad"] = tilt
        errors["tilt_rad"] = float(np.sqrt(gradient @ covariance @ gradient))
    elif term.deadzone():
        params["float_below_nm"] = float(term.deadzone() or 0.0)
    elif term.effect == "thermal_drift" and term.time_constant() is not None:
        params["time_constant"] = float(term.time_constant() or 0.0)
    return params, errors


def _pm(value: float, error: float, scale: float = 1.0, unit: str = "") -> str:
    """``1.9e-3 (±0.1e-3)``: value and standard error with one exponent, error to 1–2 digits."""
    v, e = value * scale, abs(error * scale)
    if not (math.isfinite(v) and math.isfinite(e)):
        return f"{v:.3g}{unit} (±{e:.2g})"
    reference = abs(v) if v != 0 else e
    exponent = 0 if reference == 0 else math.floor(math.log10(reference))
    if -2 <= exponent <= 3:
        exponent = 0
    m, me = v / 10.0**exponent, e / 10.0**exponent
    digits = 2 if me <= 0 else min(max(1 - math.floor(math.log10(me)), 0), 4)
    tail = "" if exponent == 0 else f"e{exponent}"
    return f"{m:.{digits}f}{tail}{unit} (±{me:.{digits}f}{tail})"


def explanation(
    term: Term,
    joint_names: tuple[str, ...],
    params: dict[str, float],
    errors: dict[str, float],
    heldout: tuple[float, float],
    clock_unit: str,
) -> str:
    """One sentence: the physics, its size with ±1 standard error, the held-out gain."""
    joint = "" if term.joint_index is None else joint_names[term.joint_index]
    gain = f"held-out position error {heldout[0]:.3g} → {heldout[1]:.3g} mm"
    e = term.effect
    if e == "joint_compliance":
        c = params["compliance_rad_per_nm"]
        what = (
            f"{joint} behaves as a torsional spring of "
            f"{_pm(c, errors['compliance_rad_per_nm'])} rad/Nm"
        )
        if c < 0:
            what += " — negative, which no spring does: read it as another load-driven effect"
    elif e in ("base_flex", "link_bending"):
        a, b = params["flex_a_rad_per_nm"], params["flex_b_rad_per_nm"]
        where = "the robot's base/mount" if e == "base_flex" else f"the structure carrying {joint}"
        what = (
            f"{where} tilts under the gravity moment it carries (about two axes ⟂ {joint}: "
            f"{_pm(a, errors['flex_a_rad_per_nm'])} and {_pm(b, errors['flex_b_rad_per_nm'])} "
            "rad/Nm)"
        )
    elif e == "gear_periodic":
        what = (
            f"{joint} has a periodic transmission error of "
            f"{_pm(params['amplitude_rad'], errors['amplitude_rad'], 1e3, ' mrad')} amplitude, "
            f"{int(params['harmonic'])}× per joint revolution "
            f"(phase {math.degrees(params['phase_rad']):.0f}°)"
        )
    elif e == "backlash":
        trigger = (
            "by the sign of its gravity load"
            if term.variant.startswith("load")
            else "by the direction it was approached from"
        )
        if term.deadzone():
            trigger += f" once |τ| exceeds {term.deadzone():.2g} N·m (below that it floats)"
        what = (
            f"{joint} has {_pm(params['backlash_rad'], errors['backlash_rad'], 1e3, ' mrad')} "
            f"of backlash, taken up {trigger}"
        )
    elif e == "joint_scale":
        s = params["scale_error"]
        what = (
            f"{joint}'s angle reads {'short' if s > 0 else 'long'} by "
            f"{_pm(abs(s), errors['scale_error'], 1e2, ' %')} of the rotation "
            "(gear-ratio or encoder-scale error)"
        )
    elif e == "thermal_drift":
        what = _drift_sentence(term, joint, params, errors, clock_unit)
    elif e == "payload_mass":
        what = (
            f"the arm carries {_pm(params['payload_kg'], errors['payload_kg'], 1.0, ' kg')} "
            "more than declared at the payload centre"
        )
    elif e == "gravity_direction":
        tilt = _pm(params["tilt_rad"], errors["tilt_rad"], 180 / math.pi, "°")
        what = f"gravity is tilted by {tilt} from the base's −z axis: the base is not level"
    elif e == "depth_scale":
        axis = (
            "the measurement frame's z (camera axis)"
            if term.variant == "measurement_z"
            else ("the marker frame's z (flange camera axis)")
        )
        what = (
            f"the sensor's depth along {axis} is off by "
            f"{_pm(params['scale'], errors['scale'], 1e3, ' mm per m')}"
        )
    else:  # pragma: no cover - vocabulary is closed
        what = f"{e} on {joint}"
    return f"{what}: {gain}."


def _drift_sentence(
    term: Term, joint: str, params: dict[str, float], errors: dict[str, float], clock_unit: str
) -> str:
    per = "h" if clock_unit == "s" else "100 samples"
    per_scale = 3600.0 if clock_unit == "s" else 100.0
    constant = term.time_constant()
    if term.joint_index is not None:
        name = term.parameters[0]
        if constant is None:
            return (
                f"{joint}'s zero drifts by "
                f"{_pm(params[name], errors[name], 1e3 * per_scale, f' mrad per {per}')}"
            )
        unit = "min" if clock_unit == "s" else "samples"
        shown = constant / 60.0 if clock_unit == "s" else constant
        return (
            f"{joint}'s zero drifts by {_pm(params[name], errors[name], 1e3, ' mrad')} "
            f"during warm-up (time constant {shown:.3g} {unit})"
        )
    values = np.array([params[n] for n in term.parameters])
    shift_mm = float(np.linalg.norm(values[:3])) * 1e3
    turn_mrad = float(np.linalg.norm(values[3:])) * 1e3
    if constant is None:
        return (
            f"the measurement frame (camera/tracker) drifts by {shift_mm * per_scale:.3g} mm and "
            f"{turn_mrad * per_scale:.3g} mrad per {per}"
        )
    return (
        f"the measurement frame (camera/tracker) settles by {shift_mm:.3g} mm and "
        f"{turn_mrad:.3g} mrad during warm-up"
    )


def describe(term: Term, joint_names: tuple[str, ...]) -> str:
    """Short label, e.g. ``gear_periodic h2 on panda_joint3``."""
    where = "" if term.joint_index is None else f" on {joint_names[term.joint_index]}"
    variant = f" ({term.variant})" if term.variant else ""
    return f"{term.effect}{variant}{where}"
