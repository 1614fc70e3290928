"""Mechanism-level simulator of the effects discovery looks for (issue 14).

:mod:`solver.simulate` adds each hidden effect with the same formula the discovery library
fits, so a convention both got wrong cannot show. This module simulates the *mechanisms*
instead and shares no formula with :mod:`solver.discovery`: it never imports it, nor the
calibration's gravity loads or chain kinematics. The robot is Pinocchio's model of the URDF
(``chain.pin_model``, with its own per-joint placement errors); everything is computed in
Pinocchio's world frame:

* **gravity moments** are summed from the body masses, ``M_j = Σ_b m_b (c_b − p_j) × g``
  over the bodies b carried by joint j (and the payload point mass), N·m about joint j's
  origin ``p_j``; the torque on the joint is ``a_j · M_j`` with ``a_j`` its axis from the
  joint Jacobian;
* **joints** read on the motor side: the encoder reads the motor (divided by the nominal
  ratio) and the link stands where the transmission puts it —
  an elastic joint deflects by ``c · a_j·M_j(q_link)`` (solved at the deflected
  configuration); a dead band (backlash) lets the link rest anywhere within ±b/2 of the motor:
  where the gravity torque beats the link-side holding friction the link falls against the
  tooth on the side gravity pushes it, elsewhere it stays where the last motion left it (the
  play operator: ``link ← clamp(link, motor − b/2, motor + b/2)``); a gear's pitch curve with
  runout and lobes, individual tooth pitch errors and a tooth-profile error gives the link
  angle by rolling the pinion along it; a wrong gear ratio scales the reading; a warming
  encoder shifts its zero with a first-order temperature rise;
* **structures** bend: the link carrying joint j (the mount, for the first joint) tilts about
  the two axes ⟂ joint j's axis by ``c · M_⊥`` about ``p_j`` (the mount: about the base
  origin), rotating everything it carries;
* **sensors** are cameras: a fixed camera whose mount warms up (its frame moves by a twist in
  its own frame with a first-order rise), or a camera on the flange; a focal length off by a
  factor scales the depth (camera-frame z) of what the camera sees and nothing else.

Measurement noise is a twist in the marker frame, as in :mod:`solver.simulate`.

:func:`conceal` puts the same mechanisms into a *real* recording: the links stood where the
recorded readings say, so the joint mechanisms are inverted sample by sample (which motor
reading puts the link there, given the history) and the structural and sensor mechanisms move
the measured poses. That keeps the real noise and unmodelled structure of the recording.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pinocchio as pin
import scipy.optimize

from solver import lie
from solver.arrays import FloatArray
from solver.model import KinematicChain, pin_configuration, sample_configurations

STANDARD_GRAVITY = np.array([0.0, 0.0, -9.81])


# --- joint mechanisms (the link angle from the motor-side reading) ---------------------------


@dataclass(frozen=True)
class ElasticJoint:
    """Torsional spring between motor and link: the link deflects along the gravity torque."""

    joint: str
    compliance_rad_per_nm: float


@dataclass(frozen=True)
class DeadBand:
    """Backlash ``backlash_rad`` between motor and link.

    Where the gravity torque about the joint exceeds ``holding_nm`` (friction on the link
    side) the link rests against the motor tooth on the side gravity pushes it; elsewhere it
    stays where the motion left it. ``holding_nm = inf``: the approach direction alone decides.
    """

    joint: str
    backlash_rad: float
    holding_nm: float = 0.0


@dataclass(frozen=True)
class GearTrain:
    """Output gear of a joint: pitch radius ``pitch_radius_m`` with ``teeth`` teeth, its pitch
    curve off-round by ``runout_m`` (an eccentric bore), ``ovality_m`` (2 lobes) and
    ``trilobe_m`` (3 lobes, a three-jaw chuck) at angles ``*_angle_rad``; individual tooth
    pitch errors of ``pitch_error_rad`` (s.d., seeded by ``seed``) and a tooth-profile error
    of ``profile_error_rad`` (once per tooth)."""

    joint: str
    pitch_radius_m: float = 0.05
    teeth: int = 120
    runout_m: float = 0.0
    runout_angle_rad: float = 0.0
    ovality_m: float = 0.0
    ovality_angle_rad: float = 0.0
    trilobe_m: float = 0.0
    trilobe_angle_rad: float = 0.0
    pitch_error_rad: float = 0.0
    profile_error_rad: float = 0.0
    seed: int = 0


@dataclass(frozen=True)
class RatioError:
    """The controller divides the motor angle by a nominal gear ratio; the true ratio is
    ``1/(1 + ratio_error)`` of it, so the link turns ``1 + ratio_error`` times the reading."""

    joint: str
    ratio_error: float


@dataclass(frozen=True)
class EncoderWarmup:
    """The joint's encoder zero shifts with its temperature: ``shift_rad`` at the end of a
    first-order rise with time constant ``time_constant_s``, or ``shift_rad`` per second
    (a steady rise) when ``time_constant_s`` is None."""

    joint: str
    shift_rad: float
    time_constant_s: float | None = None


JointMechanism = ElasticJoint | DeadBand | GearTrain | RatioError | EncoderWarmup


@dataclass(frozen=True)
class Bending:
    """The link carrying ``joint`` (for the first joint: the mount) tilts about both axes ⟂
    the joint axis by ``compliance_rad_per_nm`` × the gravity moment it transmits."""

    joint: str
    compliance_rad_per_nm: float


@dataclass(frozen=True)
class CameraWarmup:
    """A fixed camera's mount moves by the twist ``twist`` ([v; w], m and rad, camera frame)
    at the end of a first-order rise with ``time_constant_s`` (per second if None)."""

    twist: FloatArray
    time_constant_s: float | None = None


@dataclass(frozen=True)
class FocalLengthError:
    """The camera's focal length is off by ``scale``: the depth (camera z) it reconstructs is
    ``1 + scale`` times the true one, the image coordinates are right. ``on_flange``: the
    camera is the marker (eye-in-hand, looking at a fixed board, the measurement frame)."""

    scale: float
    on_flange: bool = False


@dataclass(frozen=True)
class MechanismSpec:
    """A recording of a robot with mechanisms: readings sampled uniformly in the joint ranges,
    ``sample_period_s`` apart; per-joint placement errors (s.d.) ``geometry_*``; the base in the
    camera frame ``measurement_frame`` (4, 4), the marker in the tip frame ``tool_offset``;
    measurement noise (6,) s.d. of a marker-frame twist; gravity in the base frame; a payload
    point mass at ``payload_com_m`` (tip frame)."""

    n_samples: int
    seed: int
    joints: tuple[JointMechanism, ...] = ()
    bending: tuple[Bending, ...] = ()
    camera_warmup: CameraWarmup | None = None
    focal_length: FocalLengthError | None = None
    geometry_translation_m: float = 1e-3
    geometry_rotation_rad: float = 2e-3
    measurement_frame: FloatArray = field(default_factory=lambda: np.eye(4))
    tool_offset: FloatArray = field(default_factory=lambda: np.eye(4))
    noise_sigma: FloatArray = field(default_factory=lambda: np.full(6, 5e-5))
    gravity_base: FloatArray = field(default_factory=lambda: STANDARD_GRAVITY.copy())
    payload_kg: float = 0.0
    payload_com_m: FloatArray = field(default_factory=lambda: np.zeros(3))
    sample_period_s: float = 4.0


@dataclass(frozen=True)
class MechanismRecording:
    """``joint_positions`` (N, k) the readings; ``link_positions`` where the links stood;
    ``measured_pose`` (N, 4, 4) the marker in the measurement frame; ``true_pose`` without
    noise; ``time_s`` (N,)."""

    joint_positions: FloatArray
    link_positions: FloatArray
    measured_pose: FloatArray
    true_pose: FloatArray
    time_s: FloatArray


class Robot:
    """Pinocchio's model of a chain with a payload: gravity moments and poses in the world."""

    def __init__(
        self,
        chain: KinematicChain,
        model: pin.Model | None = None,
        gravity_base: FloatArray = STANDARD_GRAVITY,
        payload_kg: float = 0.0,
        payload_com_m: FloatArray | None = None,
    ) -> None:
        self.chain = chain
        self.model = chain.pin_model if model is None else model
        self.data = self.model.createData()
        self.base_id = self.model.getFrameId(chain.base_frame)
        self.tip_id = self.model.getFrameId(chain.tip_frame)
        pin.framesForwardKinematics(self.model, self.data, pin.neutral(self.model))
        self.world_base = self.data.oMf[self.base_id].homogeneous.copy()  # fixed: before joint 1
        self.gravity_world = self.world_base[:3, :3] @ np.asarray(gravity_base, dtype=float)
        self.payload_kg = payload_kg
        self.payload_com_m = np.zeros(3) if payload_com_m is None else payload_com_m
        self.joint_ids = chain.pin_joint_ids

    def update(self, link_positions: FloatArray) -> None:
        """Place every body for one configuration (k,) rad."""
        q = pin_configuration(self.chain, link_positions[None, :])[0]
        pin.forwardKinematics(self.model, self.data, q)
        pin.updateFramePlacements(self.model, self.data)
        pin.computeJointJacobians(self.model, self.data, q)

    def axis_world(self, column: int) -> FloatArray:
        """Unit axis (3,) of chain joint ``column`` in the world, from its Jacobian."""
        j = self.joint_ids[column]
        jacobian = pin.getJointJacobian(
            self.model, self.data, j, pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
        )
        return np.asarray(jacobian[3:, self.model.joints[j].idx_v], dtype=float)

    def origin_world(self, column: int) -> FloatArray:
        return np.asarray(self.data.oMi[self.joint_ids[column]].translation, dtype=float)

    def gravity_moment(self, column: int, about: FloatArray | None = None) -> FloatArray:
        """Moment (3,) N·m, world frame, of the weight of everything chain joint ``column``
        carries (payload included) about ``about`` (default the joint origin)."""
        j = self.joint_ids[column]
        point = self.origin_world(column) if about is None else about
        moment = np.zeros(3)
        for body in self.model.subtrees[j]:
            inertia = self.model.inertias[body]
            centre = self.data.oMi[body].act(np.asarray(inertia.lever))
            moment += np.cross(centre - point, inertia.mass * self.gravity_world)
        if self.payload_kg:
            centre = self.data.oMf[self.tip_id].act(self.payload_com_m)
            moment += np.cross(centre - point, self.payload_kg * self.gravity_world)
        return moment

    def joint_torque(self, column: int) -> float:
        """Torque gravity exerts about chain joint ``column``'s axis, N·m."""
        return float(self.axis_world(column) @ self.gravity_moment(column))

    def tip_in_base(self) -> FloatArray:
        """Tip frame in the base frame (4, 4) for the last :meth:`update`."""
        world_tip = self.data.oMf[self.tip_id].homogeneous
        return np.asarray(lie.inverse(self.world_base[None])[0] @ world_tip, dtype=float)


