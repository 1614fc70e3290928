"""Configuration ranking from a calibration result (paper §IV-D): the ONE place the CLI and the
HTTP service call. Result JSON + configurations or a target pose -> :class:`RankingResult`.

Planners call this many times per second: build the :class:`solver.ranking.UncertaintyModel`
once per calibration with :func:`uncertainty_model` and pass it in (``model=``).
"""

from __future__ import annotations

import hashlib
import weakref
from collections.abc import Sequence
from typing import Any

import numpy as np
import pydantic_core

from schemas.calibration import CalibrationResult
from schemas.ranking import (
    CalibrationReference,
    PoseWeights,
    RankedConfiguration,
    RankingOptions,
    RankingResult,
    TargetRankingRequest,
    TaskWeights,
)
from service.render import corrections, result_json
from solver import lie
from solver.arrays import FloatArray
from solver.errors import KincalError, SolverError
from solver.ik import IKCandidate, IKOptions, ik_candidates
from solver.kinematics import parameter_names
from solver.model import KinematicChain
from solver.predictive import PredictiveModel, PredictiveParts
from solver.ranking import (
    ConfigurationScores,
    RandomEffects,
    TaskMetric,
    UncertaintyModel,
    ee_covariance,
    score_configurations,
)

NO_COVARIANCE = "has no covariance: run calibrate with covariance first"
NO_PREDICTIVE = (
    "has no predictive covariance (Cov(θ̂) and the model-error part, issue 13): re-run "
    "calibrate with this version of kincal"
)


def no_predictive(result: CalibrationResult) -> str:
    """Why ``result`` has no predictive covariance, in words that follow "the result"."""
    measurement = result.measurement
    if measurement is not None and measurement.type not in ("pose", "position"):
        return (
            "has no predictive covariance: it was calibrated without covariances "
            f"(measurement '{measurement.type}'), or by a kincal before issue 15"
        )
    return NO_PREDICTIVE


TIP_FRAME = "end effector (tip) frame"
"""How a measurement type whose residual is the tip pose names its frame (the start of
``measurement.frame``: relative-base, eye-on-head)."""


def model_error_applies(result: CalibrationResult) -> bool:
    """Whether the result's model-error part is a covariance of the predicted tip pose: for
    pose/position recordings (measurement-frame axes) and the types whose residual is the tip
    pose (tip-frame axes); not for a ball in a socket, markers or chosen components, whose
    residual is not the tip pose (their model error is in their own residual space)."""
    measurement = result.measurement
    if measurement is None or measurement.type in ("pose", "position"):
        return True
    return measurement.frame.startswith(TIP_FRAME)


def not_applicable_note(result: CalibrationResult) -> str | None:
    """What ``kincal predict`` leaves out of a measurement-type result's total, in words; None
    when every part applies."""
    measurement = result.measurement
    if result.predictive is None or model_error_applies(result) or measurement is None:
        return None
    return (
        f"measurement '{measurement.type}': the model-error part is estimated in its own "
        f"residual space ({measurement.frame}, components {', '.join(measurement.components)}), "
        "not for the tip pose: it is not applicable to the predicted tip covariance and left "
        "out (zero); the parameter part is the tip's J_θ Cov(θ̂) J_θᵀ over the chain "
        "parameters (the measurement's own unknowns do not move the tip)"
    )


NO_IK_SOLUTION = (
    "no configuration within the joint limits reaches the target; give it in the measurement "
    "frame (as kincal predict reports poses) or allow a free axis (--free-axis)"
)
_AXES = {"x": (1.0, 0.0, 0.0), "y": (0.0, 1.0, 0.0), "z": (0.0, 0.0, 1.0)}


