"""Deterministic calibration of geometry and compliance (paper Eq. 8–10, §V-A).

Gauss–Newton on the stacked end-effector-frame residuals with the columns of
:func:`solver.kinematics.stacked_jacobian`, after a closed-form alignment of the measurement frame
and tool offset. Columns that the data cannot identify are removed once, up front, by a
column-pivoted QR and reported by name; the same columns stay fixed through the iterations.
"""

from __future__ import annotations

import functools
import time
from dataclasses import dataclass, field

import numpy as np
import scipy.linalg
from numpy.typing import NDArray

from solver import lie
from solver.alignment import align_full_pose, align_position_only
from solver.errors import CalibrationError
from solver.kinematics import (
    ChainParameters,
    evaluate_chain,
    forward_kinematics,
    parameter_names,
    pose_residuals,
    stacked_jacobian,
)
from solver.model import KinematicChain, gravity_loads, sample_configurations

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True)
class FitOptions:
    """Settings of the deterministic fit.

    ``rotation_weight_m_per_rad``: residual rotation rows are multiplied by this (paper: 1, i.e.
    1 rad counts like 1 m). ``rank_tolerance``: a column is unidentifiable when its pivoted-QR
    diagonal, relative to the largest, falls below this (columns scaled to unit norm first).
    ``free_links``: indices of the links ``L_i`` (0-based) to calibrate, None = all;
    ``(0, k)`` calibrates only the measurement frame and the tool offset.
    """

    max_iterations: int = 50
    tolerance: float = 1e-10
    rotation_weight_m_per_rad: float = 1.0
    rank_tolerance: float = 1e-7
    free_links: tuple[int, ...] | None = None
    fit_compliance: bool = True


@dataclass(frozen=True)
class DeterministicFit:
    """Result of :func:`fit_deterministic`.

    ``estimated``/``removed``: parameter names kept / dropped as unidentifiable (or not free).
    ``standard_errors``: of the estimated parameters at the solution (same order as
    ``estimated``; link entries are local twists in m and rad, compliance in rad/N·m).
    ``residuals`` (N, d) unweighted, m and rad; ``jacobian`` (N, d, p) of the estimated columns,
    weighted like the fit (rotation rows times the weight).
    """

    params: ChainParameters
    estimated: list[str]
    removed: list[str]
    standard_errors: FloatArray
    rank: int
    condition_number: float
    iterations: int
    converged: bool
    cost_history: list[float]
    residuals: FloatArray
    jacobian: FloatArray
    elapsed_s: float
    notes: list[str] = field(default_factory=list)


def nominal_pose(chain: KinematicChain, joint_positions: FloatArray) -> FloatArray:
    """URDF forward kinematics base -> tip, rigid; (N, 4, 4)."""
    params = ChainParameters.nominal(chain)
    zero_loads = np.zeros((joint_positions.shape[0], len(chain.compliance_axes)))
    return forward_kinematics(chain, params, joint_positions, zero_loads)


def initial_parameters(
    chain: KinematicChain,
    joint_positions: FloatArray,
    measured_pose: FloatArray,
    *,
    position_only: bool,
) -> ChainParameters:
    """Nominal geometry; closed-form measurement frame folded into L_1, tool into L_{k+1}."""
    nominal = nominal_pose(chain, joint_positions)
    if position_only:
        world, tool = align_position_only(nominal, measured_pose[:, :3, 3])
    else:
        world, tool = align_full_pose(nominal, measured_pose)
    links = chain.nominal_links.copy()
    links[0] = world @ links[0]
    links[-1] = links[-1] @ tool
    return ChainParameters(links, np.zeros(len(chain.compliance_axes)))


def weighted(values: FloatArray, *, position_only: bool, rotation_weight: float) -> FloatArray:
    """Multiply the rotation rows (axis 1, entries 3..5) by the weight (full pose only)."""
    if position_only or rotation_weight == 1.0:
        return values
    scale = np.r_[1.0, 1.0, 1.0, rotation_weight, rotation_weight, rotation_weight]
    return values * scale.reshape((1, 6) + (1,) * (values.ndim - 2))


