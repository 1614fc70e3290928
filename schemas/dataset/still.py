"""Samples of a calibration from streams: one sample per interval in which the robot holds
still, joint readings and measured poses averaged over it.

A joint-state interval (between two consecutive messages) is *still* when every joint's
finite-difference velocity is at most ``tolerance_rad_s`` (rad/s, m/s for prismatic joints);
a *still segment* is a maximal run of messages joined by still intervals. A segment shorter than
``window_s`` is dropped ("too short"); so is one without a measurement message inside it, the
segment shrunk by ``clock_tolerance_s`` at both ends so that a measurement clock off by up to that
much still falls inside ("no measurement").

With a capture topic (a message when the robot was told to measure) each capture is a sample
instead: the window of ``window_s`` centred on it must be still ("moving" otherwise) and hold a
measurement (:func:`synchronise_captures`); two captures at one configuration are two samples.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

NS_PER_S = 1_000_000_000
Row = tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None, int]
"""A sample: mean joints (k,), mean position (3,), mean quaternion (4,) or None, stamp ns."""


@dataclass(frozen=True)
class StillSettings:
    """How still is still: joint speed (rad/s), shortest hold (s), clock offset tolerated
    between the joint-state and measurement topics (s)."""

    tolerance_rad_s: float = 1e-3
    window_s: float = 0.2
    clock_tolerance_s: float = 0.02  # the CLI's defaults (service/cli/common.py) equal these


@dataclass(frozen=True)
class Measurements:
    """Measured poses at stamps (n,) ns: position (n, 3) m, quaternion (n, 4) x,y,z,w or None
    (position-only)."""

    stamps_ns: NDArray[np.int64]
    position_m: NDArray[np.float64]
    quaternion_xyzw: NDArray[np.float64] | None


@dataclass(frozen=True)
class Samples:
    """One row per kept segment: mean joints (n, k), mean position (n, 3), mean quaternion
    (n, 4) or None, the segment's mid time (n,) ns; and what was dropped."""

    joint_positions: NDArray[np.float64]
    position_m: NDArray[np.float64]
    quaternion_xyzw: NDArray[np.float64] | None
    stamps_ns: NDArray[np.int64]
    n_messages: int
    n_moving: int
    n_too_short: int
    n_no_measurement: int
    n_captures: int | None = None
    """With a capture topic: its messages (``n_moving`` then counts captures taken while the
    robot moved, ``n_too_short`` is 0)."""

    @property
    def n_samples(self) -> int:
        return len(self.stamps_ns)


def still_segments(
    stamps_ns: NDArray[np.int64], joints: NDArray[np.float64], tolerance_rad_s: float
) -> list[tuple[int, int]]:
    """Index ranges ``[start, stop)`` of the still segments of joint readings (n, k) at sorted
    stamps (n,) ns; a segment holds at least two messages."""
    if len(stamps_ns) < 2:
        return []
    dt_s = np.diff(stamps_ns).astype(float) / NS_PER_S
    step = np.max(np.abs(np.diff(joints, axis=0)), axis=1)
    still = np.where(dt_s > 0, step <= tolerance_rad_s * dt_s, step == 0.0)
    edges = np.diff(np.concatenate([[0], still.astype(np.int8), [0]]))
    starts, stops = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(a), int(b) + 1) for a, b in zip(starts, stops, strict=True)]


def mean_quaternion(quaternions_xyzw: NDArray[np.float64]) -> NDArray[np.float64]:
    """The average rotation of (n, 4) unit quaternions: the principal eigenvector of Σ q qᵀ
    (invariant to each quaternion's sign), signed like the first."""
    _, vectors = np.linalg.eigh(quaternions_xyzw.T @ quaternions_xyzw)
    mean = vectors[:, -1]
    return mean if mean @ quaternions_xyzw[0] >= 0.0 else -mean


def _is_still(joints: NDArray[np.float64], stamps_ns: NDArray[np.int64], tolerance: float) -> bool:
    return len(joints) >= 2 and still_segments(stamps_ns, joints, tolerance) == [(0, len(joints))]