def perturbed_model(
    chain: KinematicChain, spec: MechanismSpec, rng: np.random.Generator
) -> pin.Model:
    """Copy of the chain's model with every chain joint placement off by a random twist."""
    model = chain.pin_model.copy()
    for j in chain.pin_joint_ids:
        twist = np.r_[
            rng.normal(0.0, spec.geometry_translation_m, 3),
            rng.normal(0.0, spec.geometry_rotation_rad, 3),
        ]
        model.jointPlacements[j] = model.jointPlacements[j] * pin.exp6(twist)
    return model


# --- the joint side ----------------------------------------------------------------------------


def gear_reading_to_link(
    gear: GearTrain, lower_rad: float, upper_rad: float
) -> Callable[[FloatArray], FloatArray]:
    """The link angle as a function of the reading for ``gear`` over [lower, upper] rad.

    The pinion rolls without slip along the output gear's pitch curve ``r(ψ)`` (body angle ψ,
    the mesh fixed in space, so at link angle θ it touches ψ = −θ): the rolled arc is
    ``s(θ) = ∫_0^θ r(−θ') dθ'`` and the reading is ``s/r̄`` with r̄ the mean radius (one link
    revolution reads one revolution). Tooth k engages ``F_k`` late (cumulative pitch error),
    and the tooth flank adds a profile error once per tooth.
    """
    rng = np.random.default_rng(gear.seed)
    pitch = rng.normal(0.0, gear.pitch_error_rad, gear.teeth)
    cumulative = np.cumsum(pitch - pitch.mean())
    cumulative -= cumulative.mean()
    margin = 0.5
    grid = np.linspace(lower_rad - margin, upper_rad + margin, 40_000)

    def radius(body_angle: FloatArray) -> FloatArray:
        e, a = gear.runout_m, body_angle - gear.runout_angle_rad
        circle = e * np.cos(a) + np.sqrt(gear.pitch_radius_m**2 - (e * np.sin(a)) ** 2)
        lobes = gear.ovality_m * np.cos(2.0 * (body_angle - gear.ovality_angle_rad))
        lobes += gear.trilobe_m * np.cos(3.0 * (body_angle - gear.trilobe_angle_rad))
        return np.asarray(circle + lobes, dtype=float)

    turn = np.linspace(0.0, 2.0 * np.pi, 4096, endpoint=False)
    mean_radius = float(np.mean(radius(turn)))
    r = radius(-grid)
    arc = np.concatenate([[0.0], np.cumsum(0.5 * (r[1:] + r[:-1]) * np.diff(grid))])
    arc -= np.interp(0.0, grid, arc)
    reading_of_link = arc / mean_radius
    tooth = 2.0 * np.pi / gear.teeth

    def link(reading: FloatArray) -> FloatArray:
        reading = np.asarray(reading, dtype=float)
        index = np.floor(np.mod(reading, 2.0 * np.pi) / tooth).astype(int)
        within = np.mod(reading, tooth) / tooth
        late = (1.0 - within) * cumulative[index % gear.teeth] + within * cumulative[
            (index + 1) % gear.teeth
        ]
        profile = gear.profile_error_rad * np.sin(2.0 * np.pi * within)
        return np.asarray(np.interp(reading - late, reading_of_link, grid) + profile, dtype=float)

    return link