def random_effects(result: CalibrationResult, chain: KinematicChain) -> RandomEffects:
    """Σ_1..Σ_k (+ tip frame) and Σ_n from the result's ``covariance`` block, by frame name."""
    if result.covariance is None:
        raise KincalError(f"calibration result {NO_COVARIANCE}")
    names = chain.link_names  # joint names, then the tip frame
    frames = np.zeros((len(names), 6, 6))
    seen: set[str] = set()
    for frame in result.covariance.frames:
        if frame.name not in names:
            raise KincalError(
                f"covariance frame {frame.name!r} is not a joint of the chain "
                f"({', '.join(names)}); the result is inconsistent, re-run calibrate"
            )
        if frame.name in seen:
            raise KincalError(f"covariance frame {frame.name!r} appears twice; re-run calibrate")
        seen.add(frame.name)
        frames[names.index(frame.name)] = np.array(frame.matrix, dtype=float)
    try:
        return RandomEffects(frames, np.array(result.covariance.noise.matrix, dtype=float))
    except SolverError as exc:
        raise KincalError(f"calibration result covariance: {exc}") from exc


def uncertainty_model(result: CalibrationResult) -> UncertaintyModel:
    """Calibrated chain + random effects + gravity settings of a result, ready to score."""
    chain, params = result_json.result_chain(result)
    effects = random_effects(result, chain)
    return UncertaintyModel.build(
        chain, params, effects, np.asarray(result.options.gravity_base_m_s2, dtype=float)
    )


def predict_covariances(
    result: CalibrationResult,
    joint_positions: FloatArray,
    payload_kg: FloatArray | None = None,
    *,
    include_noise: bool = True,
) -> FloatArray:
    """Predicted end-effector covariance Σ_E(q) (Eq. 12), (N, 6, 6), EE frame, [v; w], m/rad.

    Includes the measurement noise Σ_n unless ``include_noise`` is False (then it is the robot's
    own spread). ``payload_kg`` (N,) or None for the result's default payload.
    """
    model = uncertainty_model(result)
    q = corrections.true_configurations(result, model.chain, joint_positions, payload_kg)
    payload = payload_kg if payload_kg is not None else result.options.payload_kg
    return ee_covariance(model, q, payload_kg=payload, include_noise=include_noise)


_PREDICTIVE: weakref.WeakKeyDictionary[UncertaintyModel, PredictiveModel] = (
    weakref.WeakKeyDictionary()
)
"""Each uncertainty model's :class:`PredictiveModel`, built on its first "total" request (the
service keeps one uncertainty model per calibration)."""


def predictive_model(
    result: CalibrationResult, model: UncertaintyModel | None = None
) -> PredictiveModel:
    """The calibrated chain (``model``'s, when given) with the result's Cov(θ̂) and
    model-error part (zero when the calibration ran without held-out splits);
    :class:`KincalError` when the result has none."""
    if result.predictive is None:
        raise KincalError(f"calibration result {no_predictive(result)}")
    if model is not None and model in _PREDICTIVE:
        return _PREDICTIVE[model]
    chain, params = (model.chain, model.params) if model else result_json.result_chain(result)
    names = parameter_names(chain)
    block = result.predictive
    listed = block.parameter_covariance.parameters
    own = set(result.measurement.unknown_names()) if result.measurement is not None else set()
    unknown = [n for n in listed if n not in names and n not in own]
    if unknown:
        raise KincalError(
            f"predictive.parameter_covariance names {unknown}, not parameters of the chain; "
            "the result is inconsistent, re-run calibrate"
        )
    matrix = np.array(block.parameter_covariance.matrix, dtype=float).reshape(len(listed), -1)
    chain_rows = [i for i, n in enumerate(listed) if n in names]  # the tip's marginal block
    variance = np.zeros(6)
    if block.model_error is not None and model_error_applies(result):
        values = np.array(block.model_error.variance, dtype=float)
        variance[: values.size] = values
    built = PredictiveModel(
        chain,
        params,
        np.array([names.index(listed[i]) for i in chain_rows], dtype=np.intp),
        matrix[np.ix_(chain_rows, chain_rows)],
        variance,
        model_error_in_tip_frame=result.measurement is not None
        and result.measurement.frame.startswith(TIP_FRAME),
    )
    if model is not None:
        _PREDICTIVE[model] = built
    return built


