"""Streamed calibration (issue 7): chunking, executors and merging change nothing but speed."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from solver import lie
from solver.calibration import (
    FitOptions,
    NormalEquations,
    ResidualSpread,
    normal_equations,
    outlier_mask,
)
from solver.covariance.estimate import estimate_covariances
from solver.covariance.layout import make_layout
from solver.covariance.statistics import build_moment_statistics
from solver.executors import InProcessExecutor, blocks, make_executor
from solver.gravity import StaticGravityModel, static_gravity_loads
from solver.kinematics import evaluate_chain, parameter_names
from solver.measurement import FullPose, Position
from solver.measurement.pose import fit_deterministic, pose_measurement
from solver.simulate import SimulatedRecording, SimulationSpec, look_at, simulate_recording
from solver.stream.calibrate import (
    CovarianceSettings,
    StreamedCalibration,
    StreamSettings,
    calibrate_streamed_fits,
    covariance_stage,
)
from solver.stream.chunks import ArrayChunks, StreamProblem, release, row_ranges
from solver.stream.covariance import streamed_covariance_sums
from solver.stream.fit import PassCount, streamed_fit_sums
from solver.stream.sums import CovarianceSpec, covariance_spec
from tests.conftest import chain

REL = 1e-10
ROBOT = "kinova"
FULL = FitOptions()


def _baseline_options() -> FitOptions:
    return FitOptions(free_links=(0, chain(ROBOT).n_links - 1), fit_compliance=False)


def _recording(n: int, seed: int) -> SimulatedRecording:
    c = chain(ROBOT)
    spec = SimulationSpec(
        n_samples=n,
        seed=seed,
        compliance_rad_per_nm={c.compliance_axes[1].name: 5e-4, c.compliance_axes[2].name: 8e-4},
        perturbation_sigma=np.full((c.n_joints, 6), 1e-4),
        noise_sigma=np.array([5e-5] * 3 + [1e-4] * 3),
        measurement_frame=look_at(np.array([0.8, -0.5, 0.45]), np.array([0.0, 0.0, 0.3])),
        outlier_fraction=0.02,
    )
    return simulate_recording(c, spec)


def _problem(rec: SimulatedRecording, chunk_rows: int, block_rows: int) -> StreamProblem:
    pose = rec.measured_pose
    source = ArrayChunks(
        rec.joint_positions, pose[:, :3, 3], lie.matrix_to_quaternion_xyzw(pose[:, :3, :3])
    )
    n = rec.joint_positions.shape[0]
    return StreamProblem(
        chain(ROBOT),
        source,
        row_ranges(n, chunk_rows),
        measurement=FullPose(),
        block_rows=block_rows,
    )


def _close(a: np.ndarray, b: np.ndarray, rel: float = REL) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and float(np.abs(a - b).max()) <= rel * float(np.abs(b).max())


def _fit_vector(cal: StreamedCalibration) -> np.ndarray:
    parts = []
    for fit in (cal.first, cal.fit, cal.baseline):
        assert fit is not None  # the 2σ rule's first fit
        parts += [fit.params.links.ravel(), fit.params.compliance_rad_per_nm, fit.standard_errors]
    return np.concatenate(parts)


def _spec(problem: StreamProblem) -> CovarianceSpec:
    c = chain(ROBOT)
    return covariance_spec(problem.residual_dim, c.joint_names, range(c.n_joints))


def _run(problem: StreamProblem, executor, warm_rows: int):  # type: ignore[no-untyped-def]
    spec = _spec(problem)
    cal = calibrate_streamed_fits(
        problem,
        executor,
        FULL,
        _baseline_options(),
        StreamSettings(warm_start_rows=warm_rows, outlier_rule="sigma"),
        covariance=spec,
    )
    # nnls (active set): the answer moves with G and h only by rounding; the samples streamed
    cov = covariance_stage(
        problem,
        executor,
        cal,
        CovarianceSettings(spec, "moment", "nnls"),
        PassCount(),
        in_memory_samples=0,
    )
    release(problem, executor)
    return cal, cov


@pytest.fixture(scope="module")
def recording() -> SimulatedRecording:
    return _recording(2400, seed=5)


@pytest.fixture(scope="module")
def unchunked(recording: SimulatedRecording):  # type: ignore[no-untyped-def]
    n = recording.joint_positions.shape[0]
    return _run(_problem(recording, n, n), InProcessExecutor(), warm_rows=800)


def test_chunked_equals_unchunked(recording: SimulatedRecording, unchunked) -> None:  # type: ignore[no-untyped-def]
    """Chunks of 500 rows in blocks of 128 vs one block of everything, warm start on 800 rows
    (so the streamed iterations do real work): same fits, outliers and covariances."""
    cal, cov = _run(_problem(recording, 500, 128), InProcessExecutor(), warm_rows=800)
    ref_cal, ref_cov = unchunked
    assert cal.first is not None and cal.first.iterations >= 1 and cal.first.passes >= 2
    assert np.array_equal(cal.removed_rows, ref_cal.removed_rows)
    assert 0 < cal.removed_rows.size < 0.5 * cal.n_rows
    assert _close(_fit_vector(cal), _fit_vector(ref_cal))
    assert cal.fit.cost_history[-1] == pytest.approx(ref_cal.fit.cost_history[-1], rel=REL)
    assert _close(cov.theta, ref_cov.theta)
    assert _close(cov.statistics.gram, ref_cov.statistics.gram)


def test_streamed_equals_the_in_memory_fit_and_covariances(recording: SimulatedRecording) -> None:
    """With every row in the warm start the streamed pipeline is the in-memory one: first fit,
    2σ rule, refit on the kept rows, moment-matching covariances (Eq. 13-14)."""
    c = chain(ROBOT)
    cal, cov = _run(_problem(recording, 700, 256), InProcessExecutor(), warm_rows=10_000)
    q, pose = recording.joint_positions, recording.measured_pose
    quaternion = lie.matrix_to_quaternion_xyzw(pose[:, :3, :3])
    measured = lie.pose_matrix(pose[:, :3, 3], quaternion)
    loads = static_gravity_loads(StaticGravityModel.from_chain(c), q)
    first = fit_deterministic(c, q, measured, loads, measurement=FullPose())
    used = np.flatnonzero(outlier_mask(first.residuals, 2.0))
    fit = fit_deterministic(c, q[used], measured[used], loads[used], measurement=FullPose())
    assert np.array_equal(cal.removed_rows, np.setdiff1d(np.arange(q.shape[0]), used))
    assert cal.fit.estimated == fit.estimated
    assert _close(cal.fit.params.links, fit.params.links)
    assert _close(cal.fit.params.compliance_rad_per_nm, fit.params.compliance_rad_per_nm)
    assert _close(cal.fit.standard_errors, fit.standard_errors)
    jacobians = evaluate_chain(c, cal.fit.params, q[used], loads[used]).link_jacobians[:, :-1]
    residuals = fit.residuals
    memory = estimate_covariances(
        residuals, jacobians, c.joint_names, estimator="moment", solver="nnls"
    )
    assert _close(cov.statistics.gram, memory.statistics.gram)
    assert _close(cov.statistics.cross, memory.statistics.cross)
    assert _close(cov.theta, memory.theta)
    # pseudo-inverse on the identifiable subspace (rcond 1e-13): rounding shows at ~1e-7
    assert _close(cov.theta_covariance, memory.theta_covariance, 1e-6)
    assert cov.estimator == "moment" and cov.n_samples == used.size


@pytest.mark.parametrize("estimator", ["ml", "reml"])
def test_likelihood_estimates_stream_like_in_memory(
    recording: SimulatedRecording, estimator: str
) -> None:
    """Issue 17: ML and REML over streamed passes (every NLL evaluation a pass over the
    chunks, the fit basis from merged R factors) equal the same estimators on the samples
    gathered into memory."""
    problem = _problem(recording, 600, 256)
    executor = InProcessExecutor()
    spec = _spec(problem)
    cal = calibrate_streamed_fits(
        problem, executor, FULL, _baseline_options(), StreamSettings(800), covariance=spec
    )
    settings = CovarianceSettings(spec, estimator, "nnls")  # type: ignore[arg-type]
    count = PassCount()
    streamed = covariance_stage(problem, executor, cal, settings, count, in_memory_samples=0)
    passes = count.passes
    memory = covariance_stage(problem, executor, cal, settings, PassCount())
    release(problem, executor)
    assert streamed.solution.status == memory.solution.status == "optimal"
    assert streamed.solution.iterations == memory.solution.iterations
    assert passes > streamed.solution.iterations  # each evaluation was a pass
    assert _close(streamed.theta, memory.theta, 1e-8)
    assert streamed.theta_covariance is not None and memory.theta_covariance is not None
    assert _close(streamed.theta_covariance, memory.theta_covariance, 1e-6)


@pytest.mark.parametrize(
    "kind, kwargs",
    [("processes", {"n_workers": 2}), ("dask", {"n_workers": 2, "dask_processes": False})],
)
def test_every_backend_gives_the_in_process_numbers(
    recording: SimulatedRecording,
    unchunked,  # type: ignore[no-untyped-def]
    kind: str,
    kwargs: dict[str, object],
) -> None:
    problem = _problem(recording, 400, 512)
    reference = _run(problem, InProcessExecutor(), warm_rows=800)
    with make_executor(kind, **kwargs) as executor:  # type: ignore[arg-type]
        cal, cov = _run(problem, executor, warm_rows=800)
    assert _close(_fit_vector(cal), _fit_vector(reference[0]))
    assert np.array_equal(cal.removed_rows, reference[0].removed_rows)
    assert _close(cov.theta, reference[1].theta)


def test_statistics_of_two_recordings_merge_to_those_of_their_union() -> None:
    """Normal equations, residual spread and covariance statistics of recording A plus those
    of recording B equal those of A and B concatenated (and the in-memory ones)."""
    c = chain(ROBOT)
    a, b = _recording(700, seed=21), _recording(500, seed=22)
    union = SimulatedRecording(
        **{
            **a.__dict__,
            "joint_positions": np.concatenate([a.joint_positions, b.joint_positions]),
            "measured_pose": np.concatenate([a.measured_pose, b.measured_pose]),
        }
    )
    params = a.true_params
    keep = np.arange(len(parameter_names(c)))
    executor = InProcessExecutor()
    layout = make_layout(c.joint_names, 6, structure="diag")
    fit_sums, cov_sums = [], []
    for rec in (a, b, union):
        problem = _problem(rec, 300, 128)
        fit_sums.append(streamed_fit_sums(problem, executor, params, keep, FULL))
        spec = CovarianceSpec(tuple(range(c.n_joints)), layout)
        cov_sums.append(streamed_covariance_sums(problem, executor, params, spec))
        release(problem, executor)
    merged, whole = fit_sums[0] + fit_sums[1], fit_sums[2]
    assert _close(merged.normal.gram, whole.normal.gram)
    assert _close(merged.normal.cross, whole.normal.cross)
    assert merged.normal.cost == pytest.approx(whole.normal.cost, rel=REL)
    assert merged.spread.n == whole.spread.n == 1200
    assert _close(merged.spread.mean, whole.spread.mean) and _close(
        merged.spread.m2, whole.spread.m2
    )
    stats, stats_whole = cov_sums[0].stats + cov_sums[1].stats, cov_sums[2].stats
    assert stats is not None and stats_whole is not None
    assert _close(stats.gram, stats_whole.gram) and _close(stats.cross, stats_whole.cross)
    # ... and the in-memory statistics of the union
    q, pose = union.joint_positions, union.measured_pose
    loads = static_gravity_loads(StaticGravityModel.from_chain(c), q)
    evaluation = evaluate_chain(c, params, q, loads)
    from solver.kinematics import pose_residuals

    residuals = pose_residuals(evaluation.pose, pose)
    memory = build_moment_statistics(residuals, evaluation.link_jacobians[:, :-1], layout)
    assert _close(stats.gram, memory.gram, 1e-9) and _close(stats.cross, memory.cross, 1e-9)
    spread = ResidualSpread.of(residuals)
    assert _close(merged.spread.mean, spread.mean, 1e-9)
    assert _close(merged.spread.m2, spread.m2, 1e-9)


def test_merged_normal_equations_and_spread_are_exact_sums() -> None:
    rng = np.random.default_rng(3)
    design, target = rng.normal(size=(50, 4)), rng.normal(size=50)
    whole = normal_equations(design, target)
    parts: NormalEquations = normal_equations(design[:20], target[:20]) + normal_equations(
        design[20:], target[20:]
    )
    assert _close(parts.gram, whole.gram, 1e-14) and parts.n_rows == 50
    values = rng.normal(loc=3.0, size=(40, 6))
    merged = ResidualSpread.of(values[:7]) + ResidualSpread.of(values[7:])
    assert _close(merged.std, values.std(axis=0), 1e-13)
    assert _close(merged.mean, values.mean(axis=0), 1e-14)


def test_blocks_cover_items_once_in_order() -> None:
    for n in range(12):
        for workers in (1, 2, 5):
            ranges = blocks(n, workers)
            assert len(ranges) == workers
            assert [i for r in ranges for i in r] == list(range(n))


def test_without_the_chunk_cache_the_numbers_are_the_same(
    recording: SimulatedRecording,
    unchunked,  # type: ignore[no-untyped-def]
) -> None:
    """cache_bytes=0 re-reads every chunk on every pass (memory independent of N)."""
    problem = dataclasses.replace(_problem(recording, 500, 128), cache_bytes=0)
    cal, cov = _run(problem, InProcessExecutor(), warm_rows=800)
    ref_cal, ref_cov = unchunked
    assert np.array_equal(cal.removed_rows, ref_cal.removed_rows)
    assert _close(_fit_vector(cal), _fit_vector(ref_cal))
    assert _close(cov.theta, ref_cov.theta)


def _problem_of(rec: SimulatedRecording, *, rotation: bool) -> StreamProblem:
    pose = rec.measured_pose
    quaternion = lie.matrix_to_quaternion_xyzw(pose[:, :3, :3]) if rotation else None
    source = ArrayChunks(rec.joint_positions, pose[:, :3, 3], quaternion)
    rows = row_ranges(rec.joint_positions.shape[0], 300)
    return StreamProblem(
        chain(ROBOT),
        source,
        rows,
        measurement=pose_measurement(rotation=rotation),
        block_rows=128,
    )


@pytest.mark.parametrize(
    "rotation, options",
    [(False, FULL), (True, FitOptions(rotation_weight_m_per_rad=0.3))],
    ids=["position-only", "rotation-weight"],
)
def test_streamed_fit_equals_in_memory_for_positions_and_weighted_rotation(
    recording: SimulatedRecording, rotation: bool, options: FitOptions
) -> None:
    """The structured normal equations (band Gram, unit tip columns, row weights) give the
    in-memory fits; the covariance statistics are the in-memory ones."""
    c = chain(ROBOT)
    problem = _problem_of(recording, rotation=rotation)
    spec = covariance_spec(problem.residual_dim, c.joint_names, range(c.n_joints))
    executor = InProcessExecutor()
    cal = calibrate_streamed_fits(
        problem,
        executor,
        options,
        _baseline_options(),
        StreamSettings(outlier_rule="sigma"),
        covariance=spec,
    )
    sums = cal.covariance or streamed_covariance_sums(
        problem, executor, cal.fit.params, spec, cal.rule
    )
    release(problem, executor)
    q, pose = recording.joint_positions, recording.measured_pose
    quaternion = lie.matrix_to_quaternion_xyzw(pose[:, :3, :3]) if rotation else None
    measured = lie.pose_matrix(pose[:, :3, 3], quaternion)
    loads = static_gravity_loads(StaticGravityModel.from_chain(c), q)
    first = fit_deterministic(
        c,
        q,
        measured,
        loads,
        measurement=FullPose() if rotation else Position(),
        options=options,
    )
    used = np.flatnonzero(outlier_mask(first.residuals, 2.0))
    fit = fit_deterministic(
        c,
        q[used],
        measured[used],
        loads[used],
        measurement=FullPose() if rotation else Position(),
        options=options,
    )
    assert cal.fit.estimated == fit.estimated
    assert _close(cal.fit.params.links, fit.params.links)
    assert _close(cal.fit.params.compliance_rad_per_nm, fit.params.compliance_rad_per_nm)
    # the streamed path inverts the normal equations, the in-memory one a QR factor: the
    # largest standard error (9 mrad, j2s6s200_joint_5.rz, position-only) carries rounding of
    # relative size κ²·eps, 1.3e-10 here
    assert _close(cal.fit.standard_errors, fit.standard_errors, 1e-9)
    assert np.array_equal(cal.removed_rows, np.setdiff1d(np.arange(q.shape[0]), used))
    d = 6 if rotation else 3
    evaluation = evaluate_chain(c, cal.fit.params, q[used], loads[used])
    layout = make_layout(c.joint_names, d)
    memory = build_moment_statistics(fit.residuals, evaluation.link_jacobians[:, :-1, :d], layout)
    assert sums.stats is not None
    assert _close(sums.stats.gram, memory.gram, 1e-9)
    assert _close(sums.stats.cross, memory.cross, 1e-9)


@pytest.mark.parametrize(
    "structure, known, rotation",
    [
        ("diag", False, True),
        ("diag", True, True),
        ("full", False, True),
        ("full", True, True),
        ("diag", False, False),
    ],
)
def test_statistics_taken_along_the_fit_equal_a_pass_of_their_own(
    recording: SimulatedRecording, structure: str, known: bool, rotation: bool
) -> None:
    """The refit's last pass takes the covariance statistics along (no pass of their own);
    they equal the statistics pass at the same point, for diagonal and full Σ, with and
    without a known noise covariance, pose or position-only; so do the Jacobian ranges."""
    c = chain(ROBOT)
    problem = _problem_of(recording, rotation=rotation)
    noise = np.diag([4e-9] * 3 + [1e-8] * 3) if known else None
    spec = covariance_spec(
        problem.residual_dim,
        c.joint_names,
        range(c.n_joints),
        structure=structure,
        noise_covariance=noise,
    )
    executor = InProcessExecutor()
    cal = calibrate_streamed_fits(
        problem, executor, FULL, _baseline_options(), StreamSettings(800), covariance=spec
    )
    assert cal.covariance is not None
    alone = streamed_covariance_sums(problem, executor, cal.fit.params, spec, cal.rule)
    release(problem, executor)
    along = cal.covariance
    assert along.stats is not None and alone.stats is not None
    assert along.n == alone.n == cal.fit.sums.errors.n
    assert _close(along.stats.gram, alone.stats.gram, 1e-12)
    assert _close(along.stats.cross, alone.stats.cross, 1e-12)
    assert along.stats.const == pytest.approx(alone.stats.const, rel=1e-12)
    for got, want in [
        (along.jacobians.total, alone.jacobians.total),
        (along.jacobians.low, alone.jacobians.low),
        (along.jacobians.high, alone.jacobians.high),
    ]:
        assert _close(got, want, 1e-12)
