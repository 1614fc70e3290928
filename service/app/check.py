"""``kincal check``: is a calibration still valid? A few new poses against its own predictive
uncertainty (issue 33): the ONE place the CLI (and later the HTTP service) call.

Result JSON + a check recording (the columns ``kincal calibrate`` reads) -> :class:`CheckResult`.
The total predictive covariance is the one ``kincal predict`` writes (:mod:`service.app.rank`);
the tests and the located change are :mod:`solver.check`'s.
"""

from __future__ import annotations

import datetime as dt
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from schemas.calibration import CalibrationResult, Verdict
from schemas.check import (
    DEFAULT_LEVEL,
    CandidateTest,
    ChangeComponent,
    CheckPose,
    CheckResult,
    GlobalTestResult,
    LocatedChange,
    StatedSize,
)
from schemas.dataset import PoseDataset
from service import kincal_version
from service.app import rank
from service.app.measurement_input import read_chain_dataset
from service.app.preflight import check_dataset
from service.render import corrections, result_json
from service.render.text import verdict_codes
from solver import check as checks
from solver import lie
from solver.arrays import FloatArray
from solver.errors import DatasetError, JointColumnsError, KincalError
from solver.ranking import ee_covariance
from solver.verdict import reach_m

RECALIBRATE_FIX = "re-run kincal calibrate with --covariance diag (the default) and --heldout"
"""How to get a result the check can take (the HTTP service words it for its options)."""

FAR_OFF_SHARE_OF_REACH = 0.1
"""Check poses whose median predicted-to-measured distance exceeds this share of the robot's
reach are not in the calibration's measurement frame (or of its marker): refused."""


@dataclass(frozen=True)
class CheckArrays:
    """A check recording against a calibration, as :mod:`solver.check` takes it: ``residuals``
    (n, d) end-effector frame (m, rad), ``covariance`` the joint predictive covariance
    (n·d, n·d) and the ``candidates`` at the check poses."""

    residuals: FloatArray
    covariance: FloatArray
    candidates: list[checks.Candidate]


def refuse_unsupported(result: CalibrationResult, result_name: str) -> None:
    """:class:`KincalError` when ``result`` lacks a part of the predictive covariance or was
    calibrated on a measurement type the check does not take yet."""
    if result.measurement is not None:
        raise KincalError(
            f"{result_name}: measurement '{result.measurement.type}': kincal check takes "
            "calibrations of pose and position recordings (measurement pose or position) for "
            "now; its residual is not the tip pose"
        )
    missing = []
    if result.covariance is None:
        missing.append("the random effects Σ_E and the noise Σ_n (covariance)")
    if result.predictive is None:
        missing.append("Cov(θ̂) and the model-error part (predictive)")
    if missing:
        raise KincalError(
            f"{result_name} has no {' nor '.join(missing)}: the check needs the total "
            f"predictive covariance; {RECALIBRATE_FIX}"
        )


def read_check_recording(
    source: str | Path | PoseDataset,
    result: CalibrationResult,
    result_name: str,
    name: str | None = None,
) -> PoseDataset:
    """The check recording (called ``name`` in messages and the document, default its path),
    read and checked like a calibration's (units, limits, repeated rows); :class:`KincalError`
    naming the mismatch when it is of another robot or another measurement type than the
    calibration."""
    chain, _ = result_json.result_chain(result)
    if isinstance(source, PoseDataset):
        dataset = source
    else:
        try:
            dataset = read_chain_dataset(source, chain, name=name)
        except JointColumnsError as exc:
            raise KincalError(
                f"check recording: not a recording of the calibrated robot "
                f"{result.robot.name} ({len(chain.joint_names)} joints "
                f"{', '.join(chain.joint_names)}): {exc}"
            ) from exc
        except DatasetError as exc:
            raise KincalError(f"check recording: {exc}") from exc
    check_dataset(dataset, chain)
    recorded = dataset.measurement_model
    calibrated = result_json.result_measurement(result)
    if recorded != calibrated:
        kinds = {"position": "positions only (x,y,z)", "pose": "full poses (x,y,z,qx,qy,qz,qw)"}
        raise KincalError(
            f"check recording {dataset.source}: holds {kinds[recorded.name]} but "
            f"{result_name} was calibrated on {kinds[calibrated.name]}; check with "
            "a recording of the same measurement type"
        )
    return dataset


@dataclass(frozen=True)
class PredictedParts:
    """The calibration's prediction at n configurations, as :mod:`solver.check` takes it:
    ``pose`` (n, 4, 4) the predicted tip poses (measurement frame), ``local`` (n, d, d) the
    parts of the predictive covariance independent between poses (Σ_E + Σ_n + model error),
    ``parameter_jacobian`` (n, d, p) and ``parameter_covariance`` Cov(θ̂) (p, p) its shared
    part, and the ``candidates`` at those configurations (end-effector frames, m and rad)."""

    pose: FloatArray
    local: FloatArray
    parameter_jacobian: FloatArray
    parameter_covariance: FloatArray
    candidates: list[checks.Candidate]

    def covariance(self) -> FloatArray:
        """The joint predictive covariance (n·d, n·d) (:func:`solver.check.joint_covariance`)."""
        return checks.joint_covariance(
            self.local, self.parameter_jacobian, self.parameter_covariance
        )