PREDICTION_PARTS = ("total", "random_effects", "noise", "parameters", "model_error")
"""What ``kincal predict --part`` can write: the total predicted covariance, or one part."""


def predict_covariance_parts(
    result: CalibrationResult,
    joint_positions: FloatArray,
    payload_kg: FloatArray | None = None,
) -> dict[str, FloatArray]:
    """Every part of the predicted covariance (N, 6, 6), EE frame, [v; w], m/rad, keyed by
    :data:`PREDICTION_PARTS` without "total": Σ_E of the chain frames (Eq. 12), Σ_n, the
    parameter-estimation part J_θ Cov(θ̂) J_θᵀ and the model-error part (the last two zero
    when the result predates them: :data:`NO_PREDICTIVE`)."""
    model = uncertainty_model(result)
    q = corrections.true_configurations(result, model.chain, joint_positions, payload_kg)
    payload = payload_kg if payload_kg is not None else result.options.payload_kg
    random = ee_covariance(model, q, payload_kg=payload, include_noise=False)
    noise = np.broadcast_to(model.effects.noise_covariance, random.shape)
    parts = {"random_effects": random, "noise": np.array(noise)}
    extra = predictive_parts(result, model, q, payload)
    zeros = np.zeros_like(random)
    parts["parameters"] = zeros if extra is None else extra.parameters
    parts["model_error"] = zeros if extra is None else extra.model_error
    return parts


def predicted_covariance(
    result: CalibrationResult,
    joint_positions: FloatArray,
    payload_kg: FloatArray | None = None,
    *,
    part: str = "total",
    include_noise: bool = True,
) -> FloatArray:
    """One of :data:`PREDICTION_PARTS` at joint readings (N, k) rad, (N, 6, 6): "total" sums
    every part (Σ_n only with ``include_noise``), "random_effects" is Σ_E (+ Σ_n with
    ``include_noise``, Eq. 12)."""
    parts = predict_covariance_parts(result, joint_positions, payload_kg)
    noise = parts["noise"] if include_noise else 0.0
    if part == "total":
        return parts["random_effects"] + parts["parameters"] + parts["model_error"] + noise
    if part == "random_effects":
        return parts["random_effects"] + noise
    return parts[part]


def predictive_parts(
    result: CalibrationResult,
    model: UncertaintyModel,
    q: FloatArray,
    payload_kg: FloatArray | float,
) -> PredictiveParts | None:
    """The parameter-estimation and model-error parts at true configurations ``q`` (N, k);
    None when the result has no ``predictive`` block."""
    if result.predictive is None:
        return None
    return predictive_model(result, model).parts(q, model.loads(q, payload_kg))


def task_metric(options: RankingOptions) -> TaskMetric:
    """The task matrix M of Eq. (22) from the weights in the options."""
    weights = options.weights
    try:
        if isinstance(weights, PoseWeights):
            w = np.array(weights.matrix if weights.matrix is not None else weights.diagonal)
            return TaskMetric.pose_weights(
                w,
                rotation_scale_m_per_rad=weights.rotation_scale_m_per_rad,
                include_noise=options.include_noise,
            )
        return TaskMetric.task_point(
            weights.point_m, weights.axis_weights, include_noise=options.include_noise
        )
    except SolverError as exc:
        raise KincalError(f"weights: {exc}") from exc


