"""Closed-form first guess of the measurement frame W and the tool/marker offset T.

Measurements satisfy ``X_measured ≈ W · X_nominal(q) · T``: W is the robot base in the measurement
frame (camera, tracker), T the marker on the flange. Gauss–Newton then refines both with the rest
of the chain, so these only need to land in its basin of attraction; users need not supply
extrinsics.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from solver import lie
from solver.arrays import FloatArray
from solver.errors import CalibrationError


def kabsch_rotation(source: FloatArray, target: FloatArray) -> FloatArray:
    """Rotation R minimising ``sum |target_n - R source_n|^2`` for centred point sets (N, 3)."""
    u, _, vt = np.linalg.svd(target.T @ source)
    sign = np.sign(np.linalg.det(u @ vt))
    return u @ np.diag([1.0, 1.0, sign]) @ vt


def project_to_rotation(matrix: FloatArray) -> FloatArray:
    """Closest rotation (Frobenius) to a 3x3 matrix."""
    u, _, vt = np.linalg.svd(matrix)
    return u @ np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))]) @ vt


def align_full_pose(nominal: FloatArray, measured: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Robot-world/hand-eye ``measured_n = W · nominal_n · T`` for full poses (N, 4, 4).

    Rotation of W from relative rotations, ``log(R_m,a R_m,b^T) = R_W log(R_a R_b^T)``
    (Kabsch on rotation vectors), R_T as the chordal mean, then both translations by one linear
    least-squares solve: ``p_m - R_W p_n = R_W R_n t_T + t_W``.
    """
    n = nominal.shape[0]
    first, second = _pairs(n)
    alpha = lie.so3_log(nominal[first, :3, :3] @ np.swapaxes(nominal[second, :3, :3], 1, 2))
    beta = lie.so3_log(measured[first, :3, :3] @ np.swapaxes(measured[second, :3, :3], 1, 2))
    usable = (np.linalg.norm(alpha, axis=1) > 0.05) & (np.linalg.norm(alpha, axis=1) < 2.8)
    if usable.sum() < 2:
        raise CalibrationError(
            "the recorded orientations barely change; record configurations that rotate the "
            "end effector about at least two different axes"
        )
    rotation_world = kabsch_rotation(alpha[usable], beta[usable])
    tool_guess = np.swapaxes(nominal[:, :3, :3], 1, 2) @ rotation_world.T @ measured[:, :3, :3]
    rotation_tool = project_to_rotation(tool_guess.sum(axis=0))
    design = np.concatenate(
        [rotation_world @ nominal[:, :3, :3], np.broadcast_to(np.eye(3), (n, 3, 3))], axis=2
    ).reshape(3 * n, 6)
    rhs = (measured[:, :3, 3] - nominal[:, :3, 3] @ rotation_world.T).reshape(3 * n)
    solution = np.linalg.lstsq(design, rhs, rcond=None)[0]
    return _transform(rotation_world, solution[3:]), _transform(rotation_tool, solution[:3])


def align_positions(
    nominal: FloatArray, measured_position_m: FloatArray, *, iterations: int = 50
) -> tuple[FloatArray, FloatArray]:
    """``p_m = R_W (p_n + R_n t_T) + t_W`` for positions (N, 3): Kabsch alternated with a linear
    solve for the marker offset t_T; the tool rotation is unobservable and stays identity."""
    n = nominal.shape[0]
    offset_tool = np.zeros(3)
    rotation_world = np.eye(3)
    for _ in range(iterations):
        points = nominal[:, :3, 3] + nominal[:, :3, :3] @ offset_tool
        centred_points = points - points.mean(axis=0)
        centred_measured = measured_position_m - measured_position_m.mean(axis=0)
        rotation_world = kabsch_rotation(centred_points, centred_measured)
        design = np.concatenate(
            [rotation_world @ nominal[:, :3, :3], np.broadcast_to(np.eye(3), (n, 3, 3))], axis=2
        ).reshape(3 * n, 6)
        rhs = (measured_position_m - nominal[:, :3, 3] @ rotation_world.T).reshape(3 * n)
        solution = np.linalg.lstsq(design, rhs, rcond=None)[0]
        if np.linalg.norm(solution[:3] - offset_tool) < 1e-12:
            break
        offset_tool = solution[:3]
    world = _transform(rotation_world, solution[3:])
    return world, _transform(np.eye(3), offset_tool)


def _pairs(n: int) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Index pairs spread over the recording (several offsets, so pairs differ in rotation)."""
    index = np.arange(n)
    offsets = sorted({max(1, n // d) for d in (2, 3, 5, 7)} - {n})
    first = np.concatenate([index for _ in offsets])
    second = np.concatenate([(index + o) % n for o in offsets])
    return first, second


def _transform(rotation: FloatArray, translation: FloatArray) -> FloatArray:
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = translation
    return out
