"""benchmarks/model_selection.py: the prior rows, the GCV score, the limits of the prior's
weight (the table's TIAGo rows are re-run by tests/test_quoted_numbers.py)."""

from __future__ import annotations

import dataclasses
from functools import cache

import numpy as np
import pytest

from benchmarks import model_selection as selection
from solver import lie
from solver.calibration import FitOptions
from solver.evaluation import split_indices
from solver.measurement.fit import fit_measurement
from solver.measurement.models import MeasurementRows, ModelParameters, Position
from solver.model import KinematicChain


@cache
def tiago() -> tuple[KinematicChain, MeasurementRows]:
    (recording,) = [r for r in selection.RECORDINGS if r.name == "TIAGo"]
    chain, rows, measurement = selection.load_rows(recording)
    assert not measurement.measures_rotation
    return chain, rows


def training_rows() -> MeasurementRows:
    _, rows = tiago()
    train, _ = split_indices(rows.n, 1, 0.9)
    return rows.take(train)


def test_prior_rows_are_minus_their_jacobian_times_a_small_step_from_nominal() -> None:
    chain, _ = tiago()
    weights = np.array([2.0, 2.0, 2.0, 3.0, 3.0, 3.0])
    model = selection.toward_nominal(Position(), weights)
    nominal = ModelParameters(np.array(chain.nominal_links), np.zeros(len(chain.compliance_axes)))
    residual, design = model.constraints(chain, nominal)
    assert np.allclose(residual, 0.0)
    step = np.zeros(design.shape[1])
    step[6 * 2 : 6 * 2 + 6] = 1e-6 * np.arange(1, 7)
    links = nominal.links.copy()
    links[2] = links[2] @ lie.se3_exp(step[12:18])
    moved, _ = model.constraints(chain, dataclasses.replace(nominal, links=links))
    assert np.allclose(moved, -design @ step, rtol=1e-6, atol=1e-15)


def test_zero_prior_weight_is_todays_fit_and_a_huge_one_keeps_the_urdf() -> None:
    chain, _ = tiago()
    train = training_rows()
    options = FitOptions(fit_compliance=False)
    today = fit_measurement(chain, Position(), train, options)
    keep = selection.data_columns(chain, Position(), train, options)
    free = fit_measurement(
        chain, selection.toward_nominal(Position(), np.zeros(6)), train, options, columns=keep
    )
    assert free.estimated == today.estimated
    assert np.allclose(free.params.links, today.params.links, atol=1e-9)
    stiff = fit_measurement(
        chain, selection.toward_nominal(Position(), np.full(6, 1e6)), train, options, columns=keep
    )
    assert selection.largest_inner_rotation_rad(chain, stiff.params) < 1e-6
    inner = np.array(stiff.params.links[1:-1])
    assert np.allclose(inner[:, :3, 3], np.array(chain.nominal_links[1:-1])[:, :3, 3], atol=1e-6)


def test_gcv_trace_is_the_hat_matrix_trace_of_the_penalised_step() -> None:
    """GCV's ``tr H`` against an explicit hat matrix ``A (AᵀA + PᵀP)⁻¹ Aᵀ``: with the prior
    rows it is below the number of fitted columns, and the score equals the formula."""
    chain, _ = tiago()
    train = training_rows()
    options = FitOptions(fit_compliance=False)
    keep = selection.data_columns(chain, Position(), train, options)
    model = selection.toward_nominal(Position(), np.full(6, 0.3))
    fit = fit_measurement(chain, model, train, options, columns=keep)
    design = fit.jacobian.reshape(-1, keep.size)
    _, prior = model.constraints(chain, fit.params)
    hat = design @ np.linalg.solve(design.T @ design + prior[:, keep].T @ prior[:, keep], design.T)
    m = design.shape[0]
    expected = float(np.sum(fit.residuals**2)) / m / (1.0 - np.trace(hat) / m) ** 2
    assert np.trace(hat) < keep.size - 0.5
    assert selection.gcv_score(chain, model, fit, options) == pytest.approx(expected, rel=1e-8)


def test_table_says_mean_standard_error_and_the_acceptance_for_the_fixed_compliance_model() -> None:
    rows = [
        {
            "method": "ridge-gcv",
            "robot": "TIAGo",
            "model": "--fix compliance",
            "heldout_mm": [6.9, 7.0, 7.1],
            "largest_inner_rotation_rad": 0.1,
        },
        {
            "method": "today",
            "robot": "TALOS",
            "model": "default",
            "heldout_mm": [0.5, 0.6, 0.7],
            "largest_inner_rotation_rad": 0.03,
        },
    ]
    text = selection.render(rows)
    assert (
        "| ridge-gcv | TIAGo | `--fix compliance` | 7.000 ± 0.058 | 0.100 | 6.85 ± 0.35 | yes |"
        in text
    )
    assert text.endswith("| today | TALOS | default | 0.600 ± 0.058 | 0.030 | 0.56 ± 0.04 | – |")