def synchronise_captures(
    stamps_ns: NDArray[np.int64],
    joints: NDArray[np.float64],
    measured: Measurements,
    captures_ns: NDArray[np.int64],
    settings: StillSettings,
) -> Samples:
    """One sample per capture message: joints and measurements averaged over ``window_s``
    centred on it (measurements within ``clock_tolerance_s`` of the window's ends left out);
    dropped when the joints move inside the window or no measurement falls inside."""
    half_ns = round(settings.window_s * NS_PER_S / 2)
    margin_ns = round(settings.clock_tolerance_s * NS_PER_S)
    windows = [
        (int(t), int(t) - half_ns, int(t) + half_ns) for t in np.sort(captures_ns, kind="stable")
    ]
    still: list[tuple[int, int, int, int, int]] = []
    for stamp, first, last in windows:
        lo = int(np.searchsorted(stamps_ns, first, side="left"))
        hi = int(np.searchsorted(stamps_ns, last, side="right"))
        if _is_still(joints[lo:hi], stamps_ns[lo:hi], settings.tolerance_rad_s):
            still.append((lo, hi, first + margin_ns, last - margin_ns, stamp))
    moving = len(windows) - len(still)
    rows, no_measurement = _measured_rows(still, joints, measured)
    return _samples(
        rows,
        joints.shape[1],
        measured,
        len(stamps_ns),
        moving,
        0,
        no_measurement,
        n_captures=len(windows),
    )


def _measured_rows(
    windows: list[tuple[int, int, int, int, int]],
    joints: NDArray[np.float64],
    measured: Measurements,
) -> tuple[list[Row], int]:
    """The samples of still windows ``(start, stop, first_ns, last_ns, stamp_ns)``: joints
    ``[start, stop)`` averaged, measurements stamped in ``[first_ns, last_ns]`` averaged; and
    how many windows had no measurement."""
    rows: list[Row] = []
    for start, stop, first_ns, last_ns, stamp_ns in windows:
        row = _averages(joints[start:stop], measured, first_ns, last_ns)
        if row is not None:
            rows.append((*row, stamp_ns))
    return rows, len(windows) - len(rows)


def _averages(
    joints: NDArray[np.float64], measured: Measurements, first_ns: int, last_ns: int
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64] | None] | None:
    """Mean joints, and mean position and rotation of the measurements stamped within
    ``[first_ns, last_ns]``; None without one."""
    lo = np.searchsorted(measured.stamps_ns, first_ns, side="left")
    hi = np.searchsorted(measured.stamps_ns, last_ns, side="right")
    if hi <= lo:
        return None
    quaternion = (
        None
        if measured.quaternion_xyzw is None
        else mean_quaternion(measured.quaternion_xyzw[lo:hi])
    )
    return joints.mean(axis=0), measured.position_m[lo:hi].mean(axis=0), quaternion


def _samples(
    rows: list[Row],
    k: int,
    measured: Measurements,
    n_messages: int,
    n_moving: int,
    n_too_short: int,
    n_no_measurement: int,
    n_captures: int | None = None,
) -> Samples:
    return Samples(
        joint_positions=np.array([r[0] for r in rows]).reshape(-1, k),
        position_m=np.array([r[1] for r in rows]).reshape(-1, 3),
        quaternion_xyzw=None
        if measured.quaternion_xyzw is None
        else np.array([r[2] for r in rows]).reshape(-1, 4),
        stamps_ns=np.array([r[3] for r in rows], dtype=np.int64),
        n_messages=n_messages,
        n_moving=n_moving,
        n_too_short=n_too_short,
        n_no_measurement=n_no_measurement,
        n_captures=n_captures,
    )


def synchronise(
    stamps_ns: NDArray[np.int64],
    joints: NDArray[np.float64],
    measured: Measurements,
    settings: StillSettings,
) -> Samples:
    """One sample per still segment of the joint readings (n, k) at stamps (n,) ns with a
    measurement inside it (see the module docstring)."""
    segments = still_segments(stamps_ns, joints, settings.tolerance_rad_s)
    margin_ns = round(settings.clock_tolerance_s * NS_PER_S)
    window_ns = round(settings.window_s * NS_PER_S)
    long_enough: list[tuple[int, int, int, int, int]] = []
    for start, stop in segments:
        first, last = int(stamps_ns[start]), int(stamps_ns[stop - 1])
        if last - first >= window_ns:
            long_enough.append(
                (start, stop, first + margin_ns, last - margin_ns, (first + last) // 2)
            )
    too_short = len(segments) - len(long_enough)
    rows, no_measurement = _measured_rows(long_enough, joints, measured)
    in_segments = sum(stop - start for start, stop in segments)
    n_moving = len(stamps_ns) - in_segments
    return _samples(
        rows, joints.shape[1], measured, len(stamps_ns), n_moving, too_short, no_measurement
    )
