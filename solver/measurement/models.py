"""Measurement models: what one recorded row measures about the chain (issue 15).

Every model gives, for N rows at once, its residual ``r`` (N, d) (measured minus predicted, in
the model's :attr:`MeasurementModel.frame`), the Jacobian ``A`` (N, d, P + E) of ``r`` with the
convention of the Gauss–Newton step of Eq. (10) — ``r(θ ⊕ δ) ≈ r(θ) − A δ`` — over the P chain
columns of :func:`solver.kinematics.parameter_names` (local link twists m/rad, compliance
rad/N·m) and the E unknowns of its own (:meth:`MeasurementModel.extra_names`), and the chain
columns it can see at all (:meth:`MeasurementModel.visible_columns`).

The chain side always comes from :func:`solver.kinematics.evaluate_chain`: the end-effector
pose ``X`` (measurement frame ← tip) and the tip-local twist ``t = J_tip δ`` each chain column
moves it by (``X ← X·Exp(t)``, paper Eq. 9). Each model only chains its own derivative onto
``J_tip``:

- :class:`FullPose`, :class:`Position`: the residuals of DESIGN.md §2 (tip frame), with the
  Jacobian of Eq. (9) used since the paper (exact where the residual is zero);
- :class:`PoseComponents`: chosen components of ``[p_m − p; Log(R_m Rᵀ)]`` in the
  measurement frame (e.g. a plane contact: z, rx, ry), exact Jacobian;
- :class:`FixedPoints`: ball in socket, ``P_g − p`` in the robot base frame with one unknown
  point per socket and optional known distances between sockets;
- :class:`MultiMarker`: m markers per row, each ``p_m,j − (p + R t_j)`` with its own offset
  ``t_j`` on the flange;
- :class:`RelativeBase`: the marker measured in the frame of another unknown marker carried
  by the robot base (that frame is ``L_1``);
- :class:`EyeOnHead`: the sensor carried by the link after a chosen joint of the chain; the
  measurement is the tip in that moving sensor frame.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass, field, replace

import numpy as np

from solver import lie
from solver.alignment import align_full_pose, align_positions
from solver.arrays import BoolArray, FloatArray, IntArray
from solver.errors import CalibrationError
from solver.kinematics import (
    TWIST_COMPONENTS,
    ChainEvaluation,
    ChainParameters,
    evaluate_chain,
    forward_kinematics,
    pose_residuals,
    position_residuals,
    stacked_jacobian,
)
from solver.model import KinematicChain


@dataclass(frozen=True)
class ModelParameters(ChainParameters):
    """The chain's parameters and a measurement model's own unknowns ``extra`` (E,), in the
    order of :meth:`MeasurementModel.extra_names` (m for points and offsets)."""

    extra: FloatArray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True, eq=False)
class MeasurementRows:
    """Rows of a recording as every model takes them: joint positions (N, k) rad, gravity
    loads (N, n_axes) N·m, what was measured (``measured``: (N, 4, 4) poses for the pose
    models, (N, m, 3) marker positions in m for :class:`MultiMarker`, (N, 0) for
    :class:`FixedPoints`) and ``group`` (N,): the socket of each row (0 elsewhere)."""

    joint_positions: FloatArray
    loads_nm: FloatArray
    measured: FloatArray
    group: IntArray

    @classmethod
    def of(
        cls,
        joint_positions: FloatArray,
        loads_nm: FloatArray,
        measured: FloatArray | None = None,
        group: IntArray | None = None,
    ) -> MeasurementRows:
        n = joint_positions.shape[0]
        return cls(
            np.asarray(joint_positions, dtype=float),
            np.asarray(loads_nm, dtype=float),
            np.zeros((n, 0)) if measured is None else np.asarray(measured, dtype=float),
            np.zeros(n, dtype=np.intp) if group is None else np.asarray(group, dtype=np.intp),
        )

    @property
    def n(self) -> int:
        return int(self.joint_positions.shape[0])

    def take(self, index: IntArray) -> MeasurementRows:
        return MeasurementRows(
            self.joint_positions[index],
            self.loads_nm[index],
            self.measured[index],
            self.group[index],
        )


def chain_column_count(chain: KinematicChain) -> int:
    """P: link twists (6 per link) and compliances."""
    return 6 * chain.n_links + len(chain.compliance_axes)


def tip_linearisation(
    chain: KinematicChain, params: ChainParameters, rows: MeasurementRows
) -> tuple[FloatArray, FloatArray]:
    """End-effector pose ``X`` (N, 4, 4) and the tip-local twist per chain column ``J_tip``
    (N, 6, P) (paper Eq. 9, :func:`solver.kinematics.stacked_jacobian`)."""
    evaluation = evaluate_chain(chain, params, rows.joint_positions, rows.loads_nm)
    return evaluation.pose, stacked_jacobian(evaluation)


class MeasurementModel(ABC):
    """What a row measures; see the module docstring for the conventions."""

    name: str = ""

    @property
    @abstractmethod
    def dim(self) -> int:
        """Residual rows per recorded row (d)."""

    @property
    @abstractmethod
    def frame(self) -> str:
        """The frame the residual is expressed in, in words."""

    @property
    def components(self) -> tuple[str, ...]:
        """Name of each residual row (d,), e.g. ``x, y, z``."""
        return tuple(f"r{i}" for i in range(self.dim))

    @property
    def translation_rows(self) -> tuple[int, ...]:
        """Residual rows in m (their norm is a row's translation error)."""
        return tuple(range(self.dim))

    @property
    def rotation_rows(self) -> tuple[int, ...]:
        """Residual rows in rad (their norm is a row's rotation error)."""
        return ()

    @property
    def noise_rows(self) -> dict[str, tuple[tuple[int, ...], ...]] | None:
        """The noise layout of Eq. (12) for this residual (as rotated by
        :meth:`tip_frame_rotation`): the noise frame by name with its placements, each the
        residual row of the six axes [v; w] (−1: the axis does not reach the residual), all
        sharing one Σ_n (:func:`solver.covariance.layout.make_layout`); None: one tip-frame
        noise on rows 0..d−1, as for a pose or position recording."""
        return None

    def extra_names(self) -> list[str]:
        """Names of the model's own unknowns (E)."""
        return []

    def tip_frame_rotation(
        self, chain: KinematicChain, params: ModelParameters, rows: MeasurementRows
    ) -> FloatArray | None:
        """Per row (N, d, d): the rotation taking this model's residual into the tip frame,
        where the measurement noise of Eq. (12) acts (DESIGN.md §2), for the covariance
        calibration; None when the residual is in the tip frame already."""
        return None

    def visible_columns(self, chain: KinematicChain) -> BoolArray:
        """Chain columns (P,) the measurement depends on at all (others stay at the start)."""
        return np.ones(chain_column_count(chain), dtype=bool)

    @property
    def sensor_joint_index(self) -> int | None:
        """The joint (0-based) after which the measuring sensor rides on the chain
        (:class:`EyeOnHead`); None: the sensor is fixed in the measurement frame, and
        :meth:`at_tip` takes the end effector's pose in that frame."""
        return None

    @abstractmethod
    def start(self, chain: KinematicChain, rows: MeasurementRows) -> ModelParameters:
        """A first guess in the Gauss–Newton basin (closed form where there is one)."""

    def linearise(
        self,
        chain: KinematicChain,
        params: ModelParameters,
        rows: MeasurementRows,
        *,
        jacobian: bool = True,
    ) -> tuple[FloatArray, FloatArray | None]:
        """Residual (N, d) and, with ``jacobian``, ``A`` (N, d, P + E): from :meth:`at_tip`,
        the chain columns ``M J_tip`` (N, d, P), then the model's own unknowns (N, d, E).
        Overridden by :class:`FullPose` (``M`` is rows of I₆: a slice, not a product) and
        :class:`EyeOnHead` (its rows are seen from a sensor on the chain, not from the base)."""
        if not jacobian:
            pose = forward_kinematics(chain, params, rows.joint_positions, rows.loads_nm)
            return self.at_tip(pose, params.extra, rows)[0], None
        pose, j_tip = tip_linearisation(chain, params, rows)
        residual, tip_map, columns = self.at_tip(pose, params.extra, rows)
        return residual, np.concatenate([tip_map @ j_tip, columns], axis=2)

    @abstractmethod
    def at_tip(
        self, pose: FloatArray, extra: FloatArray, rows: MeasurementRows
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """The model at a predicted end-effector pose ``X`` (N, 4, 4) and its own unknowns
        ``extra`` (E,): residual (N, d), the map ``M`` (N, d, 6) of a tip-local twist ``t``
        (``X ← X·Exp(t)``) to the residual, ``r ≈ r − M t``, and the residual's columns of the
        unknowns (N, d, E), same sign convention. The chain columns of :meth:`linearise` are
        ``M J_tip``; discovery (:mod:`solver.discovery.fitting`) maps its own tip-twist columns
        (terms, drift, depth) through ``M`` too."""

    def constraints(
        self, chain: KinematicChain, params: ModelParameters
    ) -> tuple[FloatArray, FloatArray]:
        """Extra equations beside the rows (known distances): residual (c,), ``A`` (c, P+E)."""
        return np.zeros(0), np.zeros((0, chain_column_count(chain) + len(self.extra_names())))

    def check_rows(self, rows: MeasurementRows) -> None:  # noqa: B027 (most models check)
        """A clear :class:`CalibrationError` when ``rows`` do not fit the model."""

    def apply(
        self, chain: KinematicChain, params: ChainParameters, step: FloatArray, keep: IntArray
    ) -> ModelParameters:
        """A Gauss–Newton step over the columns ``keep``: local link corrections
        ``L_i ← L_i·Exp(δ_i)``, compliances and the model's unknowns added."""
        p = chain_column_count(chain)
        extra = params.extra if isinstance(params, ModelParameters) else np.zeros(0)
        full = np.zeros(p + extra.size)
        full[keep] = step
        twists = full[: 6 * chain.n_links].reshape(chain.n_links, 6)
        return ModelParameters(
            params.links @ lie.se3_exp(twists),
            params.compliance_rad_per_nm + full[6 * chain.n_links : p],
            extra + full[p:],
        )

    def _with_extra_columns(self, chain_jacobian: FloatArray) -> FloatArray:
        """``chain_jacobian`` (N, d, P) with zero columns for the model's unknowns."""
        n, d, _ = chain_jacobian.shape
        return np.concatenate([chain_jacobian, np.zeros((n, d, len(self.extra_names())))], axis=2)


def _links_folded(
    chain: KinematicChain, first: int, world: FloatArray, tool: FloatArray, base: ChainParameters
) -> ModelParameters:
    """``base`` with ``world`` folded into link ``first`` and ``tool`` into the last link."""
    links = base.links.copy()
    links[first] = world @ links[first]
    links[-1] = links[-1] @ tool
    return ModelParameters(links, np.zeros(len(chain.compliance_axes)))


# --- full pose and position (DESIGN.md §2) ------------------------------------------------------


@dataclass(frozen=True)
class FullPose(MeasurementModel):
    """The marker's pose in the measurement frame: ``r = Log(X⁻¹ X_m)`` (N, 6), [v; w] in m and
    rad, tip frame; ``A = J_tip`` (Eq. 9).

    The type of a pose recording's rows wherever they are fitted, streamed or not (issue 35):
    the pose paths take a :class:`FullPose` (or :class:`Position`, or a model whose rows are
    either) and ask it — :attr:`dim`, :attr:`measures_rotation`, :meth:`residuals`,
    :meth:`align` — instead of a flag. Everything here keys on :attr:`rotation_rows`, so a
    subclass that measures positions only overrides that (and :attr:`dim`) alone."""

    name = "pose"

    @property
    def dim(self) -> int:
        return 6

    @property
    def frame(self) -> str:
        return "end effector (tip) frame"

    @property
    def components(self) -> tuple[str, ...]:
        return TWIST_COMPONENTS

    @property
    def translation_rows(self) -> tuple[int, ...]:
        return (0, 1, 2)

    @property
    def rotation_rows(self) -> tuple[int, ...]:
        return (3, 4, 5)

    @property
    def measures_rotation(self) -> bool:
        """Whether the rows carry the marker's rotation (else its position alone)."""
        return bool(self.rotation_rows)

    def residuals(self, predicted_pose: FloatArray, measured_pose: FloatArray) -> FloatArray:
        """The residual of DESIGN.md §2 (Eq. 8) of predicted poses (N, 4, 4) against measured
        ones (N, 4, 4), tip frame, (N, d): :func:`~solver.kinematics.pose_residuals`, or
        :func:`~solver.kinematics.position_residuals` when the rows measure no rotation."""
        if self.measures_rotation:
            return pose_residuals(predicted_pose, measured_pose)
        return position_residuals(predicted_pose, measured_pose)

    def align(
        self, nominal: FloatArray, measured_pose: FloatArray
    ) -> tuple[FloatArray, FloatArray]:
        """Closed-form measurement frame ← base and flange → marker transforms (4, 4) that
        fit ``nominal`` (N, 4, 4) to ``measured_pose`` (N, 4, 4): Kabsch on poses, or on
        positions (the tool rotation then stays identity)."""
        if self.measures_rotation:
            return align_full_pose(nominal, measured_pose)
        return align_positions(nominal, measured_pose[:, :3, 3])

    def predicted_pose(
        self, chain: KinematicChain, params: ChainParameters, rows: MeasurementRows
    ) -> FloatArray:
        """The pose the model predicts for each row (N, 4, 4), measurement frame."""
        return forward_kinematics(chain, params, rows.joint_positions, rows.loads_nm)

    def start(self, chain: KinematicChain, rows: MeasurementRows) -> ModelParameters:
        world, tool = self.align(nominal_pose(chain, rows.joint_positions), rows.measured)
        return _links_folded(chain, 0, world, tool, ChainParameters.nominal(chain))

    def linearise(
        self,
        chain: KinematicChain,
        params: ModelParameters,
        rows: MeasurementRows,
        *,
        jacobian: bool = True,
    ) -> tuple[FloatArray, FloatArray | None]:
        d = self.dim
        if not jacobian:
            pose = forward_kinematics(chain, params, rows.joint_positions, rows.loads_nm)
            return self.residuals(pose, rows.measured), None
        pose, j_tip = tip_linearisation(chain, params, rows)
        residual = self.residuals(pose, rows.measured)
        return residual, self._with_extra_columns(j_tip[:, :d])

    def at_tip(
        self, pose: FloatArray, extra: FloatArray, rows: MeasurementRows
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``r = Log(X⁻¹ X_m)`` (first 3 rows for position), ``M`` the first d rows of I₆."""
        n, d = pose.shape[0], self.dim
        residual = self.residuals(pose, rows.measured)
        tip_map = np.broadcast_to(np.eye(6)[:d], (n, d, 6))
        return residual, tip_map, np.zeros((n, d, 0))

    def check_rows(self, rows: MeasurementRows) -> None:
        _check_pose_rows(self, rows)


@dataclass(frozen=True)
class Position(FullPose):
    """The marker's position: ``r = Rᵀ (p_m − p)`` (N, 3), m, tip frame (the translation of
    ``X⁻¹ X_m`` whatever the unmeasured rotation); ``A = J_tip[:3]``."""

    name = "position"

    @property
    def dim(self) -> int:
        return 3

    @property
    def components(self) -> tuple[str, ...]:
        return TWIST_COMPONENTS[:3]

    @property
    def rotation_rows(self) -> tuple[int, ...]:
        return ()


def nominal_pose(chain: KinematicChain, joint_positions: FloatArray) -> FloatArray:
    """URDF forward kinematics base -> tip, rigid; (N, 4, 4)."""
    zero_loads = np.zeros((joint_positions.shape[0], len(chain.compliance_axes)))
    return forward_kinematics(chain, ChainParameters.nominal(chain), joint_positions, zero_loads)


def _check_pose_rows(model: MeasurementModel, rows: MeasurementRows) -> None:
    if rows.measured.shape[1:] != (4, 4):
        raise CalibrationError(
            f"measurement '{model.name}' needs a measured pose per row (x,y,z and, for "
            f"rotations, qx,qy,qz,qw columns); the rows carry {rows.measured.shape[1:]} values"
        )


# --- chosen pose components -------------------------------------------------------------------


@dataclass(frozen=True)
class PoseComponents(MeasurementModel):
    """Chosen components of the pose error in the measurement frame,
    ``e = [p_m − p; Log(R_m Rᵀ)]`` (x, y, z in m; rx, ry, rz in rad), e.g. a plane contact
    measures z, rx, ry of the tool in the frame of the plane. With ``X ← X·Exp([v; w])``:
    ``δe_t = −R v`` and ``δe_r = −Jr⁻¹(Log(R_m Rᵀ)) R w`` (exact)."""

    selected: tuple[str, ...] = ("tz", "rx", "ry")
    name = "components"

    def __post_init__(self) -> None:
        unknown = [c for c in self.selected if c not in TWIST_COMPONENTS]
        if unknown or not self.selected or len(set(self.selected)) != len(self.selected):
            raise CalibrationError(
                f"measurement components {list(self.selected)}: choose distinct components "
                f"among {', '.join(TWIST_COMPONENTS)} (e.g. tz,rx,ry for a plane contact)"
            )

    @property
    def index(self) -> IntArray:
        return np.array([TWIST_COMPONENTS.index(c) for c in self.selected], dtype=np.intp)

    @property
    def dim(self) -> int:
        return len(self.selected)

    @property
    def frame(self) -> str:
        return "measurement frame"

    @property
    def components(self) -> tuple[str, ...]:
        return self.selected

    @property
    def translation_rows(self) -> tuple[int, ...]:
        return tuple(i for i, c in enumerate(self.selected) if c.startswith("t"))

    @property
    def rotation_rows(self) -> tuple[int, ...]:
        return tuple(i for i, c in enumerate(self.selected) if c.startswith("r"))

    @property
    def noise_rows(self) -> dict[str, tuple[tuple[int, ...], ...]]:
        """The noise of the chosen components only, in the measurement frame (a subset of
        components cannot be rotated into the tip frame): axis a of ``[v; w]`` is the
        component ``TWIST_COMPONENTS[a]``."""
        rows = tuple(self.selected.index(c) if c in self.selected else -1 for c in TWIST_COMPONENTS)
        return {"noise": (rows,)}

    def start(self, chain: KinematicChain, rows: MeasurementRows) -> ModelParameters:
        """The nominal chain: without all six components there is no closed-form alignment;
        the measurement frame must be near the robot base (e.g. the plane under the robot)."""
        return ModelParameters(chain.nominal_links.copy(), np.zeros(len(chain.compliance_axes)))

    def at_tip(
        self, pose: FloatArray, extra: FloatArray, rows: MeasurementRows
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        rotation = pose[:, :3, :3]
        rotation_error = lie.so3_log(rows.measured[:, :3, :3] @ np.swapaxes(rotation, 1, 2))
        error = np.concatenate([rows.measured[:, :3, 3] - pose[:, :3, 3], rotation_error], axis=1)
        full = np.zeros((pose.shape[0], 6, 6))
        full[:, :3, :3] = rotation
        full[:, 3:, 3:] = lie.so3_right_jacobian_inverse(rotation_error) @ rotation
        return error[:, self.index], full[:, self.index], np.zeros((pose.shape[0], self.dim, 0))

    def check_rows(self, rows: MeasurementRows) -> None:
        _check_pose_rows(self, rows)


# --- ball in socket ---------------------------------------------------------------------------


@dataclass(frozen=True)
class KnownDistance:
    """``|P_a − P_b| = distance_m`` between two sockets (0-based)."""

    a: int
    b: int
    distance_m: float


@dataclass(frozen=True)
class FixedPoints(MeasurementModel):
    """Ball in socket: the tool point (the ball centre, the tip link's translation) of every
    row of socket g is the same unknown point ``P_g`` of the robot base frame.
    ``r = P_g − p`` (N, 3), m, robot base frame; ``A_chain = R J_tip[:3]``, ``A_{P_g} = −I``.

    ``distances``: known socket distances, each one more equation
    ``distance_weight·(d − |P_a − P_b|)`` with ``A_{P_a} = w uᵀ``, ``A_{P_b} = −w uᵀ``,
    ``u = (P_a − P_b)/|P_a − P_b|`` (without one, the scale of the robot is not identified
    when its link lengths are fitted). The base frame is the robot's: ``L_1`` is not fitted
    (a rigid motion of it and of every point together changes no residual).
    """

    n_points: int = 1
    distances: tuple[KnownDistance, ...] = ()
    distance_weight: float = 1.0
    name = "point"

    def __post_init__(self) -> None:
        if self.n_points < 1:
            raise CalibrationError("measurement 'point' needs at least one socket")
        for d in self.distances:
            if not (0 <= d.a < self.n_points and 0 <= d.b < self.n_points) or d.a == d.b:
                raise CalibrationError(
                    f"known distance between sockets {d.a} and {d.b}: choose two different "
                    f"sockets among 0..{self.n_points - 1}"
                )
            if not d.distance_m > 0.0:
                raise CalibrationError(
                    f"known distance between sockets {d.a} and {d.b} is {d.distance_m} m; "
                    "give a positive distance in m"
                )

    @property
    def dim(self) -> int:
        return 3

    @property
    def frame(self) -> str:
        return "robot base frame"

    @property
    def components(self) -> tuple[str, ...]:
        return ("x", "y", "z")

    def tip_frame_rotation(
        self, chain: KinematicChain, params: ModelParameters, rows: MeasurementRows
    ) -> FloatArray:
        """``Rᵀ`` (N, 3, 3): the socket residual ``P_g − p`` (robot base frame) in the tip
        frame."""
        pose = forward_kinematics(chain, params, rows.joint_positions, rows.loads_nm)
        return np.ascontiguousarray(pose[:, :3, :3].transpose(0, 2, 1))

    def extra_names(self) -> list[str]:
        return [f"point_{g}.{a}" for g in range(self.n_points) for a in ("x", "y", "z")]

    def visible_columns(self, chain: KinematicChain) -> BoolArray:
        """Not ``L_1`` (the points are in the robot base frame); without a known distance
        not the link translations before the tool either: a robot scaled about its base with
        its points fits every socket as well, down to a robot shrunk to a point, so the
        lengths stay the URDF's (rotations, i.e. joint offsets and axis tilts, the ball
        offset and the points are fitted)."""
        visible = np.ones(chain_column_count(chain), dtype=bool)
        visible[:6] = False
        if not self.distances:
            for link in range(1, chain.n_links - 1):
                visible[6 * link : 6 * link + 3] = False
        return visible

    def points(self, params: ModelParameters) -> FloatArray:
        """The socket points (G, 3), m, robot base frame."""
        return params.extra.reshape(self.n_points, 3)

    def start(self, chain: KinematicChain, rows: MeasurementRows) -> ModelParameters:
        """Nominal chain; the ball offset ``t`` (flange frame) and the points from the linear
        least squares ``p_n + R_n t = P_{g(n)}`` (exact when the nominal chain is)."""
        nominal = nominal_pose(chain, rows.joint_positions)
        n = rows.n
        design = np.zeros((n, 3, 3 + 3 * self.n_points))
        design[:, :, :3] = nominal[:, :3, :3]
        for i, g in enumerate(rows.group):
            design[i, :, 3 + 3 * g : 6 + 3 * g] = -np.eye(3)
        solution = np.linalg.lstsq(
            design.reshape(3 * n, -1), -nominal[:, :3, 3].reshape(-1), rcond=None
        )[0]
        tool = np.eye(4)
        tool[:3, 3] = solution[:3]
        base = _links_folded(chain, 0, np.eye(4), tool, ChainParameters.nominal(chain))
        return replace(base, extra=np.asarray(solution[3:], dtype=float))

    def at_tip(
        self, pose: FloatArray, extra: FloatArray, rows: MeasurementRows
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``r = P_g − p``, ``M = R [I 0]``, ``−I`` at the row's socket point."""
        n = pose.shape[0]
        residual = extra.reshape(self.n_points, 3)[rows.group] - pose[:, :3, 3]
        tip_map = np.zeros((n, 3, 6))
        tip_map[:, :, :3] = pose[:, :3, :3]
        columns = np.zeros((n, 3, 3 * self.n_points))
        for axis in range(3):
            columns[np.arange(n), axis, 3 * rows.group + axis] = -1.0
        return residual, tip_map, columns

    def constraints(
        self, chain: KinematicChain, params: ModelParameters
    ) -> tuple[FloatArray, FloatArray]:
        p = chain_column_count(chain)
        points = self.points(params)
        residual = np.zeros(len(self.distances))
        a = np.zeros((len(self.distances), p + 3 * self.n_points))
        for i, known in enumerate(self.distances):
            delta = points[known.a] - points[known.b]
            length = float(np.linalg.norm(delta))
            unit = delta / max(length, 1e-300)
            residual[i] = self.distance_weight * (known.distance_m - length)
            a[i, p + 3 * known.a : p + 3 * known.a + 3] = self.distance_weight * unit
            a[i, p + 3 * known.b : p + 3 * known.b + 3] = -self.distance_weight * unit
        return residual, a

    def check_rows(self, rows: MeasurementRows) -> None:
        counts = np.bincount(rows.group, minlength=self.n_points)
        if rows.group.size and (rows.group.min() < 0 or rows.group.max() >= self.n_points):
            raise CalibrationError(
                f"measurement 'point': rows name socket {int(rows.group.max())} but the model "
                f"has {self.n_points} socket(s)"
            )
        few = [g for g in range(self.n_points) if counts[g] < 2]
        if few:
            raise CalibrationError(
                f"measurement 'point': socket(s) {few} have fewer than 2 rows; record several "
                "configurations with the ball in each socket"
            )


# --- several markers --------------------------------------------------------------------------


@dataclass(frozen=True)
class MultiMarker(MeasurementModel):
    """m markers per row, positions (N, m, 3) in the measurement frame, each at its own unknown
    offset ``t_j`` (m) on the flange (the frame before the tip link, which is then not fitted:
    the offsets carry it). ``r_j = p_m,j − (p + R t_j)`` (N, 3m), m, measurement frame;
    ``A_chain,j = R [I, −[t_j]x] J_tip``, ``A_{t_j} = R``."""

    n_markers: int = 2
    name = "markers"

    @property
    def dim(self) -> int:
        return 3 * self.n_markers

    @property
    def frame(self) -> str:
        return "measurement frame"

    @property
    def components(self) -> tuple[str, ...]:
        return tuple(f"m{j + 1}.{a}" for j in range(self.n_markers) for a in ("x", "y", "z"))

    @property
    def noise_rows(self) -> dict[str, tuple[tuple[int, ...], ...]]:
        """One position noise Σ_n (3×3, tip frame) shared by the markers, independent across
        them: the noise part of Eq. (12) is ``blockdiag(Σ_n, …, Σ_n)``."""
        return {
            "noise": tuple((3 * j, 3 * j + 1, 3 * j + 2, -1, -1, -1) for j in range(self.n_markers))
        }

    def tip_frame_rotation(
        self, chain: KinematicChain, params: ModelParameters, rows: MeasurementRows
    ) -> FloatArray:
        """``blockdiag(Rᵀ … Rᵀ)`` (N, 3m, 3m): every marker's residual in the tip frame, where
        ``Rᵀ A_chain,j = [I, −[t_j]x] J_tip`` and the markers' noise is constant."""
        pose = forward_kinematics(chain, params, rows.joint_positions, rows.loads_nm)
        out = np.zeros((rows.n, self.dim, self.dim))
        for j in range(self.n_markers):
            out[:, 3 * j : 3 * j + 3, 3 * j : 3 * j + 3] = pose[:, :3, :3].transpose(0, 2, 1)
        return out

    def extra_names(self) -> list[str]:
        return [f"marker_{j + 1}.{a}" for j in range(self.n_markers) for a in ("x", "y", "z")]

    def visible_columns(self, chain: KinematicChain) -> BoolArray:
        visible = np.ones(chain_column_count(chain), dtype=bool)
        last = 6 * (chain.n_links - 1)
        visible[last : last + 6] = False
        return visible

    def offsets(self, params: ModelParameters) -> FloatArray:
        """Marker offsets (m, 3) in the flange frame, m."""
        return params.extra.reshape(self.n_markers, 3)

    def start(self, chain: KinematicChain, rows: MeasurementRows) -> ModelParameters:
        """Measurement frame from the first marker (:func:`align_positions`), then every
        marker's offset by linear least squares ``R_W R_n t_j = p_m,j − R_W p_n − t_W``."""
        nominal = nominal_pose(chain, rows.joint_positions)
        world, _ = align_positions(nominal, rows.measured[:, 0])
        rotation = world[:3, :3] @ nominal[:, :3, :3]
        design = rotation.reshape(-1, 3)
        offsets = []
        for j in range(self.n_markers):
            rhs = rows.measured[:, j] - nominal[:, :3, 3] @ world[:3, :3].T - world[:3, 3]
            offsets.append(np.linalg.lstsq(design, rhs.reshape(-1), rcond=None)[0])
        base = _links_folded(chain, 0, world, np.eye(4), ChainParameters.nominal(chain))
        return replace(base, extra=np.concatenate(offsets))

    def at_tip(
        self, pose: FloatArray, extra: FloatArray, rows: MeasurementRows
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """``r_j = p_m,j − (p + R t_j)``, ``M_j = R [I, −[t_j]x]``, ``R`` at ``t_j``."""
        n = pose.shape[0]
        offsets = extra.reshape(self.n_markers, 3)
        rotation = pose[:, :3, :3]
        predicted = pose[:, None, :3, 3] + np.einsum("nij,mj->nmi", rotation, offsets)
        residual = (rows.measured - predicted).reshape(n, -1)
        tip_map = np.zeros((n, self.dim, 6))
        columns = np.zeros((n, self.dim, self.dim))
        for j, offset in enumerate(offsets):
            lever = np.concatenate([np.eye(3), -lie.skew(offset)], axis=1)  # (3, 6)
            tip_map[:, 3 * j : 3 * j + 3] = rotation @ lever
            columns[:, 3 * j : 3 * j + 3, 3 * j : 3 * j + 3] = rotation
        return residual, tip_map, columns

    def check_rows(self, rows: MeasurementRows) -> None:
        if rows.measured.shape[1:] != (self.n_markers, 3):
            raise CalibrationError(
                f"measurement 'markers' with {self.n_markers} markers needs x,y,z of each "
                f"marker per row; the rows carry {rows.measured.shape[1:]} values"
            )


# --- a frame carried by the base; a sensor carried by the chain -------------------------------


@dataclass(frozen=True)
class RelativeBase(FullPose):
    """The marker measured in the frame of another marker rigidly carried by the robot base
    (TIAGo's Vicon files: the gripper in the frame of a base marker), both unknown. That frame
    is the measurement frame of Eq. (7): ``L_1`` (base marker ← robot base) is fitted with the
    chain, ``L_{k+1}`` carries the gripper marker. Residuals as :class:`FullPose` (with
    ``rotation``) or :class:`Position`, tip frame."""

    rotation: bool = False
    name = "relative-base"

    @property
    def dim(self) -> int:
        return 6 if self.rotation else 3

    @property
    def frame(self) -> str:
        return "end effector (tip) frame; measurement frame = the marker on the robot base"

    @property
    def components(self) -> tuple[str, ...]:
        return TWIST_COMPONENTS[: self.dim]

    @property
    def rotation_rows(self) -> tuple[int, ...]:
        return (3, 4, 5) if self.rotation else ()


def seen_from_sensor(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    sensor_joint: int,
    tip: ChainEvaluation,
) -> ChainEvaluation:
    """The end effector seen from a sensor riding on the body after joint ``sensor_joint``
    (0-based), from :func:`~solver.kinematics.evaluate_chain` of the whole chain ``tip`` at the
    same ``params``, joint positions (N, k) rad and loads (N, n_axes) N·m.

    Pose ``X_S = X_0j⁻¹ X_0E`` (N, 4, 4) (the sensor mount S⁻¹ is part of ``L_{j+1}``, as in
    :class:`EyeOnHead`). Every parameter moves both ends by its tip-local twist (paper Eq. 9):
    ``X_0E ← X_0E·Exp(J_tip δ)``, ``X_0j ← X_0j·Exp(J_j δ)``, so
    ``X_S ← X_S·Exp((J_tip − Ad(X_S)⁻¹ J_j) δ)`` to first order, with ``J_j`` the body
    Jacobian of the sensor's body (zero for links, joints and axes after the sensor: they do
    not move it). Link columns (N, k+1, 6, 6) and compliance columns (N, n_axes, 6) are those
    differences; for everything at or before the sensor both ends move alike and they cancel
    to rounding, which is how discovery finds what a sensor on the chain cannot see."""
    j = sensor_joint
    links = params.links.copy()
    links[j + 1 :] = np.eye(4)
    q = np.array(joint_positions, dtype=float)
    q[:, j + 1 :] = 0.0
    loads = np.array(loads_nm, dtype=float)
    after = [a for a, axis in enumerate(chain.compliance_axes) if axis.joint_index > j]
    loads[:, after] = 0.0
    body = evaluate_chain(chain, ChainParameters(links, params.compliance_rad_per_nm), q, loads)
    body_links = body.link_jacobians.copy()
    body_links[:, j + 1 :] = 0.0
    relative = lie.inverse(body.pose) @ tip.pose
    to_tip = lie.adjoint_inverse(relative)  # (N, 6, 6): Ad(X_S)⁻¹
    return ChainEvaluation(
        relative,
        tip.link_jacobians - to_tip[:, None] @ body_links,
        tip.compliance_jacobians - np.einsum("nij,naj->nai", to_tip, body.compliance_jacobians),
    )


@dataclass(frozen=True)
class EyeOnHead(MeasurementModel):
    """A sensor carried by the chain's body after joint ``sensor_joint`` (0-based): it measures
    the tip in its own moving frame S, ``X_S = S⁻¹ X_{0,j}(q)⁻¹ X_0E(q)``, which is the chain
    after that joint with ``S⁻¹`` folded into the next link. Links and compliances before
    the sensor cancel (not fitted). Residuals as :class:`FullPose` (with ``rotation``) or
    :class:`Position`, tip frame."""

    sensor_joint: int = 0
    rotation: bool = True
    name = "eye-on-head"

    @property
    def inner(self) -> FullPose:
        return FullPose() if self.rotation else Position()

    @property
    def sensor_joint_index(self) -> int:
        return self.sensor_joint

    @property
    def dim(self) -> int:
        return self.inner.dim

    @property
    def frame(self) -> str:
        return f"end effector (tip) frame; measured from a sensor after joint {self.sensor_joint}"

    @property
    def components(self) -> tuple[str, ...]:
        return self.inner.components

    @property
    def translation_rows(self) -> tuple[int, ...]:
        return self.inner.translation_rows

    @property
    def rotation_rows(self) -> tuple[int, ...]:
        return self.inner.rotation_rows

    def _hidden_axes(self, chain: KinematicChain) -> IntArray:
        return np.array(
            [
                a
                for a, ax in enumerate(chain.compliance_axes)
                if ax.joint_index <= self.sensor_joint
            ],
            dtype=np.intp,
        )

    def visible_columns(self, chain: KinematicChain) -> BoolArray:
        visible = np.ones(chain_column_count(chain), dtype=bool)
        visible[: 6 * (self.sensor_joint + 1)] = False
        visible[6 * chain.n_links + self._hidden_axes(chain)] = False
        return visible

    def _check_sensor(self, chain: KinematicChain) -> None:
        if not 0 <= self.sensor_joint < chain.n_joints - 1:
            raise CalibrationError(
                f"measurement 'eye-on-head': sensor joint {self.sensor_joint} must be a joint "
                f"of the chain before its last (0..{chain.n_joints - 2})"
            )

    def _suffix(
        self, chain: KinematicChain, params: ChainParameters, rows: MeasurementRows
    ) -> tuple[ModelParameters, MeasurementRows]:
        """Parameters and rows whose forward kinematics is the chain after the sensor: links
        and joints up to the sensor made identity, compliances there unloaded."""
        self._check_sensor(chain)
        links = params.links.copy()
        links[: self.sensor_joint + 1] = np.eye(4)
        q = rows.joint_positions.copy()
        q[:, : self.sensor_joint + 1] = 0.0
        loads = rows.loads_nm.copy()
        loads[:, self._hidden_axes(chain)] = 0.0
        suffix = ModelParameters(links, params.compliance_rad_per_nm)
        return suffix, MeasurementRows(q, loads, rows.measured, rows.group)

    def predicted_pose(
        self, chain: KinematicChain, params: ChainParameters, rows: MeasurementRows
    ) -> FloatArray:
        """The tip in the sensor frame for each row (N, 4, 4)."""
        suffix, moved = self._suffix(chain, params, rows)
        return forward_kinematics(chain, suffix, moved.joint_positions, moved.loads_nm)

    def start(self, chain: KinematicChain, rows: MeasurementRows) -> ModelParameters:
        """Nominal chain, with the sensor frame (closed-form alignment of the chain after the
        sensor to the measurements) folded into the link after the sensor (rigid: the loads
        of ``rows`` are not used)."""
        nominal = ChainParameters.nominal(chain)
        rigid = replace(rows, loads_nm=np.zeros((rows.n, len(chain.compliance_axes))))
        suffix, moved = self._suffix(chain, nominal, rigid)
        pose = forward_kinematics(chain, suffix, moved.joint_positions, moved.loads_nm)
        world, tool = self.inner.align(pose, rows.measured)
        return _links_folded(chain, self.sensor_joint + 1, world, tool, nominal)

    def linearise(
        self,
        chain: KinematicChain,
        params: ModelParameters,
        rows: MeasurementRows,
        *,
        jacobian: bool = True,
    ) -> tuple[FloatArray, FloatArray | None]:
        """Residual of the tip in the sensor frame; ``A`` the inner model's map ``M`` chained
        onto :func:`seen_from_sensor`'s columns (those at or before the sensor cancel: they
        are left at zero, not fitted)."""
        if not jacobian:
            pose = self.predicted_pose(chain, params, rows)
            return self.inner.at_tip(pose, params.extra, rows)[0], None
        self._check_sensor(chain)
        q, loads = rows.joint_positions, rows.loads_nm
        tip = evaluate_chain(chain, params, q, loads)
        seen = seen_from_sensor(chain, params, q, loads, self.sensor_joint, tip)
        residual, tip_map, columns = self.inner.at_tip(seen.pose, params.extra, rows)
        a = np.concatenate([tip_map @ stacked_jacobian(seen), columns], axis=2)
        a[:, :, : chain_column_count(chain)] *= self.visible_columns(chain)
        return residual, a

    def at_tip(
        self, pose: FloatArray, extra: FloatArray, rows: MeasurementRows
    ) -> tuple[FloatArray, FloatArray, FloatArray]:
        """As the inner pose/position model, ``pose`` being the tip in the sensor frame."""
        return self.inner.at_tip(pose, extra, rows)

    def check_rows(self, rows: MeasurementRows) -> None:
        _check_pose_rows(self, rows)