def gear_harmonic_amplitude(gear: GearTrain, harmonic: int) -> float:
    """Amplitude (rad) of the ``harmonic``-th harmonic of the gear's transmission error
    ``link − reading`` over one revolution (a numerical Fourier coefficient)."""
    link = gear_reading_to_link(gear, -np.pi, np.pi)
    reading = np.linspace(-np.pi, np.pi, 1 << 14, endpoint=False)
    error = link(reading) - reading
    coefficient = 2.0 * np.mean(error * np.exp(-1j * harmonic * reading))
    return float(abs(coefficient))


@dataclass
class _JointSide:
    """Per-joint mechanisms of a recording, with the dead bands' state (the angle each link
    was left at by the previous sample, rad)."""

    chain: KinematicChain
    mechanisms: tuple[JointMechanism, ...]
    rest: dict[int, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        names = self.chain.joint_names
        self.column = {id(m): names.index(m.joint) for m in self.mechanisms}
        self.gears = {
            id(m): gear_reading_to_link(
                m,
                float(self.chain.lower_limits[names.index(m.joint)]),
                float(self.chain.upper_limits[names.index(m.joint)]),
            )
            for m in self.mechanisms
            if isinstance(m, GearTrain)
        }

    def link_angle(
        self, column: int, reading: float, time_s: float, torque_nm: float, commit: bool
    ) -> float:
        """Where joint ``column``'s link stands for a motor-side ``reading`` (rad), the gravity
        torque about it (at the deflected configuration) and the time; ``commit`` advances the
        dead band's state."""
        angle = reading
        for m in self.mechanisms:
            if self.column[id(m)] != column:
                continue
            if isinstance(m, GearTrain):
                angle = float(self.gears[id(m)](np.array([angle]))[0])
            elif isinstance(m, RatioError):
                angle = angle * (1.0 + m.ratio_error)
            elif isinstance(m, EncoderWarmup):
                angle += m.shift_rad * _first_order(time_s, m.time_constant_s)
        motor = angle
        for m in self.mechanisms:
            if self.column[id(m)] != column:
                continue
            if isinstance(m, ElasticJoint):
                angle += m.compliance_rad_per_nm * torque_nm
            elif isinstance(m, DeadBand):
                half = 0.5 * m.backlash_rad
                link = self.rest.get(id(m), motor)  # the first approach is unknown: centred
                if abs(torque_nm) > m.holding_nm:
                    link = motor + half * np.sign(torque_nm)
                link = float(np.clip(link, motor - half, motor + half))
                if commit:
                    self.rest[id(m)] = link
                angle += link - motor
        return angle


def _first_order(time_s: float, time_constant_s: float | None) -> float:
    """Share of a first-order rise reached at ``time_s`` (or ``time_s`` itself, per second)."""
    if time_constant_s is None:
        return time_s
    return 1.0 - float(np.exp(-time_s / time_constant_s))


def _links_of_readings(
    robot: Robot, side: _JointSide, readings: FloatArray, time_s: float, iterations: int = 4
) -> FloatArray:
    """Link angles (k,) of one sample: the joint mechanisms at the gravity torques of the
    deflected configuration (fixed point; deflections are mrad, so it converges in a few)."""
    k = readings.size
    links = readings.astype(float).copy()
    joints = sorted({side.column[id(m)] for m in side.mechanisms})
    for sweep in range(iterations + 1):
        robot.update(links)
        torques = {c: robot.joint_torque(c) for c in joints}
        commit = sweep == iterations
        links = readings.astype(float).copy()
        for c in joints:
            links[c] = side.link_angle(c, float(readings[c]), time_s, torques[c], commit)
    assert links.shape == (k,)
    return links


def _readings_of_links(
    robot: Robot, side: _JointSide, links: FloatArray, time_s: float, span_rad: float
) -> FloatArray:
    """Motor-side readings (k,) that put the links at ``links`` (the inverse of
    :func:`_links_of_readings` given the history): a monotone 1-D root per joint."""
    robot.update(links)
    readings = links.astype(float).copy()
    for c in sorted({side.column[id(m)] for m in side.mechanisms}):
        torque = robot.joint_torque(c)

        def gap(reading: float, column: int = c, tau: float = torque) -> float:
            return side.link_angle(column, reading, time_s, tau, commit=False) - links[column]

        low, high = links[c] - span_rad, links[c] + span_rad
        readings[c] = scipy.optimize.brentq(gap, low, high, xtol=1e-13)
        side.link_angle(c, float(readings[c]), time_s, torque, commit=True)
    return readings


# --- structures and sensors ----------------------------------------------------------------


def bending_in_base(robot: Robot, bending: tuple[Bending, ...]) -> FloatArray:
    """Rigid motion (4, 4), base frame, of the tip due to the bending structures at the last
    :meth:`Robot.update`: each bends about its pivot by c × (moment ⟂ its joint axis)."""
    names = robot.chain.joint_names
    motion = np.eye(4)
    for b in sorted(bending, key=lambda item: -names.index(item.joint)):  # distal first
        column = names.index(b.joint)
        pivot = robot.world_base[:3, 3] if column == 0 else robot.origin_world(column)
        axis = robot.axis_world(column)
        moment = robot.gravity_moment(column, about=pivot)
        across = moment - (moment @ axis) * axis
        rotation = lie.so3_exp(b.compliance_rad_per_nm * across)
        about = np.eye(4)
        about[:3, :3] = rotation
        about[:3, 3] = pivot - rotation @ pivot
        motion = about @ motion
    world_base = robot.world_base
    return np.asarray(lie.inverse(world_base[None])[0] @ motion @ world_base, dtype=float)


def camera_sees(
    marker_in_camera: FloatArray,
    time_s: FloatArray,
    warmup: CameraWarmup | None,
    focal: FocalLengthError | None,
) -> FloatArray:
    """What the camera reports (N, 4, 4) for true marker poses in its (cold) frame: the mount
    moved by the warm-up, then the depth scaled by the focal-length error."""
    pose = marker_in_camera
    if warmup is not None:
        share = np.array([_first_order(float(t), warmup.time_constant_s) for t in time_s])
        moved = lie.se3_exp(share[:, None] * np.asarray(warmup.twist, dtype=float)[None, :])
        pose = lie.inverse(moved) @ pose  # the camera moved: the marker, seen from it, did not
    if focal is not None:
        pose = pose.copy()
        if focal.on_flange:  # the camera is the marker: it sees the board at inverse(pose)
            board = lie.inverse(pose)
            board[:, 2, 3] *= 1.0 + focal.scale
            pose = lie.inverse(board)
        else:
            pose[:, 2, 3] *= 1.0 + focal.scale
    return np.asarray(pose, dtype=float)


# --- simulation and concealment ------------------------------------------------------------


def simulate_mechanisms(chain: KinematicChain, spec: MechanismSpec) -> MechanismRecording:
    """A recording of ``spec.n_samples`` uniformly drawn readings through the mechanisms."""
    rng = np.random.default_rng(spec.seed)
    model = perturbed_model(chain, spec, rng)
    readings = sample_configurations(chain, spec.n_samples, rng)
    noise = rng.normal(size=(spec.n_samples, 6)) * spec.noise_sigma
    robot = Robot(chain, model, spec.gravity_base, spec.payload_kg, spec.payload_com_m)
    side = _JointSide(chain, spec.joints)
    time_s = spec.sample_period_s * np.arange(spec.n_samples, dtype=float)
    links = np.empty_like(readings)
    tip = np.empty((spec.n_samples, 4, 4))
    for n in range(spec.n_samples):
        links[n] = _links_of_readings(robot, side, readings[n], float(time_s[n]))
        robot.update(links[n])
        tip[n] = bending_in_base(robot, spec.bending) @ robot.tip_in_base()
    marker = spec.measurement_frame @ tip @ spec.tool_offset
    true_pose = camera_sees(marker, time_s, spec.camera_warmup, spec.focal_length)
    return MechanismRecording(
        joint_positions=readings,
        link_positions=links,
        measured_pose=true_pose @ lie.se3_exp(noise),
        true_pose=true_pose,
        time_s=time_s,
    )


@dataclass(frozen=True)
class Concealment:
    """Mechanisms to put into a real recording (see :func:`conceal`)."""

    joints: tuple[JointMechanism, ...] = ()
    bending: tuple[Bending, ...] = ()
    camera_warmup: CameraWarmup | None = None
    focal_length: FocalLengthError | None = None
    gravity_base: FloatArray = field(default_factory=lambda: STANDARD_GRAVITY.copy())


def conceal(
    chain: KinematicChain,
    joint_positions: FloatArray,
    measured_pose: FloatArray,
    time_s: FloatArray,
    measurement_frame: FloatArray,
    concealment: Concealment,
) -> tuple[FloatArray, FloatArray]:
    """(readings, measured poses) of a real recording with ``concealment``'s mechanisms in it.

    The recorded readings are taken as where the links stood; new readings are the motor-side
    readings that put them there through the joint mechanisms, in execution order (dead bands
    keep their history). Bending moves the tip about its pivots, expressed through
    ``measurement_frame`` (the base in the measurement frame, (4, 4), e.g. from a rigid
    calibration: only its rotation matters to first order); the camera mechanisms act on the
    measured poses as the sensor would.
    """
    robot = Robot(chain, gravity_base=concealment.gravity_base)
    side = _JointSide(chain, concealment.joints)
    span = 10.0 * max([_size(m) for m in concealment.joints], default=0.0) + 1e-6
    readings = np.array(joint_positions, dtype=float)
    pose = np.array(measured_pose, dtype=float)
    base_to_measurement = np.asarray(measurement_frame, dtype=float)
    inverse_frame = lie.inverse(base_to_measurement[None])[0]
    for n in range(readings.shape[0]):
        links = np.asarray(joint_positions[n], dtype=float)
        if concealment.joints:
            readings[n] = _readings_of_links(robot, side, links, float(time_s[n]), span)
        if concealment.bending:
            robot.update(links)
            motion = bending_in_base(robot, concealment.bending)
            pose[n] = base_to_measurement @ motion @ inverse_frame @ pose[n]
    pose = camera_sees(
        pose, np.asarray(time_s, dtype=float), concealment.camera_warmup, concealment.focal_length
    )
    return readings, pose


def _size(mechanism: JointMechanism) -> float:
    """A bound (rad) on how far the mechanism can move a link from its reading."""
    if isinstance(mechanism, ElasticJoint):
        return abs(mechanism.compliance_rad_per_nm) * 500.0
    if isinstance(mechanism, DeadBand):
        return mechanism.backlash_rad
    if isinstance(mechanism, GearTrain):
        bound = (mechanism.runout_m + mechanism.ovality_m + mechanism.trilobe_m) / max(
            mechanism.pitch_radius_m, 1e-9
        )
        return (
            4.0 * bound
            + 6.0 * mechanism.pitch_error_rad * np.sqrt(mechanism.teeth)
            + (mechanism.profile_error_rad)
        )
    if isinstance(mechanism, RatioError):
        return abs(mechanism.ratio_error) * 10.0
    return abs(mechanism.shift_rad) * 1e5