def predicted_parts(
    result: CalibrationResult, joint_positions: FloatArray, payload_kg: FloatArray | None, d: int
) -> PredictedParts:
    """:class:`PredictedParts` of ``result`` at ``joint_positions`` (n, k) read with payloads
    ``payload_kg`` (n,) kg (None: the calibration's), d = 6 (full pose) or 3 (position): the
    diagonal blocks of the joint covariance are
    :func:`service.app.rank.predicted_covariance`'s total (Σ_E + Σ_n + J_θ Cov(θ̂) J_θᵀ +
    model error), the off-diagonal ones the parameter part. ``kincal check`` and ``kincal
    design --check`` both come here."""
    model = rank.uncertainty_model(result)
    chain = model.chain
    payload = payload_kg if payload_kg is not None else result.options.payload_kg
    q = corrections.true_configurations(result, chain, joint_positions, payload)
    predictive = rank.predictive_model(result, model)
    point = predictive.point(q, model.loads(q, payload))
    local = ee_covariance(model, q, payload_kg=payload, include_noise=True)
    local = local + predictive.model_error(point)
    return PredictedParts(
        point.pose,
        local[:, :d, :d],
        point.parameter_jacobian[:, :d],
        predictive.parameter_covariance,
        checks.candidates_at(chain, point.frame_jacobians[:, :, :d], q),
    )


def check_arrays(result: CalibrationResult, dataset: PoseDataset) -> CheckArrays:
    """Residuals, joint predictive covariance and candidates of ``dataset``'s poses under
    ``result`` (:func:`predicted_parts`)."""
    measurement = dataset.measurement_model
    parts = predicted_parts(result, dataset.joint_positions, dataset.payload_kg, measurement.dim)
    measured = lie.pose_matrix(dataset.position_m, dataset.quaternion_xyzw)
    residuals = measurement.residuals(parts.pose, measured)
    return CheckArrays(residuals, parts.covariance(), parts.candidates)


def refuse_other_frames(
    residuals: FloatArray, result: CalibrationResult, dataset: PoseDataset
) -> None:
    """:class:`KincalError` when the check poses are, at the median, further from their
    predictions than :data:`FAR_OFF_SHARE_OF_REACH` of the reach: another measurement frame
    or another marker or tool, not a drift."""
    chain, _ = result_json.result_chain(result)
    reach = reach_m(chain.nominal_links[:, :3, 3])
    median_m = float(np.median(np.linalg.norm(residuals[:, :3], axis=1)))
    if reach > 0.0 and median_m > FAR_OFF_SHARE_OF_REACH * reach:
        raise KincalError(
            f"check recording {dataset.source}: its poses are {median_m * 1000:.0f} mm (median) "
            f"from the calibration's predictions, {median_m / reach:.0%} of the robot's reach: "
            "not in the calibration's measurement frame or not of its marker/tool; record the "
            "check in the same frames as the calibration"
        )


def advice(
    tests: checks.PoseTests, located: checks.LocatedDrift | None, calibration: Verdict | None
) -> str:
    """What to do next, in one line; a calibration that failed its own tests is recalibrated
    first, whatever the check says (a drift cannot be told from its misfit)."""
    bad = ", ".join(str(i + 1) for i in tests.bad_samples)
    remeasure = f"re-measure pose(s) {bad}; " if bad else ""
    if calibration is not None and calibration.status == "failed":
        return (
            f"{remeasure}recalibrate (kincal calibrate, following its verdict's fixes): the "
            f"calibration checked failed its own tests ({verdict_codes(calibration)}), so its "
            "predictions are no yardstick and this check cannot tell a drift from its misfit"
        )
    if tests.verdict == "inconclusive":
        return f"{remeasure}record at least {checks.MIN_POSES} check poses"
    if tests.verdict == "holds":
        return f"{remeasure}keep using the calibration" if bad else "keep using the calibration"
    best = located.best if located is not None else None
    if best is None:
        return (
            f"{remeasure}record a new calibration recording and recalibrate everything "
            "(kincal calibrate); no single candidate change explains the drift"
        )
    kind = best.candidate.kind
    free = {
        "joint_offset": "--free joint_offsets",
        "base": "--free base",
        "tool": "--free tool",
        "link": "--free geometry",
    }
    if kind == "joint_scale":
        return (
            f"{remeasure}{best.candidate.name}: kincal models no joint scale; check that "
            "joint's encoder and transmission, then recalibrate"
        )
    return (
        f"{remeasure}record a new calibration recording and recalibrate {best.candidate.name} "
        f"(kincal calibrate RECORDING {free[kind]})"
    )


