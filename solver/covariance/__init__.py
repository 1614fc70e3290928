"""Covariance calibration of random perturbations in the kinematic chain (paper §IV-C).

Arrays in, arrays out; conventions of DESIGN.md §2 (end-effector frame, [v; w], m and rad).
Entry point: :func:`estimate_covariances`. The pieces are public for benchmarks:

- :mod:`.layout` — θ layout, design of Eq. (12–13);
- :mod:`.statistics` — additive sufficient statistics G, h, c of Eq. (13–14);
- :mod:`.objective` — the one objective all solvers share, scaling, PSD projection;
- :mod:`.solvers` — clarabel, pgd (Eq. 15, published and stable settings), nnls;
- :mod:`.identifiability` — rank, conditioning, null directions in words, the null-space rule;
- :mod:`.likelihood` / :mod:`.fitting` — Eq. (12), ML (Eq. 16–17), REML, Fisher information;
- :mod:`.uncertainty` — standard errors and intervals of σ.
"""

from __future__ import annotations

from solver.covariance.estimate import CovarianceEstimate, FrameCovariance, estimate_covariances
from solver.covariance.fitting import fit_likelihood
from solver.covariance.identifiability import (
    IdentifiabilityReport,
    analyse_identifiability,
    resolve_null_space,
)
from solver.covariance.layout import (
    POSE_AXES,
    CovarianceLayout,
    column_matrix,
    design_matrix,
    make_layout,
    vech_w,
)
from solver.covariance.likelihood import (
    ee_covariance_batch,
    fisher_information_ml,
    fisher_information_reml,
    fit_basis_transform,
    gaussian_nll,
    moment_sandwich_meat,
    restricted_nll,
    theta_gradient,
)
from solver.covariance.objective import (
    moment_gradient,
    moment_objective,
    moment_residual_norm,
    problem_scaling,
    projected_gradient_residual,
    scaled_problem,
)
from solver.covariance.solvers import (
    KKT_TOLERANCE,
    PGD_PUBLISHED,
    PGD_STABLE,
    CovarianceSolution,
    PGDSettings,
    published_step_limit,
    solve_clarabel,
    solve_moment,
    solve_nnls,
    solve_pgd,
)
from solver.covariance.statistics import (
    MomentStatistics,
    build_moment_statistics,
    empty_statistics,
)
from solver.covariance.uncertainty import ThetaUncertainty, theta_covariance, theta_uncertainty

__all__ = [
    "KKT_TOLERANCE",
    "PGD_PUBLISHED",
    "PGD_STABLE",
    "POSE_AXES",
    "CovarianceEstimate",
    "CovarianceLayout",
    "CovarianceSolution",
    "FrameCovariance",
    "IdentifiabilityReport",
    "MomentStatistics",
    "PGDSettings",
    "ThetaUncertainty",
    "analyse_identifiability",
    "build_moment_statistics",
    "column_matrix",
    "design_matrix",
    "ee_covariance_batch",
    "empty_statistics",
    "estimate_covariances",
    "fisher_information_ml",
    "fisher_information_reml",
    "fit_basis_transform",
    "fit_likelihood",
    "gaussian_nll",
    "make_layout",
    "moment_gradient",
    "moment_objective",
    "moment_residual_norm",
    "moment_sandwich_meat",
    "problem_scaling",
    "projected_gradient_residual",
    "published_step_limit",
    "resolve_null_space",
    "restricted_nll",
    "scaled_problem",
    "solve_clarabel",
    "solve_moment",
    "solve_nnls",
    "solve_pgd",
    "theta_covariance",
    "theta_gradient",
    "theta_uncertainty",
    "vech_w",
]
