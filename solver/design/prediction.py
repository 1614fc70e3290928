"""What a design predicts before any data is recorded: parameter standard errors and the
parameter part of the predicted pose variance over task configurations.

With K poses of information ``M = P + Σ_{n∈S} M_n`` (equilibrated, noise-whitened, Eq. 8–10 with
Gaussian noise), the estimate's covariance is ``M⁻¹`` in equilibrated units, so
``se_i = sqrt((M⁻¹)_ii) / s_i`` in the parameter's units (m, rad, rad/N·m), and at a configuration
q the pose error the parameters leave has covariance ``J(q) Cov(θ) J(q)ᵀ`` (end-effector frame,
[v; w]; its trace, 1 m ↔ 1 rad as in DESIGN.md §2, is the "parameter part of the predicted pose
variance"; the sensor noise comes on top).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from solver.arrays import FloatArray
from solver.design.information import (
    InformationBlock,
    geometry_information,
    whitened_pose_jacobian,
)
from solver.kinematics import ChainParameters, evaluate_chain, parameter_names, stacked_jacobian
from solver.model import KinematicChain


def block_columns(chain: KinematicChain, block: InformationBlock) -> NDArray[np.intp]:
    """Stacked-Jacobian column indices of a geometry block's parameters."""
    names = parameter_names(chain)
    return np.array([names.index(name) for name in block.names], dtype=np.intp)


def equilibrated_pose_jacobian(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    block: InformationBlock,
    rows: int,
) -> FloatArray:
    """``Ĵ(q) = J(q)[:rows, keep] / s`` (N, rows, p): pose change (m, rad) per equilibrated
    parameter of the geometry ``block``."""
    evaluation = evaluate_chain(chain, params, joint_positions, loads_nm)
    jacobian = stacked_jacobian(evaluation)[:, :rows][:, :, block_columns(chain, block)]
    return jacobian / block.scale[: block.dimension]


def task_root(task_jacobian: FloatArray) -> FloatArray:
    """R (p, p) with ``R Rᵀ = T = mean_t Ĵ_tᵀ Ĵ_t`` for task Jacobians (N_t, rows, p)."""
    flat = task_jacobian.reshape(-1, task_jacobian.shape[2])
    t = flat.T @ flat / task_jacobian.shape[0]
    eigval, eigvec = np.linalg.eigh(0.5 * (t + t.T))
    return np.asarray(eigvec * np.sqrt(np.clip(eigval, 0.0, None)), dtype=float)


def parameter_covariance(information: FloatArray) -> FloatArray:
    """``M⁻¹`` (p, p); a singular information gives infinite variances."""
    try:
        return np.asarray(np.linalg.inv(information), dtype=float)
    except np.linalg.LinAlgError:
        return np.full_like(information, np.inf)


def standard_errors(
    block: InformationBlock, information: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Per parameter of a geometry block: the standard error in its own units and the
    equilibrated one (its effect on a measurement, in units of the sensor noise)."""
    equilibrated = np.sqrt(np.clip(np.diag(parameter_covariance(information)), 0.0, None))
    return equilibrated / block.scale[: block.dimension], equilibrated


def predicted_pose_variance(information: FloatArray, task_jacobian: FloatArray) -> FloatArray:
    """``tr(Ĵ_t M⁻¹ Ĵ_tᵀ)`` per task configuration (N_t,), m² + rad²."""
    covariance = parameter_covariance(information)
    return np.einsum("nri,ij,nrj->n", task_jacobian, covariance, task_jacobian)


@dataclass(frozen=True)
class Yardstick:
    """How designs are compared on one working volume: the identifiable parameters and their
    equilibration fixed by ``reference`` (the geometry block of held-out configurations in
    the volume, the calibration's pruning rule), and the equilibrated pose Jacobians ``task``
    (N_t, rows, p) of those held-out configurations. Every design is scored on the same
    parameters, units, noise and task, whatever candidates it came from."""

    chain: KinematicChain
    params: ChainParameters
    noise_std: FloatArray
    reference: InformationBlock
    task: FloatArray

    @classmethod
    def on(
        cls,
        chain: KinematicChain,
        params: ChainParameters,
        heldout: FloatArray,
        heldout_loads_nm: FloatArray,
        noise_std: FloatArray,
    ) -> Yardstick:
        reference = geometry_information(chain, params, heldout, heldout_loads_nm, noise_std)
        rows = noise_std.shape[0]
        task = equilibrated_pose_jacobian(chain, params, heldout, heldout_loads_nm, reference, rows)
        return cls(chain, params, noise_std, reference, task)

    def block(self, joint_positions: FloatArray, loads_nm: FloatArray) -> InformationBlock:
        """The information block of candidate configurations in the yardstick's parameters
        and units (no prior), so that criterion I is exactly :meth:`score`'s variance."""
        rows = whitened_pose_jacobian(
            self.chain, self.params, joint_positions, loads_nm, self.noise_std
        )
        columns = block_columns(self.chain, self.reference)
        p = columns.size
        return replace(
            self.reference,
            factors=np.ascontiguousarray(rows[:, :, columns] / self.reference.scale),
            prior=np.zeros((p, p)),
        )

    def score(self, joint_positions: FloatArray, loads_nm: FloatArray) -> tuple[float, float]:
        """(the parameter part of the predicted pose variance, mean over the task, m² + rad²;
        the worst identifiable parameter's standard error, equilibrated: in units of the
        sensor noise) of recording ``joint_positions`` (N, k), repeats counted."""
        information = self.block(joint_positions, loads_nm).information()
        variance = float(np.mean(predicted_pose_variance(information, self.task)))
        return variance, float(np.max(standard_errors(self.reference, information)[1]))
