"""Which samples a pass uses: the outlier rule as a fixed keep mask per chunk.

Two rules. :class:`OutlierRule` keeps a sample whose every residual component lies within
``sigma`` spreads of a centre: with the mean and standard deviation at 2σ it is the paper's
rule (§V-A), with the median and the scaled MAD at a family-wise threshold it is the first,
robust step of the model-based rule. :class:`RowRule` is a decision already taken row by row —
the model-based rule's: each sample's residual against its own predicted covariance Σ_E(q)
(Eq. 12), see :func:`solver.stream.covariance.model_rule_removed`.
"""

from __future__ import annotations

import hashlib
import uuid
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray
from scipy import special

from solver import lie
from solver.arrays import BoolArray, FloatArray
from solver.batch_chain import (
    pose_residuals,
    sweep_chain,
)
from solver.calibration import (
    within_spread,
)
from solver.distributions import f_isf
from solver.kinematics import ChainParameters
from solver.stream.chunks import Block, StreamProblem, cache_masks, cached_masks, take_residuals


@dataclass(frozen=True, eq=False)
class OutlierRule:
    """Paper §V-A as a fixed rule: residuals at ``params`` within ``sigma`` standard deviations
    ``std`` of ``mean`` (d,) in every component; ``token`` names it in the mask cache."""

    params: ChainParameters
    mean: FloatArray
    std: FloatArray
    sigma: float
    token: str = field(default_factory=lambda: uuid.uuid4().hex)


@dataclass(frozen=True, eq=False)
class RowRule:
    """Keeps every sample but ``removed_rows`` (sorted 0-based rows of the recording)."""

    removed_rows: NDArray[np.int64]
    token: str = field(default_factory=lambda: uuid.uuid4().hex)

    def keep(self, rows: NDArray[np.integer[Any]]) -> BoolArray:
        return ~np.isin(rows, self.removed_rows)


Rule = OutlierRule | RowRule


def family_wise_z(level: float, n_rows: int, dim: int) -> float:
    """Per-component |z| beyond which a Gaussian component of one of ``n_rows`` samples falls
    with probability ``level`` over the whole recording (Bonferroni over n·d two-sided tests)."""
    return float(-special.ndtri(level / (2.0 * n_rows * dim)))  # scipy.stats.norm.isf


def family_wise_t2(level: float, n_rows: int, dim: int, dof: float) -> float:
    """Squared Mahalanobis distance beyond which one of ``n_rows`` clean samples falls with
    probability ``level`` over the whole recording (Bonferroni), when the covariance it is
    measured against was itself estimated with ``dof`` degrees of freedom: Hotelling's
    ``T² = dof·d/(dof − d + 1) · F(d, dof − d + 1)``, which tends to χ²_d as ``dof`` grows.
    At N = 119 poses the χ² quantile (28.3) would remove clean samples whose distance is
    inflated only by the covariance estimate's own error; T² (33.2) does not."""
    alpha = level / n_rows
    dof = max(dof, dim + 1.0)
    return float(dof * dim / (dof - dim + 1) * f_isf(alpha, dim, dof - dim + 1))


MODEL_RULE_MAX_SHARE = 0.5
"""The model-based rule may remove at most this share of a recording's rows: beyond it the
"gross errors" are the majority, and a model fitted to them cannot tell which rows are wrong
(the breakdown point of any estimator is one half)."""


def model_rule_refusal(
    n_rows: int, n_removed: int, min_rows: int, converged: bool
) -> Literal["not_converged", "model_misfit"] | None:
    """Why the model-based rule must not remove ``n_removed`` of ``n_rows`` rows, None when it
    may: it would leave fewer than ``min_rows`` (the fit then has fewer equations than
    identifiable parameters) or remove more than :data:`MODEL_RULE_MAX_SHARE` of the rows. The
    cause is the fit the rows were judged by: "not_converged" when it had not converged, else
    "model_misfit" (the model does not explain the data, so every row looks like an outlier)."""
    if n_removed == 0:
        return None
    if n_rows - n_removed >= min_rows and n_removed <= MODEL_RULE_MAX_SHARE * n_rows:
        return None
    return "model_misfit" if converged else "not_converged"


