"""Simulated ball-in-socket recordings: configurations whose tool point sits in a socket.

The configurations come from damped Newton steps on the tool point (joint Jacobian by central
differences of :func:`solver.kinematics.forward_kinematics`, all rows at once) from random
configurations, to the socket point plus the socket's play ``e_n ~ N(0, σ² I)``; the residual of
:class:`~solver.measurement.models.FixedPoints` at the true parameters is then ``−e_n``.
"""

from __future__ import annotations

import numpy as np

from solver.arrays import FloatArray
from solver.kinematics import ChainParameters, forward_kinematics
from solver.model import KinematicChain


def configurations_at_points(
    chain: KinematicChain,
    params: ChainParameters,
    targets_m: FloatArray,
    start: FloatArray,
    *,
    iterations: int = 60,
    step_rad: float = 1e-6,
    perturbations: FloatArray | None = None,
) -> FloatArray:
    """Joint positions (N, k) near ``start`` (N, k) whose tool point (translation of the rigid
    forward kinematics at ``params``) reaches ``targets_m`` (N, 3), m, robot base frame;
    ``perturbations`` (N, k, 6): each row's random local twists of the joint frames (Eq. 7),
    so that the perturbed robot's ball sits in the socket."""
    q = start.astype(float).copy()
    n, k = q.shape
    loads = np.zeros((n, len(chain.compliance_axes)))

    def point(x: FloatArray) -> FloatArray:
        return forward_kinematics(chain, params, x, loads, perturbations=perturbations)[:, :3, 3]

    for _ in range(iterations):
        error = targets_m - point(q)
        if np.abs(error).max() < 1e-13:
            break
        jacobian = np.empty((n, 3, k))
        for j in range(k):
            delta = np.zeros(k)
            delta[j] = step_rad
            jacobian[:, :, j] = (point(q + delta) - point(q - delta)) / (2 * step_rad)
        step = np.linalg.pinv(jacobian) @ error[:, :, None]
        q += np.clip(step[:, :, 0], -0.3, 0.3)
    return q
