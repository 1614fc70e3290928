"""Per-sample driving signals ("features") of the candidate terms, and the data they act on.

A deflection term is a rotation about a fixed axis whose angle is ``coefficient × feature[n]``
(paper Eq. 6 is the case feature = gravity torque). :class:`solver.model.ComplianceAxis` with the
feature matrix passed as ``loads_nm`` evaluates any such term exactly, Jacobian column included,
so every feature here is a plain (N,) array in execution order:

* ``tau:<axis>``      gravity moment about a joint axis or a virtual axis ⟂ to it, N·m (Eq. 6);
* ``sign_tau:<j>``    ½·sign(τ_j): backlash taken up by the gravity load (the link rests on
                      the side gravity pushes it to, ahead of a motor-side reading);
* ``deadzone_tau:<j>:<τ0>``  ½·sign(τ_j) where |τ_j| > τ0, else 0: the same backlash floating
                      (mean zero) where the load is too small to take it up;
* ``lag:<j>``         −½·sign(q_j[n] − q_j[n−1]): backlash taken up by the approach direction,
                      the link lagging a motor-side reading (0 for the first row: its approach
                      is unknown; docs/discovery_physics.md derives the sign);
* ``q:<j>``           q_j, rad: joint scale (gear-ratio) error;
* ``sin<h>:<j>``, ``cos<h>:<j>``  sin(h q_j), cos(h q_j): periodic transmission error;
* ``time:linear``     t − t_0 (s; acquisition index when no time stamps);
* ``time:warmup:<T>`` 1 − exp(−(t − t_0)/T): warm-up drift with time constant T;
* ``basis:<family>:<j>:<i>``  column i of the generic angle or load basis of joint j
                      (:func:`angle_basis`, :func:`load_basis`): unexplained structure;
* ``one``             1: gives the Jacobian column per unit angle of an axis (plots, designs).

All but ``one`` are centred over the recording (see :meth:`FeatureBank.column`). The
``sign_tau``, ``deadzone_tau``, ``q``, ``sin``/``cos`` features are functions of one configuration
alone (:func:`configuration_feature`): the recording's columns and a single configuration's
value (``kincal predict`` of a result carrying discovered corrections) come from that function.

Gravity moments are linear in the gravity vector and in the payload mass, so they are kept as
a basis (unit gravity along base x, y, z; robot and 1 kg payload) and recombined for any tilted
gravity or extra payload without new RNEA sweeps.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import NDArray

from solver.arrays import FloatArray
from solver.errors import ModelError
from solver.gravity import StaticGravityModel, static_gravity_loads
from solver.measurement.models import (
    FixedPoints,
    FullPose,
    MeasurementModel,
    MeasurementRows,
)
from solver.model import ComplianceAxis, KinematicChain, gravity_loads

FLEX_LABELS = ("flex_a", "flex_b")
ANGLE_LIBRARY_HARMONICS = (1, 2, 3)
ANGLE_EXTRA_HARMONICS = (4, 5, 6)
ANGLE_EXTRA_DEGREES = range(2, 6)
LOAD_EXTRA_DEGREES = range(2, 5)
# Floating zones of load-sign backlash tried, as quantiles of |τ| (0 = plain sign).
DEADZONE_QUANTILES = (0.0, 0.025, 0.05, 0.1, 0.15, 0.2, 0.3)


@dataclass(frozen=True, eq=False)
class DiscoveryData:
    """Recordings as solver arrays, rows in execution order.

    ``joint_positions`` (N, k) rad; ``measured_pose`` (N, 4, 4) marker in the measurement frame;
    ``pose_model``: what it measures, :class:`~solver.measurement.FullPose` or
    :class:`~solver.measurement.Position` (its rotation then ignored); ``time_s`` (N,) or None
    (then time features use the acquisition index); ``payload_kg`` (N,) known payload;
    ``gravity_base`` (3,) m/s² in the base frame (the user's model).

    ``measurement``: what a row measures when it is not the marker's pose or position
    (:mod:`solver.measurement.models`: ball in socket, several markers, chosen pose
    components), None for those two; then ``measured`` holds its rows' measurements
    (:attr:`MeasurementRows.measured`, e.g. (N, m, 3) marker positions; None: ``measured_pose``)
    and ``group`` (N,) each row's socket. ``measured_pose`` is then only used as a position per
    row for the "range" variable (:meth:`range_m`) and may be identity.
    """

    joint_positions: FloatArray
    measured_pose: FloatArray
    pose_model: FullPose
    time_s: FloatArray | None = None
    payload_kg: FloatArray | None = None
    gravity_base: FloatArray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    measurement: MeasurementModel | None = None
    measured: FloatArray | None = None
    group: NDArray[np.intp] | None = None

    @property
    def n_samples(self) -> int:
        return int(self.joint_positions.shape[0])

    @property
    def model(self) -> MeasurementModel:
        """The measurement model of the rows (``pose_model`` unless ``measurement``)."""
        return self.pose_model if self.measurement is None else self.measurement

    @property
    def is_pose(self) -> bool:
        """Rows measure the marker's pose or position (the residuals of DESIGN.md §2)."""
        return self.measurement is None

    @property
    def rows(self) -> int:
        """Residual rows per sample: the model's dimension (6 for a pose, 3 for a position)."""
        return self.model.dim

    def noise_blocks(self) -> list[slice | list[int]]:
        """Residual rows sharing one noise scale: the translation rows, the rotation rows (a
        slice where they are contiguous)."""
        model = self.model
        return [
            slice(b[0], b[-1] + 1) if list(b) == list(range(b[0], b[-1] + 1)) else list(b)
            for b in (model.translation_rows, model.rotation_rows)
            if b
        ]

    def measurement_rows(self, rows: NDArray[np.intp]) -> MeasurementRows:
        """``rows`` as the measurement model takes them (loads unused: the model sees the tip)."""
        measured = self.measured_pose if self.measured is None else self.measured
        group = None if self.group is None else self.group[rows]
        return MeasurementRows.of(
            self.joint_positions[rows], np.zeros((rows.size, 0)), measured[rows], group
        )

    def with_configurations(self, configurations: FloatArray) -> DiscoveryData:
        """The recording followed by new ``configurations`` (P, k) rad with nothing measured
        (identity poses, zero marker positions, socket 0, no payload, no time stamps): rows
        whose columns a pose design evaluates."""
        pool = configurations.shape[0]
        measured = self.measured
        if measured is not None:
            measured = np.concatenate([measured, np.zeros((pool, *measured.shape[1:]))])
        return replace(
            self,
            joint_positions=np.vstack([self.joint_positions, configurations]),
            measured_pose=np.concatenate([self.measured_pose, np.tile(np.eye(4), (pool, 1, 1))]),
            time_s=None,
            payload_kg=np.r_[self.payload(), np.zeros(pool)],
            measured=measured,
            group=None if self.group is None else np.r_[self.group, np.zeros(pool, dtype=np.intp)],
        )

    def range_m(self) -> FloatArray | None:
        """Per row the distance of what was measured from the measurement frame's origin (the
        mean over markers), m; None when nothing is measured in a sensor frame (sockets)."""
        if isinstance(self.measurement, FixedPoints):
            return None
        if self.measured is not None and self.measured.ndim == 3 and self.measured.shape[2] == 3:
            return np.asarray(np.linalg.norm(self.measured, axis=2).mean(axis=1), dtype=float)
        return np.asarray(np.linalg.norm(self.measured_pose[:, :3, 3], axis=1), dtype=float)

    def payload(self) -> FloatArray:
        if self.payload_kg is None:
            return np.zeros(self.n_samples)
        return np.asarray(self.payload_kg, dtype=float)

    def clock(self) -> tuple[FloatArray, str]:
        """(t − t_0, unit) — seconds, or the acquisition index when there are no time stamps."""
        if self.time_s is None:
            return np.arange(self.n_samples, dtype=float), "sample"
        t = np.asarray(self.time_s, dtype=float)
        return t - t[0], "s"


def orthogonal_axes(axis: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Two unit axes completing ``axis`` to a right-handed basis (a, b, axis).

    Same construction as :func:`solver.model.build_chain` uses for ``virtual_axes_at``, so the
    names ``<joint>.flex_a`` / ``.flex_b`` mean the same axes everywhere (tested).
    """
    helper = np.eye(3)[int(np.argmin(np.abs(axis)))]
    first = np.cross(helper, axis)
    first /= np.linalg.norm(first)
    return first, np.cross(axis, first)


def axis_of(chain: KinematicChain, joint_index: int, direction: str) -> ComplianceAxis:
    """The joint axis (``direction == "joint"``) or a virtual axis ⟂ to it (``flex_a/b``)."""
    name = chain.joint_names[joint_index]
    joint_axis = chain.joint_screws[joint_index, 3:].copy()
    if direction == "joint":
        return ComplianceAxis(name, joint_index, joint_axis, is_joint_axis=True)
    vector = orthogonal_axes(joint_axis)[FLEX_LABELS.index(direction)]
    return ComplianceAxis(f"{name}.{direction}", joint_index, vector, is_joint_axis=False)


def probe_chain(chain: KinematicChain) -> KinematicChain:
    """``chain`` with every revolute joint's axis and both virtual axes as compliance axes."""
    axes: list[ComplianceAxis] = []
    for i in np.flatnonzero(chain.is_revolute()):
        axes += [axis_of(chain, int(i), d) for d in (*FLEX_LABELS, "joint")]
    return replace(chain, compliance_axes=tuple(axes))


@dataclass(frozen=True, eq=False)
class GravityBasis:
    """Gravity moments about every probe axis per unit gravity component and per kg payload.

    ``robot[j]`` (N, n_axes): moments (N·m) for gravity = unit vector e_j (m/s²) in the base
    frame; ``payload[j]`` the same for a 1 kg point mass at the payload centre.
    """

    axis_names: tuple[str, ...]
    robot: FloatArray  # (3, N, n_axes)
    payload: FloatArray  # (3, N, n_axes)

    def moments(self, gravity_base: FloatArray, payload_kg: FloatArray) -> FloatArray:
        """τ (N, n_axes) for a gravity vector (3,) and per-sample payload masses (N,)."""
        robot = np.tensordot(gravity_base, self.robot, axes=1)
        return robot + payload_kg[:, None] * np.tensordot(gravity_base, self.payload, axes=1)

    def payload_moments(self, gravity_base: FloatArray) -> FloatArray:
        """∂τ/∂m (N, n_axes): moments of 1 kg extra payload."""
        return np.tensordot(gravity_base, self.payload, axes=1)

    def column(self, name: str) -> int:
        return self.axis_names.index(name)


def gravity_moments_nm(
    probe: KinematicChain,
    joint_positions: FloatArray,
    *,
    gravity_base: FloatArray,
    payload_kg: FloatArray | float = 0.0,
) -> FloatArray:
    """:func:`solver.model.gravity_loads` (N, n_axes), N·m: in closed form
    (:func:`solver.gravity.static_gravity_loads`, equal to rounding and ~15× faster at
    N = 500) where ``probe`` is a serial chain of its joints, by Pinocchio's RNEA otherwise."""
    static = _static_gravity(probe)
    if static is None:
        return gravity_loads(
            probe, joint_positions, gravity_base=gravity_base, payload_kg=payload_kg
        )
    return static_gravity_loads(
        static, joint_positions, gravity_base=gravity_base, payload_kg=payload_kg
    )


@functools.lru_cache(maxsize=8)
def _static_gravity(probe: KinematicChain) -> StaticGravityModel | None:
    """The closed form's constants of ``probe`` (chains hash by identity), None where it is
    not a serial chain of its joints."""
    try:
        return StaticGravityModel.from_chain(probe)
    except ModelError:
        return None


def gravity_basis(probe: KinematicChain, joint_positions: FloatArray) -> GravityBasis:
    """Six gravity sweeps (:func:`gravity_moments_nm`) give every gravity-driven feature for
    any gravity and payload."""
    robot, payload = [], []
    for unit in np.eye(3):
        bare = gravity_moments_nm(probe, joint_positions, gravity_base=unit)
        robot.append(bare)
        payload.append(
            gravity_moments_nm(probe, joint_positions, gravity_base=unit, payload_kg=1.0) - bare
        )
    return GravityBasis(
        tuple(a.name for a in probe.compliance_axes), np.array(robot), np.array(payload)
    )


def approach_lag(joint_positions: FloatArray) -> FloatArray:
    """−½·sign(q[n] − q[n−1]) per joint (N, k); the first row is 0 (approach unknown).

    Backlash b read on the motor side: the motor drives the link through a dead band, so after
    a move the link trails the reading by b/2 against the motion,
    ``q_link = q_read − (b/2)·sign(Δq) = q_read + b·lag`` with b ≥ 0.
    """
    out = np.zeros_like(joint_positions, dtype=float)
    out[1:] = -0.5 * np.sign(np.diff(joint_positions, axis=0))
    return out


def time_shape(clock: FloatArray, time_constant: float | None) -> FloatArray:
    """Linear drift (``time_constant`` None) or warm-up 1 − exp(−t/T)."""
    if time_constant is None:
        return clock.copy()
    return 1.0 - np.exp(-clock / time_constant)


def legendre_basis(values: FloatArray, degrees: range) -> FloatArray:
    """Legendre polynomials of ``values`` scaled to [−1, 1] over their observed range, (N, n)."""
    low, high = float(values.min()), float(values.max())
    scaled = np.zeros_like(values) if high <= low else 2.0 * (values - low) / (high - low) - 1.0
    table = np.polynomial.legendre.legvander(scaled, max(degrees))
    return np.asarray(table[:, list(degrees)], dtype=np.float64)


def angle_basis(q: FloatArray, *, library: bool, extra: bool) -> FloatArray:
    """Functions of a joint angle (N, nb): the library's (q, harmonics 1..3) and/or more
    (Legendre degree 2..5 over the observed range, harmonics 4..6)."""
    parts = []
    if library:
        parts.append(q[:, None] - q.mean())
        parts += [np.column_stack([np.sin(h * q), np.cos(h * q)]) for h in ANGLE_LIBRARY_HARMONICS]
    if extra:
        parts.append(legendre_basis(q, ANGLE_EXTRA_DEGREES))
        parts += [np.column_stack([np.sin(h * q), np.cos(h * q)]) for h in ANGLE_EXTRA_HARMONICS]
    return np.column_stack(parts)


def load_basis(tau: FloatArray, *, library: bool, extra: bool) -> FloatArray:
    """Functions of a gravity torque (N, nb): the library's (τ, load-sign backlash with its
    floating zones) and/or more (Legendre degree 2..4 over the observed range)."""
    parts = []
    if library:
        parts.append(tau[:, None])
        parts += [deadzone_sign(tau, zone)[:, None] for zone in deadzones(tau)]
    if extra:
        parts.append(legendre_basis(tau, LOAD_EXTRA_DEGREES))
    return np.column_stack(parts)


def deadzones(tau: FloatArray, quantiles: tuple[float, ...] = DEADZONE_QUANTILES) -> list[float]:
    """Floating-zone half widths τ0 (N·m) for load-sign backlash: quantiles of |τ| (6 digits)."""
    magnitude = np.abs(tau)
    return sorted({float(f"{np.quantile(magnitude, f):.6g}") if f else 0.0 for f in quantiles})


def deadzone_sign(tau: FloatArray, zone: float) -> FloatArray:
    """½·sign(τ) where |τ| > τ0, 0 inside the floating zone."""
    return np.where(np.abs(tau) > zone, 0.5 * np.sign(tau), 0.0)


CONFIGURATION_KINDS = ("sign_tau", "deadzone_tau", "q")


def is_configuration_feature(key: str) -> bool:
    """A feature that is a function of the configuration (and its gravity load) alone: not of
    time, execution order or the recording's range."""
    kind = key.partition(":")[0]
    return kind in CONFIGURATION_KINDS or (kind.startswith(("sin", "cos")) and kind[3:].isdigit())


def configuration_feature(
    key: str,
    joint_positions: FloatArray,
    joint_names: tuple[str, ...],
    gravity_moment_nm: Callable[[str], FloatArray],
) -> FloatArray:
    """Uncentred value (N,) of a configuration feature (:func:`is_configuration_feature`).

    ``joint_positions`` (N, k) rad in chain order; ``gravity_moment_nm(axis_name)`` the gravity
    moment (N,) N·m about a probe axis (:func:`probe_chain`) at those configurations. Values:
    ``q`` rad, ``sin``/``cos`` and the ½·sign load features dimensionless.
    """
    kind, _, rest = key.partition(":")
    if kind == "deadzone_tau":
        name, _, zone = rest.rpartition(":")
        return deadzone_sign(gravity_moment_nm(name), float(zone))
    if kind == "sign_tau":
        return deadzone_sign(gravity_moment_nm(rest), 0.0)
    q = joint_positions[:, joint_names.index(rest)]
    if kind == "q":
        return np.array(q, dtype=float)
    if kind.startswith("sin") and kind[3:].isdigit():
        return np.sin(int(kind[3:]) * q)
    if kind.startswith("cos") and kind[3:].isdigit():
        return np.cos(int(kind[3:]) * q)
    raise ValueError(f"{key!r} is not a function of the configuration alone")


class FeatureBank:
    """Feature columns by key for one whole recording; gravity features for any (g, m).

    Always built on the full recording and sliced by row afterwards: approach directions, the
    clock origin and centred joint positions must not change when a cross-validation fold or a
    bootstrap sample picks rows.
    """

    def __init__(self, probe: KinematicChain, data: DiscoveryData) -> None:
        self.probe = probe
        self.data = data
        self.joint_names = probe.joint_names
        self.lag = approach_lag(data.joint_positions)
        self.clock, self.clock_unit = data.clock()
        self._cache: dict[str, FloatArray] = {}

    @functools.cached_property
    def basis(self) -> GravityBasis:
        """The recording's :func:`gravity_basis`, computed when a gravity feature is first
        asked for (a bank built for features of the joint angles alone never sweeps RNEA)."""
        return gravity_basis(self.probe, self.data.joint_positions)

    @functools.cached_property
    def _nominal_tau(self) -> FloatArray:
        """Gravity moments (N, axes), N·m, about every probe axis under the user's gravity
        and payload (:meth:`nominal_tau` picks one)."""
        return self.basis.moments(self.data.gravity_base, self.data.payload())

    def tau(self, axis_name: str, gravity_base: FloatArray, extra_payload_kg: float) -> FloatArray:
        """Gravity moment about a probe axis (N,), N·m."""
        column = self.basis.column(axis_name)
        gravity = np.asarray(gravity_base, dtype=float)
        robot = np.tensordot(gravity, self.basis.robot[:, :, column], axes=1)
        unit = np.tensordot(gravity, self.basis.payload[:, :, column], axes=1)
        return robot + (self.data.payload() + extra_payload_kg) * unit

    def generic_basis(self, family: str, joint_name: str) -> FloatArray:
        """Library and extra basis of joint ``joint_name`` over the whole recording."""
        if family == "angle":
            q = self.data.joint_positions[:, self.joint_names.index(joint_name)]
            return angle_basis(q, library=True, extra=True)
        return load_basis(self.nominal_tau(joint_name), library=True, extra=True)

    def nominal_tau(self, axis_name: str) -> FloatArray:
        """τ under the user's gravity and payload (N,)."""
        return self._nominal_tau[:, self.basis.column(axis_name)]

    def column(self, key: str, gravity_base: FloatArray, extra_payload_kg: float) -> FloatArray:
        """Feature ``key`` (see module docstring) as an (N,) array, centred over the recording.

        Centring changes no prediction: a constant deflection about any axis is a constant
        link rotation, which the geometry absorbs exactly. It keeps the "absorbed fraction" of
        a term about what matters — the part of its shape geometry can mimic.
        """
        if key == "one":
            return np.ones(self.data.n_samples)
        fixed = not key.startswith(("tau:", "dtau_"))  # the rest ignore gravity and payload
        if fixed and key in self._cache:
            return self._cache[key]
        values = self._raw(key, gravity_base, extra_payload_kg)
        values = values - values.mean()
        if fixed:
            self._cache[key] = values
        return values

    def mean(self, key: str, gravity_base: FloatArray, extra_payload_kg: float) -> float:
        """The recording mean of feature ``key`` that :meth:`column` subtracts."""
        return float(self._raw(key, gravity_base, extra_payload_kg).mean())

    def _raw(self, key: str, gravity_base: FloatArray, extra_payload_kg: float) -> FloatArray:
        kind, _, rest = key.partition(":")
        q = self.data.joint_positions
        if kind == "tau":
            return self.tau(rest, gravity_base, extra_payload_kg)
        if kind == "dtau_m":  # ∂τ/∂(payload mass)
            unit = self.basis.payload[:, :, self.basis.column(rest)]
            return np.tensordot(np.asarray(gravity_base, dtype=float), unit, axes=1)
        if kind in ("dtau_x", "dtau_y"):  # ∂τ/∂(base tilt about x or y): τ(e × g)
            direction = np.eye(3)[0 if kind == "dtau_x" else 1]
            tilted = np.cross(direction, np.asarray(gravity_base, dtype=float))
            return self.tau(rest, tilted, extra_payload_kg)
        if kind == "time":
            shape, _, constant = rest.partition(":")
            return time_shape(self.clock, float(constant) if shape == "warmup" else None)
        if kind == "basis":
            family, name, index = rest.split(":")
            return self.generic_basis(family, name)[:, int(index)]
        if kind == "lag":
            return self.lag[:, self.joint_names.index(rest)]
        if is_configuration_feature(key):
            return configuration_feature(key, q, self.joint_names, self.nominal_tau)
        raise ValueError(f"unknown feature key {key!r}")