def _candidate_test(test: checks.ScoreTest) -> CandidateTest:
    return CandidateTest(
        name=test.candidate.name,
        kind=test.candidate.kind,  # type: ignore[arg-type]
        statistic=test.statistic,
        dof=test.dof,
        p_value=test.p_value,
        adjusted_p_value=test.adjusted,
    )


def located_change(located: checks.LocatedDrift) -> LocatedChange | None:
    """The best candidate of ``located`` with its sizes and 95 % intervals (SI units)."""
    best = located.best
    if best is None:
        return None
    low, high = best.interval95()
    candidate = best.candidate
    components = [
        ChangeComponent(
            name=name,
            value=float(best.estimate[i]),
            low95=float(low[i]),
            high95=float(high[i]),
            unit=candidate.units[i],
        )
        for i, name in enumerate(candidate.components)
    ]
    return LocatedChange(
        name=candidate.name,
        kind=candidate.kind,  # type: ignore[arg-type]
        components=components,
        adjusted_p_value=best.adjusted,
        indistinguishable_from=[t.candidate.name for t in located.alternatives],
    )


def run_check(
    result: CalibrationResult,
    source: str | Path | PoseDataset,
    *,
    level: float = DEFAULT_LEVEL,
    result_name: str = "the calibration result",
    source_name: str | None = None,
) -> CheckResult:
    """Check ``result`` against the poses of ``source`` (called ``source_name`` in messages
    and the document, default its path) at family-wise ``level``."""
    if not 0.0 < level < 1.0:
        raise KincalError(f"--level {level}: give a probability between 0 and 1, e.g. 0.05")
    refuse_unsupported(result, result_name)
    dataset = read_check_recording(source, result, result_name, source_name)
    arrays = check_arrays(result, dataset)
    refuse_other_frames(arrays.residuals, result, dataset)
    model = checks.DriftModel.build(arrays.covariance, arrays.candidates, level)
    tests = checks.pose_verdict(arrays.residuals, model, level)
    used = tests.used
    d = arrays.residuals.shape[1]
    drift = tests.drift
    sizes = [] if tests.model is None else checks.stated_sizes(tests.model)
    located = drift.located if drift is not None and tests.verdict == "drifted" else None
    scored = drift.located.tests if drift is not None else ()
    return CheckResult(
        kincal_version=kincal_version(),
        created_utc=dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
        calibration=rank.calibration_reference(result),
        recording=dataset.source,
        dimension=d,
        level=level,
        global_critical_p=None if drift is None else drift.global_p,
        candidate_critical_p=None if drift is None else drift.candidate_p,
        verdict=tests.verdict,  # type: ignore[arg-type]
        reason=tests.reason,
        advice=advice(tests, located, result.verdict),
        calibration_verdict=result.verdict,
        max_threshold=tests.threshold if np.isfinite(tests.threshold) else None,
        poses=_poses(arrays.residuals, tests, dataset),
        global_test=None
        if drift is None
        else GlobalTestResult(
            statistic=drift.global_test.statistic,
            dof=drift.global_test.dof,
            threshold=drift.global_test.threshold,
            p_value=drift.global_test.p_value,
            n_poses=int(used.size),
        ),
        located=None if located is None else located_change(located),
        candidates=[_candidate_test(t) for t in scored],
        power=checks.POWER,
        stated_sizes=[stated_size(s) for s in sizes],
    )


def stated_size(size: checks.StatedSize) -> StatedSize:
    """A stated size as the document holds it (null where no size moves the poses)."""
    return StatedSize(
        name=size.name,
        size=size.size if np.isfinite(size.size) else None,
        unit=size.unit,
        located=size.located,
    )


def stated_sizes_at(
    result: CalibrationResult, joint_positions: FloatArray, level: float, d: int
) -> list[checks.StatedSize]:
    """The sizes :func:`run_check` states for check poses at ``joint_positions`` (n, k) when
    none is set aside (they depend on the configurations, not the measurements)."""
    parts = predicted_parts(result, joint_positions, None, d)
    model = checks.DriftModel.build(parts.covariance(), parts.candidates, level)
    return checks.stated_sizes(model)


def _poses(residuals: FloatArray, tests: checks.PoseTests, dataset: PoseDataset) -> list[CheckPose]:
    bad = set(tests.bad_samples.tolist())
    ids = dataset.sample_id
    rotation = (
        np.linalg.norm(residuals[:, 3:], axis=1) * 1000.0 if residuals.shape[1] == 6 else None
    )
    return [
        CheckPose(
            index=i + 1,
            sample_id=None if ids is None else str(ids[i]),
            d2=float(tests.d2[i]),
            translation_mm=float(np.linalg.norm(residuals[i, :3]) * 1000.0),
            rotation_mrad=None if rotation is None else float(rotation[i]),
            bad_sample=i in bad,
        )
        for i in range(residuals.shape[0])
    ]
