"""Fisher information of one calibration pose, for both calibration stages.

Every candidate configuration ``q_n`` contributes ``M_n = F_nᵀ F_n`` to the information of a
design; ``F_n`` (r, p) is stored, never ``M_n``, so scoring 10⁴ candidates costs one matrix
product. Both stages use the calibration's own Jacobians (:mod:`solver.kinematics`):

- **Geometry and compliance** (Eq. 8–10): rows of the stacked Jacobian
  :func:`~solver.kinematics.stacked_jacobian` (end-effector frame, [v; w], the first 3 rows when
  position-only) restricted to the columns :func:`solver.calibration.identifiable_columns` keeps
  (the calibration's pruning rule) and whitened by the sensor noise:
  ``F_n = Σ_n^{-1/2} J_n[:, keep]`` — the information of the noise-weighted fit.
- **Covariances** (Eq. 12–17): the expected Fisher information of the Gaussian likelihood of θ
  (:func:`solver.covariance.likelihood.fisher_information_ml`) at prior covariances,
  ``M_n = ½ K̃_nᵀ K̃_n`` with ``K̃_n`` the moment design (:func:`~solver.covariance.layout.
  design_matrix`) of the whitened frame Jacobians ``L_n⁻¹ A_f(q_n)``, restricted to the
  directions of θ the candidate set identifies (singular values above
  :data:`solver.covariance.identifiability.RANK_RTOL` of the largest, the rule of the result's
  identifiability report).

Parameters are equilibrated (θ̂ = θ · s, ``s`` the root-mean-square size of each column over the
candidates, the scaling of the calibration's pruning), so criteria that are not scale invariant
(A, E) compare parameters by their effect on a measurement in units of the sensor noise.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from solver.arrays import FloatArray, IntArray
from solver.calibration import (
    FitOptions,
    frame_columns,
    free_columns,
    identifiable_columns,
    pivoted_columns,
    weighted,
)
from solver.covariance.identifiability import RANK_RTOL
from solver.covariance.layout import (
    CovarianceLayout,
    Structure,
    column_matrix,
    design_matrix,
    make_layout,
)
from solver.covariance.likelihood import whitening
from solver.errors import SolverError
from solver.kinematics import (
    ChainParameters,
    evaluate_chain,
    forward_kinematics,
    parameter_names,
    stacked_jacobian,
)
from solver.measurement.fit import row_weights
from solver.measurement.models import (
    EyeOnHead,
    FixedPoints,
    FullPose,
    MeasurementModel,
    MeasurementRows,
    ModelParameters,
    MultiMarker,
    PoseComponents,
    chain_column_count,
)
from solver.model import KinematicChain


@dataclass(frozen=True)
class InformationBlock:
    """Per-candidate information of one stage: ``M_n = F_nᵀ F_n`` in equilibrated units.

    ``factors`` (N, r, p); ``prior`` (p, p) information already held (a recording's, for a
    sequential design; zeros otherwise); ``scale`` (p,) with θ̂ = θ · scale for the named
    parameters (``basis`` None), or the equilibration of the full θ when the block lives in
    the identifiable subspace ``basis`` (Q, p), θ̂_sub = basisᵀ (θ · scale).
    """

    stage: str
    factors: FloatArray
    prior: FloatArray
    scale: FloatArray
    names: tuple[str, ...]
    basis: FloatArray | None = None
    nuisance: int = 0
    nuisance_names: tuple[str, ...] = ()
    """Names of the ``nuisance`` columns (a measurement model's own unknowns)."""

    @property
    def n_candidates(self) -> int:
        return int(self.factors.shape[0])

    @property
    def dimension(self) -> int:
        """p: the parameters the criterion is on (the nuisance columns profiled out)."""
        return int(self.factors.shape[2]) - self.nuisance

    @property
    def columns(self) -> int:
        """p + e: the factors' columns, the e nuisance columns last."""
        return int(self.factors.shape[2])

    def subset(self, index: IntArray) -> InformationBlock:
        """The same block for the candidates ``index``."""
        return replace(self, factors=self.factors[index])

    def information(self, index: IntArray | None = None) -> FloatArray:
        """``prior + Σ_{n ∈ index} M_n`` (p, p), the nuisance parameters profiled out
        (:func:`profiled`); all candidates when ``index`` is None."""
        f = self.factors if index is None else self.factors[index]
        flat = f.reshape(-1, self.columns)
        return profiled(self.prior + flat.T @ flat, self.nuisance)


def profiled(information: FloatArray, nuisance: int) -> FloatArray:
    """The information about the first p parameters when the last ``nuisance`` (e) ones are
    unknown too: the Schur complement ``M_pp − M_pe M_ee⁺ M_ep`` (p, p) of the (p+e, p+e)
    information (the inverse of the (p, p) block of M⁻¹). Matrix-concave in M, so every
    concave criterion of it stays concave in the design weights."""
    if nuisance == 0:
        return information
    p = information.shape[0] - nuisance
    m_pe, m_ee = information[:p, p:], information[p:, p:]
    gain = np.linalg.lstsq(m_ee, m_pe.T, rcond=None)[0]  # M_ee⁺ M_ep (e, p)
    schur = information[:p, :p] - m_pe @ gain
    return np.asarray(0.5 * (schur + schur.T), dtype=float)


def profiled_factors(information: FloatArray, factors: FloatArray, nuisance: int) -> FloatArray:
    """``F̃_n = F_n,p − F_n,e M_ee⁺ M_ep`` (N, r, p): the derivative of the profiled information
    :func:`profiled` in the weight of candidate n is ``F̃_nᵀ F̃_n`` times the weight's
    multiplier (``d(M_pp − M_pe M_ee⁻¹ M_ep) = dM_pp − dM_pe B − Bᵀ dM_ep + Bᵀ dM_ee B`` with
    ``B = M_ee⁻¹ M_ep``), so the gradient of a criterion keeps the form ``‖F̃_n G‖²``."""
    if nuisance == 0:
        return factors
    p = information.shape[0] - nuisance
    gain = np.linalg.lstsq(information[p:, p:], information[p:, :p], rcond=None)[0]
    return np.asarray(factors[:, :, :p] - factors[:, :, p:] @ gain, dtype=float)


def whitened_pose_jacobian(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    noise_std: FloatArray,
) -> FloatArray:
    """``Σ_n^{-1/2} J(q)`` (N, d, P): all stacked-Jacobian columns (Eq. 9), the d =
    len(noise_std) measured rows (6 pose, 3 position-only) each divided by its noise standard
    deviation (m, rad)."""
    d = noise_std.shape[0]
    evaluation = evaluate_chain(chain, params, joint_positions, loads_nm)
    return stacked_jacobian(evaluation)[:, :d] / noise_std[None, :, None]


def geometry_information(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    noise_std: FloatArray,
    *,
    options: FitOptions | None = None,
    recorded: tuple[FloatArray, FloatArray] | None = None,
) -> InformationBlock:
    """The geometry/compliance block of candidates ``joint_positions`` (N, k), loads (N, n_axes).

    ``noise_std`` (6,) or (3,) position-only, m and rad. ``recorded``: joint positions and loads
    of a recording already made; its information becomes the prior and the identifiable columns
    are those of recording and candidates together (what the new poses can make identifiable).
    """
    d = noise_std.shape[0]
    candidates = whitened_pose_jacobian(chain, params, joint_positions, loads_nm, noise_std)
    old = (
        np.zeros((0, d, candidates.shape[2]))
        if recorded is None
        else whitened_pose_jacobian(chain, params, recorded[0], recorded[1], noise_std)
    )
    both = np.concatenate([old, candidates])
    # The calibration's pruning sees the fit's rows: unwhitened, rotation rows weighted.
    fit_rows = weighted(
        both * noise_std[None, :, None],
        dim=d,
        rotation_weight=(options or FitOptions()).rotation_weight_m_per_rad,
    )
    keep = identifiable_columns(fit_rows, chain, options or FitOptions())[0]
    scale = column_scale(candidates[:, :, keep])
    factors = candidates[:, :, keep] / scale
    prior_rows = (old[:, :, keep] / scale).reshape(-1, keep.size)
    names = parameter_names(chain)
    return InformationBlock(
        "geometry",
        np.ascontiguousarray(factors),
        prior_rows.T @ prior_rows,
        scale,
        tuple(names[i] for i in keep),
    )


def column_scale(factors: FloatArray) -> FloatArray:
    """Root-mean-square norm of each column over the candidates (N, r, p) -> (p,), > 0."""
    scale = np.sqrt(np.mean(np.sum(factors**2, axis=1), axis=0))
    return np.where(scale > 0.0, scale, 1.0)


@dataclass(frozen=True)
class CovariancePrior:
    """Covariances at which the covariance stage's information is evaluated (it depends on
    them): ``frames`` (F, 6, 6) of the perturbations ξ_f of the chain joints ``frame_index``,
    ``noise`` (6, 6) of the sensor, [v; w], m² and rad²."""

    frame_names: tuple[str, ...]
    frame_index: tuple[int, ...]
    frames: FloatArray
    noise: FloatArray


def covariance_layout(
    prior: CovariancePrior, residual_dim: int, structure: Structure
) -> CovarianceLayout:
    """The layout the calibration estimates: the prior's frames and the noise frame."""
    return make_layout(prior.frame_names, residual_dim, structure=structure)


def covariance_information(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    prior: CovariancePrior,
    *,
    residual_dim: int,
    structure: Structure = "diag",
    recorded: tuple[FloatArray, FloatArray] | None = None,
) -> tuple[InformationBlock, CovarianceLayout]:
    """The covariance block (expected ML Fisher information of θ at ``prior``) and its layout.

    Restricted to the directions of θ that recording and candidates together identify.
    """
    layout = covariance_layout(prior, residual_dim, structure)
    theta = layout.theta_from_covariances(np.concatenate([prior.frames, prior.noise[None]]))
    candidates = _covariance_factors(
        chain, params, joint_positions, loads_nm, layout, theta, prior.frame_index
    )
    old = (
        np.zeros((0, *candidates.shape[1:]))
        if recorded is None
        else _covariance_factors(
            chain, params, recorded[0], recorded[1], layout, theta, prior.frame_index
        )
    )
    scale = column_scale(candidates)
    flat = np.concatenate([old, candidates]).reshape(-1, layout.n_params) / scale
    eigval, eigvec = np.linalg.eigh(flat.T @ flat)
    singular = np.sqrt(np.clip(eigval[::-1], 0.0, None))
    basis = eigvec[:, ::-1][:, singular > RANK_RTOL * singular[0]]
    if basis.shape[1] == 0:
        raise SolverError("the candidates carry no information about the covariances")
    factors = (candidates / scale) @ basis
    prior_rows = ((old / scale) @ basis).reshape(-1, basis.shape[1])
    names = tuple(f"direction {i + 1}" for i in range(basis.shape[1]))
    block = InformationBlock(
        "covariance",
        np.ascontiguousarray(factors),
        prior_rows.T @ prior_rows,
        scale,
        names,
        basis,
    )
    return block, layout


def frame_jacobians(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    frame_index: tuple[int, ...],
    residual_dim: int,
) -> FloatArray:
    """``A_f(q)`` (N, F, d, 6) of the perturbed frames: the link Jacobians ``J_f`` of Eq. (9)."""
    evaluation = evaluate_chain(chain, params, joint_positions, loads_nm)
    return evaluation.link_jacobians[:, list(frame_index), :residual_dim, :]


def _covariance_factors(
    chain: KinematicChain,
    params: ChainParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    layout: CovarianceLayout,
    theta: FloatArray,
    frame_index: tuple[int, ...],
) -> FloatArray:
    """``K̃_n / √2`` (N, D, Q): ``Σ K̃ᵀK̃ / 2`` is :func:`fisher_information_ml`."""
    jac = frame_jacobians(
        chain, params, joint_positions, loads_nm, frame_index, layout.residual_dim
    )
    left = whitening(theta, jac, layout, None, inverse=True)
    return design_matrix(left @ column_matrix(jac, layout), layout) / np.sqrt(2.0)


def ideal_rows(
    model: MeasurementModel,
    chain: KinematicChain,
    params: ModelParameters,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    group: IntArray | None = None,
) -> MeasurementRows:
    """Rows whose measurements are what ``model`` predicts at ``params`` (zero residual), so
    its Jacobian is the one a calibration sees at convergence: poses (N, 4, 4) for the pose
    models (in the model's measurement frame), marker positions (N, m, 3) for markers; for
    ball in socket the socket ``group`` (N,) of each row (its Jacobian ``R J_tip[:3]``, ``−I``
    does not depend on the residual)."""
    if isinstance(model, FixedPoints):
        if group is None:
            raise SolverError(
                "measurement 'point': a design needs the socket of every candidate (rows "
                "need a physical contact); give recorded socket configurations"
            )
        return MeasurementRows.of(joint_positions, loads_nm, None, group)
    rows = MeasurementRows.of(joint_positions, loads_nm)
    if isinstance(model, MultiMarker):
        pose = forward_kinematics(chain, params, joint_positions, loads_nm)
        markers = pose[:, None, :3, 3] + np.einsum(
            "nij,mj->nmi", pose[:, :3, :3], model.offsets(params)
        )
        return MeasurementRows.of(joint_positions, loads_nm, markers)
    if isinstance(model, (FullPose, EyeOnHead)):
        return MeasurementRows.of(
            joint_positions, loads_nm, model.predicted_pose(chain, params, rows)
        )
    if isinstance(model, PoseComponents):
        pose = forward_kinematics(chain, params, joint_positions, loads_nm)
        return MeasurementRows.of(joint_positions, loads_nm, pose)
    raise SolverError(f"measurement {model.name!r}: no ideal rows for a design")


def model_information(
    chain: KinematicChain,
    params: ModelParameters,
    model: MeasurementModel,
    joint_positions: FloatArray,
    loads_nm: FloatArray,
    noise_std: FloatArray,
    *,
    options: FitOptions | None = None,
    group: IntArray | None = None,
) -> InformationBlock:
    """The geometry block of candidates for any measurement model, from its own Jacobian
    ``A`` (N, d, P + E) of :meth:`MeasurementModel.linearise` (Eq. 10), whitened by the noise
    of each residual row ``noise_std`` (d,): ``F_n = Σ^{-1/2} A_n[:, keep]``. ``keep``: the
    columns :func:`solver.measurement.fit.fit_measurement` would fit on all candidates (free,
    visible to the model, surviving pivoted QR on the fit's weighted rows). The model's own
    unknowns (socket points, marker offsets) are the last ``nuisance`` columns, profiled out
    by the criteria; its extra equations (known distances) are the prior. ``group``: the
    socket of each candidate (N,), for ball in socket."""
    options = options or FitOptions()
    rows = ideal_rows(model, chain, params, joint_positions, loads_nm, group)
    _, jacobian = model.linearise(chain, params, rows)
    assert jacobian is not None
    _, extra_a = model.constraints(chain, params)
    weights = row_weights(model, options)
    fit_rows = (jacobian * weights[None, :, None]).reshape(-1, jacobian.shape[2])
    free = free_columns(chain, options, jacobian.shape[2])
    n_chain = chain_column_count(chain)
    free[:n_chain] &= model.visible_columns(chain)
    first = frame_columns(chain, jacobian.shape[2])
    design = np.concatenate([fit_rows, extra_a])
    keep = pivoted_columns(design, free, options.rank_tolerance, first)[0]
    whitened = jacobian[:, :, keep] / noise_std[None, :, None]
    scale = column_scale(whitened)
    factors = whitened / scale
    # Known distances: equations of the whole design, unweighted by the poses (m, as the rows).
    prior_rows = extra_a[:, keep] / (float(noise_std[0]) * scale)
    names = parameter_names(chain) + model.extra_names()
    return InformationBlock(
        "geometry",
        np.ascontiguousarray(factors),
        prior_rows.T @ prior_rows,
        scale,
        tuple(names[i] for i in keep[keep < n_chain]),
        nuisance=int(np.sum(keep >= n_chain)),
        nuisance_names=tuple(names[i] for i in keep[keep >= n_chain]),
    )


def model_noise_std(model: MeasurementModel, noise_m: float, noise_rad: float) -> FloatArray:
    """The sensor noise of each residual row (d,): ``noise_m`` on translation rows, ``noise_rad``
    on rotation rows."""
    noise = np.full(model.dim, noise_m)
    noise[list(model.rotation_rows)] = noise_rad
    return noise