def fit_deterministic(
    chain: KinematicChain,
    joint_positions: FloatArray,
    measured_pose: FloatArray,
    loads_nm: FloatArray,
    *,
    position_only: bool,
    options: FitOptions = FitOptions(),
    start: ChainParameters | None = None,
) -> DeterministicFit:
    """Paper Eq. (10): iterate ``x_w = A_w^+ y_w`` and re-linearise until the cost settles.

    ``measured_pose`` (N, 4, 4) in the measurement frame (rotation ignored if position-only);
    ``loads_nm`` (N, n_axes) from :func:`solver.model.gravity_loads`.
    """
    started = time.perf_counter()
    params = start or initial_parameters(
        chain, joint_positions, measured_pose, position_only=position_only
    )
    names = parameter_names(chain)
    rows = 3 if position_only else 6

    def linearise(p: ChainParameters) -> tuple[FloatArray, FloatArray]:
        evaluation = evaluate_chain(chain, p, joint_positions, loads_nm)
        residual = pose_residuals(evaluation.pose, measured_pose, position_only=position_only)
        jacobian = stacked_jacobian(evaluation)[:, :rows]
        w = options.rotation_weight_m_per_rad
        return (
            weighted(residual, position_only=position_only, rotation_weight=w),
            weighted(jacobian, position_only=position_only, rotation_weight=w),
        )

    required = identifiable_parameter_count(chain, position_only=position_only, options=options)
    if rows * joint_positions.shape[0] <= required:
        raise CalibrationError(
            f"fewer samples than identifiable parameters: {joint_positions.shape[0]} samples give "
            f"{rows * joint_positions.shape[0]} equations for {required} identifiable parameters; "
            f"record at least {required // rows + 1} configurations (3x that is advisable)"
        )
    residual, jacobian = linearise(params)
    keep, rank, condition = _identifiable_columns(jacobian, chain, options)
    costs = [float(np.sum(residual**2))]
    converged = False
    iterations = 0
    while iterations < options.max_iterations:
        iterations += 1
        a = jacobian[:, :, keep].reshape(-1, keep.size)
        step = np.linalg.lstsq(a, residual.reshape(-1), rcond=None)[0]
        params, residual, jacobian, cost = _accept_step(
            params, step, keep, costs[-1], linearise, chain
        )
        costs.append(cost)
        if abs(costs[-2] - cost) <= options.tolerance * max(costs[-2], 1e-300):
            converged = True
            break
    a = jacobian[:, :, keep].reshape(-1, keep.size)
    dof = a.shape[0] - keep.size
    sigma2 = costs[-1] / dof
    covariance = sigma2 * np.linalg.pinv(a.T @ a)
    final_residual = pose_residuals(
        forward_kinematics(chain, params, joint_positions, loads_nm),
        measured_pose,
        position_only=position_only,
    )
    return DeterministicFit(
        params=params,
        estimated=[names[i] for i in keep],
        removed=[names[i] for i in range(len(names)) if i not in set(keep.tolist())],
        standard_errors=np.sqrt(np.clip(np.diag(covariance), 0.0, None)),
        rank=rank,
        condition_number=condition,
        iterations=iterations,
        converged=converged,
        cost_history=costs,
        residuals=final_residual,
        jacobian=jacobian[:, :, keep],
        elapsed_s=time.perf_counter() - started,
    )


@functools.lru_cache(maxsize=64)
def identifiable_parameter_count(
    chain: KinematicChain, *, position_only: bool, options: FitOptions = FitOptions()
) -> int:
    """Parameters identifiable from generic data: the rank on 200 random configurations.

    Depends only on the chain and the options, so it is cached (chains are immutable).
    """
    rng = np.random.default_rng(0)
    q = sample_configurations(chain, 200, rng)
    evaluation = evaluate_chain(chain, ChainParameters.nominal(chain), q, gravity_loads(chain, q))
    jacobian = stacked_jacobian(evaluation)[:, : 3 if position_only else 6]
    return _identifiable_columns(jacobian, chain, options)[1]


