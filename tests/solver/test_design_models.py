"""solver.design for every measurement model: the generic information of a model's own
Jacobian is today's pose/position information, nuisance parameters are profiled out (Schur
complement) consistently by value, gradient and Clarabel, and the predicted standard errors
of a design match the scatter of calibrations on simulated recordings at its poses."""

from __future__ import annotations

import functools

import numpy as np
import pytest

from schemas.robots import load_robot
from solver import lie
from solver.calibration import FitOptions
from solver.design import optimal_design
from solver.design.candidates import sample_candidates
from solver.design.criteria import DesignProblem
from solver.design.information import (
    geometry_information,
    ideal_rows,
    model_information,
    model_noise_std,
)
from solver.design.prediction import standard_errors
from solver.design.relaxation import solve_clarabel, solve_first_order
from solver.kinematics import ChainParameters, parameter_names
from solver.measurement.fit import fit_measurement
from solver.measurement.models import (
    FullPose,
    MeasurementModel,
    ModelParameters,
    MultiMarker,
    PoseComponents,
)
from solver.model import build_chain, gravity_loads

NOISE_M, NOISE_RAD = 5e-5, np.radians(0.003)
OFFSETS_M = np.array([[0.05, 0.0, 0.02], [-0.03, 0.04, 0.03], [0.0, -0.05, 0.06]])


@functools.cache
def kinova() -> tuple:
    robot = load_robot("kinova")
    chain = build_chain(robot.urdf_xml, robot.base_frame, robot.tip_frame)
    q = sample_candidates(chain, 40, np.random.default_rng(3))
    return chain, q, gravity_loads(chain, q)


def markers_params(chain) -> ModelParameters:
    nominal = ChainParameters.nominal(chain)
    return ModelParameters(nominal.links, nominal.compliance_rad_per_nm, OFFSETS_M.reshape(-1))


def test_pose_through_the_generic_path_is_todays_information() -> None:
    """(Position is not compared: the streamed position fit prunes columns by its own rule,
    which the service keeps using for --measurement position.)"""
    model = FullPose()
    chain, q, loads = kinova()
    noise = model_noise_std(model, NOISE_M, NOISE_RAD)
    params = ChainParameters.nominal(chain)
    today = geometry_information(chain, params, q, loads, noise)
    generic = model_information(
        chain, ModelParameters(params.links, params.compliance_rad_per_nm), model, q, loads, noise
    )
    assert generic.names == today.names and generic.nuisance == 0
    np.testing.assert_allclose(generic.scale, today.scale, rtol=1e-9)
    m_today, m_generic = today.information(), generic.information()
    np.testing.assert_allclose(m_generic, m_today, rtol=1e-9, atol=1e-9 * np.abs(m_today).max())
    index = np.arange(0, 40, 3)
    for criterion in ("D", "A"):
        a = DesignProblem((today,), criterion, index.size).set_value(index)
        b = DesignProblem((generic,), criterion, index.size).set_value(index)
        assert b == pytest.approx(a, rel=1e-9)


def markers_block():
    chain, q, loads = kinova()
    model = MultiMarker(3)
    noise = model_noise_std(model, NOISE_M, NOISE_RAD)
    return model_information(chain, markers_params(chain), model, q, loads, noise)


def test_markers_profile_out_their_offsets() -> None:
    """The profiled information is the inverse of the chain block of the full inverse, and
    the marker offsets are nuisance columns."""
    block = markers_block()
    assert block.nuisance == 9
    flat = block.factors.reshape(-1, block.columns)
    full = flat.T @ flat
    chain_cov = np.linalg.inv(full)[: block.dimension, : block.dimension]
    np.testing.assert_allclose(
        block.information(), np.linalg.inv(chain_cov), rtol=1e-6, atol=1e-8 * np.abs(full).max()
    )