MIN_EQUATIONS_PER_COVARIANCE_ENTRY = 3.0
"""The model rule's Σ_E step judges each row by a Σ_E(q) estimated from the same rows. Below
this many residual equations per identifiable covariance entry that estimate is too uncertain
to judge rows by (Hotelling's T² accounts for the deterministic fit, not for Σ_E's own
estimation): on the 21-row TIAGo Vicon file (63 equations, 44 identifiable entries) it removed
2 rows and the held-out error rose from 10.11 to 10.76 mm."""


def covariance_too_uncertain(n_equations: int, n_entries: int) -> str | None:
    """Why the Σ_E step must not judge rows (see :data:`MIN_EQUATIONS_PER_COVARIANCE_ENTRY`),
    None when it may."""
    if n_equations >= MIN_EQUATIONS_PER_COVARIANCE_ENTRY * n_entries:
        return None
    return (
        f"{n_equations} equations for {n_entries} identifiable covariance entries (fewer than "
        f"{MIN_EQUATIONS_PER_COVARIANCE_ENTRY:g} per entry): Σ_E is too uncertain to judge rows by"
    )


def robust_spread(residuals: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Median and 1.4826·MAD of residuals (n, d) per component: a centre and a standard
    deviation that a few gross errors do not move."""
    centre = np.median(residuals, axis=0)
    return centre, 1.4826 * np.median(np.abs(residuals - centre), axis=0)


def parameters_key(params: ChainParameters) -> bytes:
    """A digest of the parameter values: residuals kept from a pass are reused only at the
    very same point."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(np.ascontiguousarray(params.links).tobytes())
    digest.update(np.ascontiguousarray(params.compliance_rad_per_nm).tobytes())
    return digest.digest()


def block_residuals(
    problem: StreamProblem,
    params: ChainParameters,
    motions: list[lie.ScrewMotion],
    loads_nm: FloatArray,
    rotation: FloatArray | None,
    translation: FloatArray,
) -> FloatArray:
    """Residuals (d, b) of a block of samples at ``params``, from one forward sweep."""
    sweep = sweep_chain(problem.chain, params, motions, loads_nm, residual_dim=problem.residual_dim)
    return pose_residuals(sweep, rotation, translation).residual


def rule_mask(
    problem: StreamProblem,
    rule: OutlierRule,
    motions: list[lie.ScrewMotion],
    loads_nm: FloatArray,
    rotation: FloatArray | None,
    translation: FloatArray,
) -> BoolArray:
    """Samples kept by ``rule`` (b,): residuals at ``rule.params`` from one forward pass."""
    residual = block_residuals(problem, rule.params, motions, loads_nm, rotation, translation)
    return within_spread(residual.T, rule.mean, rule.std, rule.sigma)


def used_mask(
    problem: StreamProblem,
    rule: Rule | None,
    ref: Any,
    index: int,
    blocks: list[Block],
) -> BoolArray | None:
    """Keep mask of block ``index`` of chunk ``ref`` (prepared as ``blocks``) under ``rule``,
    None for every sample (cached per process). The residuals a pass at ``rule.params`` left
    behind are used when there are any (the rule's point is the first fit's last pass), else
    one forward sweep per block."""
    if rule is None:
        return None
    if isinstance(rule, RowRule):
        block = blocks[index]
        by_row = rule.keep(block.first_row + np.arange(block.n))
        return None if by_row.all() else by_row
    masks = cached_masks(problem, ref, rule.token)
    kept = take_residuals(problem, ref)
    if masks is None:
        if kept is not None and kept[0] == parameters_key(rule.params):
            masks = [within_spread(r.T, rule.mean, rule.std, rule.sigma) for r in kept[1]]
        else:
            masks = [
                rule_mask(problem, rule, b.motions, b.loads_nm, b.rotation, b.translation)
                for b in blocks
            ]
        cache_masks(problem, ref, rule.token, masks)
    mask = masks[index]
    return None if mask.all() else mask
