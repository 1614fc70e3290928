"""Which samples a pass uses: the outlier rule as a fixed keep mask per chunk (paper §V-A)."""

from __future__ import annotations

import hashlib
import uuid
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from solver import lie
from solver.batch_chain import (
    pose_residuals,
    sweep_chain,
)
from solver.calibration import (
    within_spread,
)
from solver.kinematics import ChainParameters
from solver.stream.chunks import Block, StreamProblem, cache_masks, cached_masks, take_residuals

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]


@dataclass(frozen=True, eq=False)
class OutlierRule:
    """Paper §V-A as a fixed rule: residuals at ``params`` within ``sigma`` standard deviations
    ``std`` of ``mean`` (d,) in every component; ``token`` names it in the mask cache."""

    params: ChainParameters
    mean: FloatArray
    std: FloatArray
    sigma: float
    token: str = field(default_factory=lambda: uuid.uuid4().hex)


def parameters_key(params: ChainParameters) -> bytes:
    """A digest of the parameter values: residuals kept from a pass are reused only at the
    very same point."""
    digest = hashlib.blake2b(digest_size=16)
    digest.update(np.ascontiguousarray(params.links).tobytes())
    digest.update(np.ascontiguousarray(params.compliance_rad_per_nm).tobytes())
    return digest.digest()


def rule_mask(
    problem: StreamProblem,
    rule: OutlierRule,
    motions: list[lie.ScrewMotion],
    loads_nm: FloatArray,
    rotation: FloatArray | None,
    translation: FloatArray,
) -> BoolArray:
    """Samples kept by ``rule`` (b,): residuals at ``rule.params`` from one forward pass."""
    sweep = sweep_chain(
        problem.chain, rule.params, motions, loads_nm, residual_dim=problem.residual_dim
    )
    residual = pose_residuals(sweep, rotation, translation).residual
    return within_spread(residual.T, rule.mean, rule.std, rule.sigma)


def used_mask(
    problem: StreamProblem,
    rule: OutlierRule | None,
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