def _accept_step(params, step, keep, previous_cost, linearise, chain):  # type: ignore[no-untyped-def]
    """Apply a Gauss–Newton step, halving it while the cost rises (at most 20 halvings)."""
    scale = 1.0
    for _ in range(20):
        candidate = _apply_step(params, scale * step, keep, chain)
        residual, jacobian = linearise(candidate)
        cost = float(np.sum(residual**2))
        if cost <= previous_cost:
            return candidate, residual, jacobian, cost
        scale *= 0.5
    return params, *linearise(params), previous_cost


def _apply_step(
    params: ChainParameters, step: FloatArray, keep: NDArray[np.intp], chain: KinematicChain
) -> ChainParameters:
    full = np.zeros(6 * chain.n_links + len(chain.compliance_axes))
    full[keep] = step
    link_twists = full[: 6 * chain.n_links].reshape(chain.n_links, 6)
    updated = params.with_link_corrections(link_twists)
    return ChainParameters(updated.links, params.compliance_rad_per_nm + full[6 * chain.n_links :])


def _identifiable_columns(
    jacobian: FloatArray, chain: KinematicChain, options: FitOptions
) -> tuple[NDArray[np.intp], int, float]:
    """Free columns that survive column-pivoted QR on the unit-norm-scaled stacked Jacobian.

    Returns kept column indices (sorted), the rank and the condition number of the kept,
    scaled columns.
    """
    n_link_cols = 6 * chain.n_links
    free = np.zeros(jacobian.shape[2], dtype=bool)
    links = range(chain.n_links) if options.free_links is None else options.free_links
    for i in links:
        free[6 * i : 6 * i + 6] = True
    free[n_link_cols:] = options.fit_compliance
    candidates = np.flatnonzero(free)
    a = jacobian[:, :, candidates].reshape(-1, candidates.size)
    norms = np.linalg.norm(a, axis=0)
    nonzero = norms > 1e-12 * max(norms.max(), 1e-300)
    candidates, a, norms = candidates[nonzero], a[:, nonzero], norms[nonzero]
    _, r, pivots = scipy.linalg.qr(a / norms, mode="economic", pivoting=True)
    diagonal = np.abs(np.diag(r))
    rank = int(np.sum(diagonal > options.rank_tolerance * diagonal[0]))
    keep = np.sort(candidates[pivots[:rank]])
    singular = np.linalg.svd(
        a[:, np.isin(candidates, keep)] / norms[np.isin(candidates, keep)], compute_uv=False
    )
    return keep, rank, float(singular[0] / singular[-1])


def outlier_mask(residuals: FloatArray, sigma: float) -> BoolArray:
    """Paper §V-A: keep samples whose every residual component is within ``sigma`` standard
    deviations of that component's mean; (N, d) -> (N,) bool."""
    centred = residuals - residuals.mean(axis=0)
    spread = residuals.std(axis=0)
    spread = np.where(spread > 0.0, spread, np.inf)
    return np.all(np.abs(centred) <= sigma * spread, axis=1)


def pose_errors(
    predicted: FloatArray, measured: FloatArray, *, position_only: bool
) -> tuple[FloatArray, FloatArray | None]:
    """Per-sample translation error (mm) and rotation error (deg; None if position-only)."""
    translation_mm = 1e3 * np.linalg.norm(predicted[:, :3, 3] - measured[:, :3, 3], axis=1)
    if position_only:
        return translation_mm, None
    relative = np.swapaxes(predicted[:, :3, :3], 1, 2) @ measured[:, :3, :3]
    return translation_mm, np.degrees(lie.rotation_angle_rad(relative))