@pytest.mark.parametrize("criterion", ["D", "A"])
def test_profiled_gradient_matches_finite_differences(criterion: str) -> None:
    block = markers_block()
    problem = DesignProblem((block,), criterion, 12, distinct=False)
    w = np.random.default_rng(1).dirichlet(np.ones(block.n_candidates))
    _, gradient = problem.value_and_gradient(w)
    step = 1e-6
    for n in (0, 7, 23):
        e = np.zeros_like(w)
        e[n] = step
        fd = (problem.value(w + e) - problem.value(w - e)) / (2 * step)
        assert gradient[n] == pytest.approx(fd, rel=1e-4, abs=1e-8)


@pytest.mark.parametrize("criterion", ["D"])
def test_profiled_relaxation_bounds_designs_and_solvers_agree(criterion: str) -> None:
    block = markers_block().subset(np.arange(16))
    problem = DesignProblem((block,), criterion, 8)
    clarabel = solve_clarabel(problem)
    if criterion != "E":
        first = solve_first_order(problem)
        assert first.value == pytest.approx(clarabel.value, rel=1e-4, abs=1e-4)
    q = kinova()[1][:16]
    design = optimal_design(problem, q, method="clarabel")
    assert design.value <= clarabel.upper_bound + 1e-9
    rng = np.random.default_rng(5)
    randoms = [problem.set_value(rng.choice(16, 8, replace=False)) for _ in range(20)]
    assert design.value >= max(randoms)


def _fit_deviation(chain, model, truth, fit) -> np.ndarray:
    """Estimated minus true chain parameters (local link twists, compliances)."""
    twists = [
        lie.se3_log(np.linalg.inv(a) @ b)
        for a, b in zip(truth.links, fit.params.links, strict=True)
    ]
    return np.concatenate(
        [np.ravel(twists), fit.params.compliance_rad_per_nm - truth.compliance_rad_per_nm]
    )


@pytest.mark.parametrize(
    "model", [MultiMarker(3), PoseComponents(("tz", "rx", "ry"))], ids=["markers", "plane"]
)
def test_predicted_standard_errors_match_simulated_calibrations(model: MeasurementModel) -> None:
    """Design K poses, calibrate 40 simulated recordings at them (noise σ), compare the
    scatter of the estimates with the standard errors the design predicts."""
    chain, q, loads = kinova()
    noise = model_noise_std(model, NOISE_M, NOISE_RAD)
    truth = (
        markers_params(chain)
        if isinstance(model, MultiMarker)
        else ModelParameters(
            ChainParameters.nominal(chain).links,
            ChainParameters.nominal(chain).compliance_rad_per_nm,
        )
    )
    options = FitOptions(
        rotation_weight_m_per_rad=NOISE_M / NOISE_RAD, non_negative_compliance=False
    )
    block = model_information(chain, truth, model, q, loads, noise, options=options)
    design = optimal_design(DesignProblem((block,), "D", 25), q, method="first_order")
    chosen = design.chosen
    predicted = standard_errors(block, block.information(chosen))[0]
    names = parameter_names(chain)
    columns = [names.index(n) for n in block.names]
    extra = list(range(len(names), len(names) + block.nuisance))
    rows = ideal_rows(model, chain, truth, q[chosen], loads[chosen])
    rng = np.random.default_rng(11)
    deviations = []
    for _ in range(40):
        if isinstance(model, MultiMarker):
            measured = rows.measured + rng.normal(size=rows.measured.shape) * NOISE_M
        else:
            twist = rng.normal(size=(chosen.size, 6)) * np.r_[[NOISE_M] * 3, [NOISE_RAD] * 3]
            measured = rows.measured @ lie.se3_exp(twist)
        noisy = type(rows).of(rows.joint_positions, rows.loads_nm, measured)
        fit = fit_measurement(chain, model, noisy, options, start=truth, columns=columns + extra)
        deviations.append(_fit_deviation(chain, model, truth, fit)[columns])
    empirical = np.std(deviations, axis=0)
    ratio = empirical / predicted
    # 40 draws: each ratio is known to ~11 %; their mean to a few %.
    assert np.mean(ratio) == pytest.approx(1.0, abs=0.1)
    assert np.all((ratio > 0.6) & (ratio < 1.4))
