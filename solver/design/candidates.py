"""Candidate configurations and the constraints a pose must meet to be measurable.

Positions are those of the chain's tip frame in the robot's base frame (nominal forward
kinematics, Eq. 7 with the URDF geometry), metres: where the user knows the sensor to be.

- :class:`WorkspaceBox`: the tip inside an axis-aligned box;
- :class:`ViewCone`: the tip inside a sensor's view cone (apex, axis, half-angle, depth range)
  and, optionally, a marker axis of the tip frame turned towards the sensor within a maximum
  incidence angle (a camera sees a planar target only from the front);
- joint limits: candidates are drawn within them (:func:`sample_candidates`) and given ones
  are checked (:func:`outside_limits`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from solver.arrays import BoolArray, FloatArray
from solver.errors import SolverError
from solver.measurement.models import nominal_pose
from solver.model import KinematicChain, sample_configurations


@dataclass(frozen=True)
class WorkspaceBox:
    """Axis-aligned box in the base frame: ``low_m`` ≤ tip position ≤ ``high_m`` (3,)."""

    low_m: FloatArray
    high_m: FloatArray

    def contains(self, pose: FloatArray) -> BoolArray:
        """Tip poses (N, 4, 4) inside the box -> (N,) bool."""
        p = pose[:, :3, 3]
        return np.all((p >= self.low_m) & (p <= self.high_m), axis=1)


@dataclass(frozen=True)
class ViewCone:
    """A sensor's working volume seen from its frame: apex ``apex_m`` and unit ``axis`` in the
    base frame, ``half_angle_rad``, depth range ``near_m``..``far_m`` along the line of sight;
    optional ``max_incidence_rad`` between the tip frame's ``marker_axis`` (tip frame, unit)
    and the direction from the tip back to the sensor."""

    apex_m: FloatArray
    axis: FloatArray
    half_angle_rad: float
    near_m: float
    far_m: float
    max_incidence_rad: float | None = None
    marker_axis: FloatArray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))

    def contains(self, pose: FloatArray) -> BoolArray:
        """Tip poses (N, 4, 4) seen by the sensor -> (N,) bool."""
        sight = pose[:, :3, 3] - self.apex_m
        distance = np.linalg.norm(sight, axis=1)
        axis = self.axis / np.linalg.norm(self.axis)
        cos_angle = (sight @ axis) / np.maximum(distance, 1e-300)
        seen = (
            (cos_angle >= np.cos(self.half_angle_rad))
            & (distance >= self.near_m)
            & (distance <= self.far_m)
        )
        if self.max_incidence_rad is None:
            return seen
        facing = pose[:, :3, :3] @ (self.marker_axis / np.linalg.norm(self.marker_axis))
        back = -sight / np.maximum(distance, 1e-300)[:, None]
        return seen & (np.sum(facing * back, axis=1) >= np.cos(self.max_incidence_rad))


@dataclass(frozen=True)
class Volume:
    """The constraints a measurable pose meets (None: no such constraint)."""

    box: WorkspaceBox | None = None
    cone: ViewCone | None = None

    def contains(self, pose: FloatArray) -> BoolArray:
        inside = np.ones(pose.shape[0], dtype=bool)
        for constraint in (self.box, self.cone):
            if constraint is not None:
                inside &= constraint.contains(pose)
        return inside

    @property
    def unconstrained(self) -> bool:
        return self.box is None and self.cone is None


tip_poses = nominal_pose
"""Nominal tip poses (N, 4, 4) in the base frame, rigid joints (the calibration's own)."""


MAX_DRAWS = 5_000_000
"""Default largest number of random configurations drawn for one sample (about 9 s of forward
kinematics on one core): small sensor volumes keep a fraction of a percent of the draws."""
PROBE_DRAWS = 100_000
"""Draws after which a volume no tip has entered is declared out of reach."""


def sample_candidates(
    chain: KinematicChain,
    n: int,
    rng: np.random.Generator,
    volume: Volume = Volume(),
    *,
    range_fraction: float = 1.0,
    max_draws: int | None = None,
) -> FloatArray:
    """``n`` configurations (n, k) uniform within the joint limits whose tip lies in ``volume``
    (rejection sampling, at most ``max_draws`` draws, default :data:`MAX_DRAWS` — a 25 cm
    tracker box at the edge of a Jaco2's reach keeps 0.3 % of the draws); a clear error if
    the volume is out of reach (no tip inside after :data:`PROBE_DRAWS` draws) or too small."""
    limit = max(200 * n, MAX_DRAWS) if max_draws is None else max_draws
    kept: list[FloatArray] = []
    found, drawn = 0, 0
    batch = max(4 * n, 1000)
    while found < n:
        if drawn >= limit or (found == 0 and drawn >= min(PROBE_DRAWS, limit)):
            raise SolverError(
                f"only {found} of {drawn} random configurations put the tip inside the working "
                f"volume (wanted {n}); check the box/cone (base frame, metres) or widen it"
            )
        q = sample_configurations(chain, batch, rng, range_fraction)
        drawn += batch
        inside = q[volume.contains(tip_poses(chain, q))] if not volume.unconstrained else q
        kept.append(inside)
        found += inside.shape[0]
    return np.concatenate(kept)[:n]


def outside_limits(chain: KinematicChain, joint_positions: FloatArray) -> NDArray[np.intp]:
    """Rows (indices) with a joint position outside the chain's limits."""
    bad = (joint_positions < chain.lower_limits - 1e-9) | (
        joint_positions > chain.upper_limits + 1e-9
    )
    return np.flatnonzero(np.any(bad, axis=1))
