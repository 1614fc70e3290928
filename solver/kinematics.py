"""Batched forward kinematics of Eq. (7) and the Jacobians shared by both calibration stages.

For N configurations at once. Frames (DESIGN.md §2): poses ``X_0E`` map the end-effector (tip,
marker) frame into the measurement frame; every Jacobian maps a local twist ``[v; w]`` to the
end-effector-frame residual ``r = Log(X_model^-1 · X_measured)``.

One Jacobian for both stages: if ``B_i`` is the part of the chain after ``L_i``, then a local link
correction ``L_i <- L_i · Exp(δ_i)`` and a random perturbation ``ξ_i`` both move the residual by
``J_i = Ad_{B_i}^-1`` (paper Eq. 9, written in the end-effector frame). A compliance coefficient
moves it by ``g = Ad_{S}^-1 · s · τ`` with ``S`` the chain from that compliant rotation onwards.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from solver import lie
from solver.arrays import FloatArray
from solver.model import KinematicChain

TWIST_COMPONENTS = ("tx", "ty", "tz", "rx", "ry", "rz")


@dataclass(frozen=True)
class ChainParameters:
    """Calibratable values of the chain: link placements and compliances.

    ``links`` (k+1, 4, 4): ``L_1`` includes the measurement frame -> robot base transform and
    ``L_{k+1}`` the flange -> marker/tool offset. ``compliance_rad_per_nm`` (n_axes,) follows
    ``chain.compliance_axes``.
    """

    links: FloatArray
    compliance_rad_per_nm: FloatArray

    @classmethod
    def nominal(cls, chain: KinematicChain) -> ChainParameters:
        """The URDF geometry, rigid joints, measurement frame = robot base frame."""
        return cls(chain.nominal_links.copy(), np.zeros(len(chain.compliance_axes)))

    def with_link_corrections(self, twists: FloatArray) -> ChainParameters:
        """``L_i <- L_i · Exp(δ_i)`` for local corrections ``twists`` (k+1, 6)."""
        return replace(self, links=self.links @ lie.se3_exp(twists))


@dataclass(frozen=True)
class ChainEvaluation:
    """Pose and Jacobians at N configurations.

    ``pose`` (N, 4, 4): ``X_0E``. ``link_jacobians`` (N, k+1, 6, 6): ``J_i = Ad_{B_i}^-1``, which
    is also the Jacobian of the perturbation ξ_i (i <= k). ``compliance_jacobians``
    (N, n_axes, 6): residual change per unit compliance (rad/N·m) of each axis.
    """

    pose: FloatArray
    link_jacobians: FloatArray
    compliance_jacobians: FloatArray


def forward_kinematics(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    perturbations: FloatArray | None = None,
) -> FloatArray:
    """Paper Eq. (7): ``X_0E`` (N, 4, 4) for joint positions (N, k) and gravity loads (N, n_axes).

    ``perturbations`` (N, k, 6), optional: the random local twists ξ_i right after each ``L_i``.
    Without them this is the mean pose.
    """
    return _evaluate(chain, params, joint_positions, loads_nm, perturbations, jacobians=False).pose


def evaluate_chain(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
) -> ChainEvaluation:
    """Mean pose and all Jacobians (paper Eq. 9, end-effector frame) in one backward sweep."""
    return _evaluate(chain, params, joint_positions, loads_nm, None, jacobians=True)


def _joint_angles(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
) -> tuple[FloatArray, FloatArray]:
    """Deflected joint positions ``q + c τ`` (N, k) and virtual-axis angles (N, n_axes) (Eq. 6)."""
    deflection = loads_nm * params.compliance_rad_per_nm
    moved = joint_positions.astype(float)
    virtual = np.zeros_like(deflection)
    for a, axis in enumerate(chain.compliance_axes):
        if axis.is_joint_axis:
            moved[:, axis.joint_index] = moved[:, axis.joint_index] + deflection[:, a]
        else:
            virtual[:, a] = deflection[:, a]
    return moved, virtual


def _evaluate(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    perturbations: FloatArray | None,
    *,
    jacobians: bool,
) -> ChainEvaluation:
    n = joint_positions.shape[0]
    k = chain.n_joints
    moved, virtual_angles = _joint_angles(chain, params, joint_positions, loads_nm)
    axes_at = [
        [a for a, ax in enumerate(chain.compliance_axes) if ax.joint_index == i] for i in range(k)
    ]

    # Written slice by slice in place: at 10^5..10^6 samples allocation and copies dominate.
    link_jac = np.empty((n, k + 1, 6, 6)) if jacobians else np.zeros((0,))
    comp_jac = np.zeros((n, len(chain.compliance_axes), 6)) if jacobians else np.zeros((0,))
    suffix = np.broadcast_to(params.links[k], (n, 4, 4)).copy()  # L_{k+1}
    if jacobians:
        link_jac[:, k] = np.eye(6)
    # Walk the chain backwards; `suffix` is always the product of everything after the cursor.
    for i in range(k - 1, -1, -1):
        suffix = lie.screw_exp(chain.joint_screws[i], moved[:, i]) @ suffix
        if jacobians:
            own = [a for a in axes_at[i] if chain.compliance_axes[a].is_joint_axis]
            if own:
                column = lie.adjoint_inverse_apply(suffix, chain.joint_screws[i])
                for a in own:
                    comp_jac[:, a] = column * loads_nm[:, a, None]
        for a in reversed(axes_at[i]):
            axis = chain.compliance_axes[a]
            if axis.is_joint_axis:
                continue
            screw = np.r_[0.0, 0.0, 0.0, axis.axis]
            suffix = lie.screw_exp(screw, virtual_angles[:, a]) @ suffix
            if jacobians:
                comp_jac[:, a] = lie.adjoint_inverse_apply(suffix, screw) * loads_nm[:, a, None]
        if perturbations is not None:
            suffix = lie.se3_exp(perturbations[:, i]) @ suffix
        if jacobians:
            lie.adjoint_inverse(suffix, out=link_jac[:, i])
        suffix = params.links[i] @ suffix
    return ChainEvaluation(suffix, link_jac, comp_jac)


def pose_residuals(model_pose: FloatArray, measured_pose: FloatArray) -> FloatArray:
    """End-effector-frame residual of a full pose (DESIGN.md §2, Eq. 8):
    ``r = Log(X_model^-1 · X_measured)`` (N, 6), [v; w] in m and rad.

    Which residual a recording has is its measurement model's choice
    (:meth:`solver.measurement.FullPose.residuals`: this, or :func:`position_residuals`)."""
    return lie.se3_log(lie.inverse(model_pose) @ measured_pose)


def position_residuals(model_pose: FloatArray, measured_pose: FloatArray) -> FloatArray:
    """End-effector-frame residual of a position (DESIGN.md §2): ``R_model^T (p_measured -
    p_model)`` (N, 3) in m, the translation of ``X_model^-1 · X_measured`` whatever the
    unmeasured rotation."""
    delta = measured_pose[:, :3, 3] - model_pose[:, :3, 3]
    return np.einsum("nji,nj->ni", model_pose[:, :3, :3], delta)


def pose_residual_map(residual: FloatArray) -> FloatArray:
    """The exact Jacobian ``M`` (N, 6, 6) of :func:`pose_residuals` ``r`` (N, 6) in a tip-local
    twist ``t`` of the model pose, ``r(X·Exp(t)) ≈ r − M t``: ``M = J_l⁻¹(r)``
    (:func:`~solver.lie.se3_left_jacobian_inverse`). Eq. 9 takes ``M = I``, which is off by
    ``½ ad_r``: a relative error of half the residual's size (5e-4 at 1 mrad). Discovery's
    Gauss–Newton steps take it (:func:`solver.discovery.fitting.fit_model`)."""
    return lie.se3_left_jacobian_inverse(residual)


def parameter_names(chain: KinematicChain) -> list[str]:
    """Stacked-Jacobian column names: ``<link>.<tx..rz>``, then ``compliance.<axis>``."""
    names = [f"{link}.{c}" for link in chain.link_names for c in TWIST_COMPONENTS]
    return names + [f"compliance.{axis.name}" for axis in chain.compliance_axes]


def stacked_jacobian(evaluation: ChainEvaluation) -> FloatArray:
    """All parameter columns, (N, 6, 6(k+1) + n_axes), in :func:`parameter_names` order."""
    n, links = evaluation.link_jacobians.shape[:2]
    link_cols = evaluation.link_jacobians.transpose(0, 2, 1, 3).reshape(n, 6, 6 * links)
    return np.concatenate([link_cols, evaluation.compliance_jacobians.transpose(0, 2, 1)], axis=2)