def ignored_rotation_axis(weights: TaskWeights) -> tuple[float, float, float] | None:
    """End-effector axis whose rotation the task does not see (z preferred), or None.

    Pose weights: a rotation axis whose column of W is zero (e.g. yaw weight 0). Task point:
    an axis through the point (rotating about it leaves the point where it is).
    """
    if isinstance(weights, PoseWeights):
        w = np.array(weights.matrix if weights.matrix is not None else np.diag(weights.diagonal))
        ignored = [a for a in range(3) if not np.any(w[:, 3 + a])]
    else:
        p = np.array(weights.point_m)
        ignored = [a for a in range(3) if not np.any(np.cross(np.eye(3)[a], p))]
    if not ignored:
        return None
    return _AXES["xyz"[2 if 2 in ignored else ignored[0]]]


def calibration_reference(result: CalibrationResult) -> CalibrationReference:
    covariance = result.covariance
    return CalibrationReference(
        robot=result.robot.name,
        urdf_sha256=result.robot.urdf_sha256,
        created_utc=result.created_utc,
        kincal_version=result.kincal_version,
        result_sha256=hashlib.sha256(result.model_dump_json().encode()).hexdigest(),
        covariance_structure=covariance.structure if covariance else "none",
        covariance_estimator=covariance.estimator if covariance else "none",
    )


class NonFiniteScoreError(KincalError):
    """A ranked configuration's score or standard deviation is not a finite number (extreme
    inputs can overflow the covariance arithmetic); ``index`` is its input row."""

    def __init__(self, index: int) -> None:
        super().__init__(
            f"the predicted uncertainty of candidate {index} is not a finite number; check joint "
            "positions (rad), payload_kg and the weights for extreme values"
        )
        self.index = index


def rank_configurations(
    result: CalibrationResult,
    joint_positions: FloatArray,
    options: RankingOptions,
    *,
    payload_kg: FloatArray | float | None = None,
    model: UncertaintyModel | None = None,
    reference: CalibrationReference | None = None,
    require_finite: bool = False,
) -> RankingResult:
    """Score configurations (N, k) rad and order them best first (Eq. 22–23).

    ``payload_kg`` per configuration or scalar (default: the calibration's payload option).
    ``index`` in the output is the 0-based input row. ``model`` and ``reference`` (of
    :func:`uncertainty_model` and :func:`calibration_reference`) may be built once per result.
    ``require_finite``: raise :class:`NonFiniteScoreError` rather than rank a non-finite score.
    """
    document = _configurations_document(
        result, joint_positions, options, payload_kg, model, reference, require_finite
    )
    return RankingResult.model_validate(document)


def rank_configurations_json(
    result: CalibrationResult,
    joint_positions: FloatArray,
    options: RankingOptions,
    *,
    payload_kg: FloatArray | float | None = None,
    model: UncertaintyModel | None = None,
    reference: CalibrationReference | None = None,
    require_finite: bool = False,
) -> bytes:
    """:func:`rank_configurations` serialised: the same bytes as its ``model_dump_json()``,
    without building a pydantic model per entry (the planners' hot path: a hundred entry models
    cost several times the scoring itself)."""
    document = _configurations_document(
        result, joint_positions, options, payload_kg, model, reference, require_finite
    )
    return pydantic_core.to_json(document, inf_nan_mode="null")


def _configurations_document(
    result: CalibrationResult,
    joint_positions: FloatArray,
    options: RankingOptions,
    payload_kg: FloatArray | float | None,
    model: UncertaintyModel | None,
    reference: CalibrationReference | None,
    require_finite: bool,
) -> dict[str, Any]:
    model = model or uncertainty_model(result)
    q = _joint_array(joint_positions, model.chain)
    q = corrections.true_configurations(result, model.chain, q, payload_kg)
    metric = task_metric(options)
    payload = result.options.payload_kg if payload_kg is None else payload_kg
    try:
        scores = score_configurations(model, q, metric, payload_kg=payload)
    except SolverError as exc:
        raise KincalError(str(exc)) from exc
    scores, parts = _scored_uncertainty(result, model, metric, options, scores, q, payload)
    entries = _entries(scores, options.top, require_finite=require_finite, score_parts=parts)
    return _document(result, model, metric, options, scores, entries, reference)


