"""The Gaussian-process baseline of paper ref. [13]: one GP per pose-error component.

Used two ways, as in the paper:

(a) as a calibration (Table II, "Cal. GP"): the "before" model (nominal robot with the
    measurement frame and tool fitted) leaves residuals ``r = Log(X_before^-1 X_measured)``
    (end-effector frame, [v; w], m and rad; 3 components for position-only data). One GP per
    component learns r as a function of the joint angles; the corrected prediction is
    ``X_before(q) · Exp(mean(q))`` (position-only: ``p + R · mean``).
(b) as an uncertainty predictor (Table III): the GP predictive variances go on the diagonal of
    the end-effector covariance and are scored with Eq. (22–23) like ours.

Kernel (documented choice; ref. [13]'s exact kernel is not reproduced in the paper):
``C · Matern(ν = 5/2, one length scale per joint, 0.05..100 rad) + White`` on the raw joint
angles, targets normalised (``normalize_y``). Matern-5/2 rather than RBF because pose errors
from geometry and compliance are smooth but not analytic-smooth over the workspace scale we
see; one length scale per joint lets the GP ignore joints that do not matter (e.g. the last
wrist joint for position). The white-noise term absorbs measurement noise and the random
perturbations. Hyper-parameters by maximum marginal likelihood (L-BFGS from the defaults; add
seeded restarts with ``GPSettings.n_restarts_optimizer``, ~3 s each at N = 125).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from sklearn.exceptions import ConvergenceWarning
from sklearn.gaussian_process import GaussianProcessRegressor
from sklearn.gaussian_process.kernels import ConstantKernel, Matern, WhiteKernel

from solver import lie
from solver.arrays import FloatArray, IntArray
from solver.calibration import FitOptions
from solver.errors import CalibrationError
from solver.evaluation import Method
from solver.kinematics import ChainParameters, forward_kinematics
from solver.measurement.models import FullPose
from solver.measurement.pose import fit_deterministic
from solver.model import KinematicChain
from solver.ranking import ConfigurationScores, TaskMetric

BaselinePoses = Callable[[IntArray, IntArray], FloatArray]
"""``(train_indices, rows) -> poses (len(rows), 4, 4)`` of a "before" model fitted on train."""


@dataclass(frozen=True)
class GPSettings:
    """Kernel bounds and optimiser restarts (see the module docstring)."""

    nu: float = 2.5
    length_scale_rad: float = 1.0
    length_scale_bounds_rad: tuple[float, float] = (0.05, 100.0)
    noise_bounds: tuple[float, float] = (1e-8, 10.0)
    n_restarts_optimizer: int = 0
    seed: int = 0


@dataclass(frozen=True, eq=False)
class GPErrorModel:
    """One fitted GP per residual component (6 for a full pose, 3 for a position)."""

    regressors: tuple[GaussianProcessRegressor, ...]

    @property
    def dim(self) -> int:
        """Residual components (6 or 3)."""
        return len(self.regressors)

    def predict(self, joint_positions: FloatArray) -> tuple[FloatArray, FloatArray]:
        """Mean (N, d) and predictive variance (N, d) of the residual, m² / rad²."""
        q = np.asarray(joint_positions, dtype=float)
        means, variances = [], []
        for gp in self.regressors:
            mean, std = gp.predict(q, return_std=True)
            means.append(mean)
            variances.append(std**2)
        return np.stack(means, axis=1), np.stack(variances, axis=1)


def fit_gp_error_model(
    joint_positions: FloatArray,
    residuals: FloatArray,
    settings: GPSettings = GPSettings(),
) -> GPErrorModel:
    """Fit one GP per column of ``residuals`` (N, 6 or 3) on ``joint_positions`` (N, k)."""
    q = np.asarray(joint_positions, dtype=float)
    r = np.asarray(residuals, dtype=float)
    if q.ndim != 2 or r.ndim != 2 or r.shape[0] != q.shape[0] or r.shape[1] not in (3, 6):
        raise CalibrationError(
            f"GP baseline needs (N, k) joints and (N, 6 or 3) residuals, got {q.shape}, {r.shape}"
        )
    if q.shape[0] < 3:
        raise CalibrationError("GP baseline needs at least 3 training samples")
    regressors = []
    for component in range(r.shape[1]):
        kernel = ConstantKernel(1.0, (1e-3, 1e3)) * Matern(
            length_scale=np.full(q.shape[1], settings.length_scale_rad),
            length_scale_bounds=settings.length_scale_bounds_rad,
            nu=settings.nu,
        ) + WhiteKernel(0.1, settings.noise_bounds)
        gp = GaussianProcessRegressor(
            kernel=kernel,
            normalize_y=True,
            n_restarts_optimizer=settings.n_restarts_optimizer,
            random_state=settings.seed + component,
        )
        with warnings.catch_warnings():
            # Length scales at their bounds are expected (joints that do not matter).
            warnings.simplefilter("ignore", ConvergenceWarning)
            gp.fit(q, r[:, component])
        regressors.append(gp)
    return GPErrorModel(tuple(regressors))


def corrected_poses(
    model: GPErrorModel, baseline_pose: FloatArray, joint_positions: FloatArray
) -> FloatArray:
    """Baseline poses (N, 4, 4) corrected by the GP mean: ``X · Exp(mean)``, or ``p + R mean``
    for position models (the rotation is left as it is)."""
    mean, _ = model.predict(joint_positions)
    if model.dim == 3:
        out = np.array(baseline_pose, dtype=float, copy=True)
        out[:, :3, 3] += np.einsum("nij,nj->ni", baseline_pose[:, :3, :3], mean)
        return out
    return baseline_pose @ lie.se3_exp(mean)


def gp_method(
    joint_positions: FloatArray,
    measured_pose: FloatArray,
    baseline: BaselinePoses | FloatArray,
    *,
    measurement: FullPose,
    settings: GPSettings = GPSettings(),
) -> Method:
    """The GP baseline as a :data:`solver.evaluation.Method` for ``cross_validate``, on the
    residuals of the rows' ``measurement`` (:class:`~solver.measurement.FullPose` or
    :class:`~solver.measurement.Position`).

    ``baseline``: the "before" model, either a callable ``(train, rows) -> poses`` that fits it
    on the training rows (no information from the test rows), or fixed poses (N, 4, 4).
    """

    def predict_test(train: IntArray, test: IntArray) -> FloatArray:
        if callable(baseline):
            before_train, before_test = baseline(train, train), baseline(train, test)
        else:
            before_train, before_test = baseline[train], baseline[test]
        residuals = measurement.residuals(before_train, measured_pose[train])
        model = fit_gp_error_model(joint_positions[train], residuals, settings)
        return corrected_poses(model, before_test, joint_positions[test])

    return predict_test


def gp_calibration_method(
    chain: KinematicChain,
    joint_positions: FloatArray,
    measured_pose: FloatArray,
    loads_nm: FloatArray,
    *,
    measurement: FullPose,
    baseline_options: FitOptions,
    settings: GPSettings | None = None,
) -> Method:
    """Paper Table II "Cal. GP" as a :func:`~solver.evaluation.cross_validate` method over
    the rows given (joint positions (N, k) rad, measured poses (N, 4, 4), gravity loads
    (N, n_axes) N·m): the "before" model — ``baseline_options`` fit only the measurement
    frame and tool, on each training split, exactly as the held-out evaluation does — corrected
    by one GP per residual component (:func:`gp_method`)."""
    fitted: dict[bytes, ChainParameters] = {}  # the GP method asks for train and test rows

    def before(train: IntArray, rows: IntArray) -> FloatArray:
        key = np.asarray(train).tobytes()
        if key not in fitted:
            fitted.clear()
            fitted[key] = fit_deterministic(
                chain,
                joint_positions[train],
                measured_pose[train],
                loads_nm[train],
                measurement=measurement,
                options=baseline_options,
            ).params
        return forward_kinematics(chain, fitted[key], joint_positions[rows], loads_nm[rows])

    return gp_method(
        joint_positions,
        measured_pose,
        before,
        measurement=measurement,
        settings=settings or GPSettings(),
    )


def gp_scores(
    model: GPErrorModel, joint_positions: FloatArray, metric: TaskMetric
) -> ConfigurationScores:
    """Paper Table III baseline: GP variances as diag Σ_E, scored with Eq. (22–23).

    Position models have no rotational variances (set to 0). The white-noise part of the
    variance is the same for every configuration, so only the GP's own uncertainty ranks.
    """
    _, variance = model.predict(joint_positions)
    if model.dim == 3:
        variance = np.concatenate([variance, np.zeros_like(variance)], axis=1)
    score = variance @ np.diag(metric.quadratic_form)
    return ConfigurationScores(score=score, ee_variance=variance)
