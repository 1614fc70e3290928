"""Check poses (``kincal design --check K``, issue 33): the K candidate configurations at which
``kincal check`` of a calibration states the smallest changes.

Result JSON + candidates (given, or drawn as ``kincal design`` draws them,
:func:`service.app.design.candidate_configurations`) -> :class:`CheckDesign`. The predictive
covariance and the candidate changes at the candidates are the check's own
(:func:`service.app.check.predicted_parts`); the choice is :mod:`solver.design.check_poses`';
the sizes reported are those :func:`service.app.check.run_check` states at the chosen poses
(:func:`service.app.check.stated_sizes_at`).
"""

from __future__ import annotations

import numpy as np

from schemas.calibration import CalibrationResult
from schemas.check import DEFAULT_LEVEL
from schemas.design import CheckDesign, DesignedSize, DesignOptions, DesignPose
from service.app import check as checks
from service.app import rank
from service.app.design import candidate_configurations
from service.render import result_json
from solver import check as solver_check
from solver.arrays import FloatArray, IntArray
from solver.design.candidates import outside_limits, tip_poses
from solver.design.check_poses import (
    CheckPoseTerms,
    choose_check_poses,
    part_scales,
    worst_relative_size,
)
from solver.errors import KincalError
from solver.model import KinematicChain

RANDOM_DRAWS = 200
"""Random sets of K candidates the chosen poses' criterion is compared with."""

CRITERION = (
    "minimise the largest located size of a joint offset, the base and the tool (translation "
    "and rotation): sqrt(noncentrality / separation information), the separation information "
    "the worst direction's information outside the span of the most similar candidate change; "
    "each size over its scale (the same with every candidate a check pose); greedy, then "
    "single exchanges"
)


def run_check_design(
    result: CalibrationResult,
    options: DesignOptions,
    n_poses: int,
    *,
    candidates: FloatArray | None = None,
    level: float = DEFAULT_LEVEL,
    result_name: str = "the calibration result",
) -> CheckDesign:
    """Choose ``n_poses`` check poses for ``result`` among ``candidates`` (N, k) (None: drawn
    within the joint limits and ``options``' working volume, ``options.n_candidates`` with
    ``options.seed``), for a check at family-wise ``level``."""
    checks.refuse_unsupported(result, result_name)
    if n_poses < solver_check.MIN_POSES:
        raise KincalError(
            f"--check {n_poses}: a check needs at least {solver_check.MIN_POSES} poses"
        )
    chain, _ = result_json.result_chain(result)
    q, notes, rows = _candidates(chain, options, candidates)
    if q.shape[0] < n_poses:
        raise KincalError(
            f"--check {n_poses}: only {q.shape[0]} candidates; give more candidates or widen "
            "the working volume"
        )
    d = result_json.result_measurement(result).dim
    parts = checks.predicted_parts(result, q, None, d)
    terms = CheckPoseTerms.build(
        parts.local,
        parts.parameter_jacobian,
        parts.parameter_covariance,
        parts.candidates,
        n_poses,
        level,
    )
    scales = part_scales(terms)
    chosen = choose_check_poses(terms, n_poses, scales)
    rng = np.random.default_rng([options.seed, 33])
    draws = np.stack([rng.choice(q.shape[0], n_poses, replace=False) for _ in range(RANDOM_DRAWS)])
    random = worst_relative_size(terms, draws, scales)
    sizes = checks.stated_sizes_at(result, q[chosen], level, d)
    scale_of = {p.name: float(s) for p, s in zip(terms.parts, scales, strict=True)}
    positions = tip_poses(chain, q[chosen])[:, :3, 3]
    return CheckDesign(
        kincal_version=result_json.kincal_version(),
        calibration=rank.calibration_reference(result),
        joint_names=list(chain.joint_names),
        candidates=int(q.shape[0]),
        candidate_source="sampled" if candidates is None else "given",
        level=level,
        power=solver_check.POWER,
        criterion=CRITERION,
        worst_relative_size=float(worst_relative_size(terms, chosen, scales)),
        random_worst_relative_size=float(np.median(random)),
        random_draws=RANDOM_DRAWS,
        poses=[
            DesignPose(
                candidate=int(rows[n]),
                joint_positions=q[n].tolist(),
                tip_position_m=(float(p[0]), float(p[1]), float(p[2])),
            )
            for n, p in zip(chosen, positions, strict=True)
        ],
        stated_sizes=[_designed(size, scale_of[size.name]) for size in sizes],
        notes=notes,
    )


def _candidates(
    chain: KinematicChain, options: DesignOptions, given: FloatArray | None
) -> tuple[FloatArray, list[str], IntArray]:
    """The candidates (N, k), notes, and each one's row in ``given`` (N,): given rows outside
    the URDF's joint limits are dropped with a note (a recording may hold a few a little
    outside them), then as :func:`service.app.design.candidate_configurations`."""
    if given is None:
        q, notes, _ = candidate_configurations(chain, options, None)
        return q, notes, np.arange(q.shape[0])
    if given.ndim != 2 or given.shape[1] != chain.n_joints:
        raise KincalError(
            f"candidates: each configuration needs {chain.n_joints} joint positions "
            f"({', '.join(chain.joint_names)})"
        )
    within = np.setdiff1d(np.arange(given.shape[0]), outside_limits(chain, given))
    q, notes, inside = candidate_configurations(chain, options, given[within])
    if within.size < given.shape[0]:
        notes.insert(
            0,
            f"{given.shape[0] - within.size} given candidates outside the joint limits dropped",
        )
    return q, notes, within if inside is None else within[inside]


def _designed(size: solver_check.StatedSize, scale: float) -> DesignedSize:
    stated = checks.stated_size(size)
    known = np.isfinite(scale) and stated.size is not None
    return DesignedSize(
        **stated.model_dump(),
        scale=scale if np.isfinite(scale) else None,
        relative=stated.size / scale if known and stated.size is not None else None,
    )