def _scored_uncertainty(
    result: CalibrationResult,
    model: UncertaintyModel,
    metric: TaskMetric,
    options: RankingOptions,
    scores: ConfigurationScores,
    q: FloatArray,
    payload: FloatArray | float,
) -> tuple[ConfigurationScores, dict[str, FloatArray] | None]:
    """``options.uncertainty`` "total": the scores of Σ_E plus the parameter-estimation and
    model-error parts (and each part's score); "random_effects": ``scores`` as they are."""
    if options.uncertainty != "total":
        return scores, None
    extra = predictive_parts(result, model, q, payload)
    if extra is None:
        raise KincalError(f"uncertainty 'total': the calibration result {no_predictive(result)}")
    form = metric.quadratic_form
    parameters = np.einsum("ab,nab->n", form, extra.parameters)
    model_error = np.einsum("ab,nab->n", form, extra.model_error)
    added = extra.parameters + extra.model_error
    total = ConfigurationScores(
        scores.score + parameters + model_error,
        scores.ee_variance + np.diagonal(added, axis1=1, axis2=2),
    )
    parts = {"random_effects": scores.score, "parameters": parameters, "model_error": model_error}
    return total, parts


def rank_target(
    result: CalibrationResult,
    request: TargetRankingRequest,
    *,
    model: UncertaintyModel | None = None,
    reference: CalibrationReference | None = None,
    require_finite: bool = False,
) -> RankingResult:
    """Distinct IK solutions for the target pose (measurement frame, as ``kincal predict``
    reports poses), ranked. Each entry carries its joints and its IK pose error.
    ``require_finite`` as for :func:`rank_configurations`."""
    model = model or uncertainty_model(result)
    axis = _free_axis(request)
    target = lie.pose_matrix(
        np.array(request.target.position_m), np.array(request.target.quaternion_xyzw)
    )
    settings = IKOptions(
        n_candidates=request.n_candidates,
        seed=request.seed,
        free_axis=axis,
        n_free_rotations=request.n_free_rotations,
    )
    try:
        candidates = ik_candidates(
            model.chain,
            model.params,
            target,
            settings,
            gravity_base=model.gravity_base,
            payload_kg=request.payload_kg,
        )
    except SolverError as exc:
        raise KincalError(str(exc)) from exc
    metric = task_metric(request.options)
    q = np.array([c.joint_positions for c in candidates]).reshape(-1, model.chain.n_joints)
    scores = score_configurations(model, q, metric, payload_kg=request.payload_kg)
    scores, parts = _scored_uncertainty(
        result, model, metric, request.options, scores, q, request.payload_kg
    )
    entries = _entries(
        scores,
        request.options.top,
        require_finite=require_finite,
        score_parts=parts,
        # IK solved for where the robot stands; a controller is sent the raw readings
        joint_positions=corrections.raw_readings(result, model.chain, q, request.payload_kg),
        candidates=candidates,
    )
    document = _document(result, model, metric, request.options, scores, entries, reference)
    document |= {"target": request.target, "free_axis": axis}
    return RankingResult.model_validate(document)


def _free_axis(request: TargetRankingRequest) -> tuple[float, float, float] | None:
    if request.free_axis == "none":
        return None
    if request.free_axis == "auto":
        return ignored_rotation_axis(request.options.weights)
    return _AXES[request.free_axis]


def _joint_array(joint_positions: FloatArray, chain: KinematicChain) -> FloatArray:
    q = np.asarray(joint_positions, dtype=float)
    if q.ndim != 2 or q.shape[1] != chain.n_joints or q.shape[0] == 0:
        raise KincalError(
            f"configurations must be rows of {chain.n_joints} joint positions "
            f"({', '.join(chain.joint_names)}), got shape {q.shape}"
        )
    if not np.all(np.isfinite(q)):
        raise KincalError("configurations contain non-finite joint positions")
    return q


# Every field of an entry, in schema order, so that a plain dict serialises exactly like the
# model (None fields included, as ``model_dump_json`` writes them).
_ENTRY_DEFAULTS = {name: info.default for name, info in RankedConfiguration.model_fields.items()}


def _entries(
    scores: ConfigurationScores,
    top: int | None,
    *,
    require_finite: bool = False,
    joint_positions: FloatArray | None = None,
    candidates: Sequence[IKCandidate] = (),
    score_parts: dict[str, FloatArray] | None = None,
) -> list[dict[str, Any]]:
    """The ranked entries as plain dicts with every :class:`RankedConfiguration` field."""
    order = scores.order()[:top]
    std_array = np.sqrt(np.maximum(scores.ee_variance[order], 0.0))
    score_array = scores.score[order]
    if require_finite:
        finite = np.isfinite(score_array) & np.isfinite(std_array).all(axis=1)
        if not finite.all():
            raise NonFiniteScoreError(int(order[int(np.argmin(finite))]))
    std = std_array.tolist()
    trace_position = scores.trace_position_m2[order].tolist()
    trace_rotation = scores.trace_rotation_rad2[order].tolist()
    score = score_array.tolist()
    parts: list[dict[str, float] | None] = [None] * order.size
    if score_parts is not None:
        picked = {name: values[order].tolist() for name, values in score_parts.items()}
        parts = [{name: values[i] for name, values in picked.items()} for i in range(order.size)]
    if joint_positions is None and not candidates:
        # The hot path: a dict display per entry (several times faster than dict(zip(...))),
        # keys in schema order; tests check it serialises exactly like the model.
        return [
            {
                "rank": rank + 1,
                "index": i,
                "score": s,
                "trace_position_m2": p,
                "trace_rotation_rad2": r,
                "ee_std": e,
                "score_parts": sp,
                "joint_positions_rad": None,
                "free_rotation_rad": None,
                "ik_translation_error_m": None,
                "ik_rotation_error_rad": None,
                "ik_source": None,
            }
            for rank, (i, s, p, r, e, sp) in enumerate(
                zip(order.tolist(), score, trace_position, trace_rotation, std, parts, strict=True)
            )
        ]
    out = []
    for rank, i in enumerate(order.tolist()):
        entry = {
            **_ENTRY_DEFAULTS,
            "rank": rank + 1,
            "index": i,
            "score": score[rank],
            "trace_position_m2": trace_position[rank],
            "trace_rotation_rad2": trace_rotation[rank],
            "ee_std": std[rank],
            "score_parts": parts[rank],
        }
        if joint_positions is not None:
            entry["joint_positions_rad"] = joint_positions[i].tolist()
        if candidates:
            c = candidates[i]
            entry |= {
                "free_rotation_rad": c.free_rotation_rad,
                "ik_translation_error_m": c.translation_error_m,
                "ik_rotation_error_rad": c.rotation_error_rad,
                "ik_source": c.source,
            }
        out.append(entry)
    return out


def _document(
    result: CalibrationResult,
    model: UncertaintyModel,
    metric: TaskMetric,
    options: RankingOptions,
    scores: ConfigurationScores,
    entries: list[dict[str, Any]],
    reference: CalibrationReference | None = None,
) -> dict[str, Any]:
    """The ranking as the plain data of :class:`RankingResult`, fields in schema order: the
    head validated as a model (without entries), the entries added as dicts."""
    head = RankingResult(
        kincal_version=result_json.kincal_version(),
        calibration=reference or calibration_reference(result),
        joint_names=list(model.chain.joint_names),
        weights=options.weights,
        task_matrix=metric.matrix.tolist(),
        score_unit=metric.unit,
        include_noise=options.include_noise,
        uncertainty=options.uncertainty,
        n_configurations=int(scores.score.size),
        best_index=scores.best() if scores.score.size else None,
        ranking=[],
    )
    document = head.model_dump()
    document["ranking"] = entries
    return document
