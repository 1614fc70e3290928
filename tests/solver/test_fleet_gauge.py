"""solver.fleet_gauge: the common gauge of a fleet's link corrections (issue 31)."""

from __future__ import annotations

import numpy as np
import pytest

from solver.fleet_gauge import UnitInformation, common_gauge, common_gauge_values

N_COMPARED = 5


def _unit(
    rng: np.random.Generator,
    theta: np.ndarray,
    held: list[int],
    *,
    n_rows: int = 400,
    noise: np.ndarray | None = None,
    slope: float = 2.0,
) -> tuple[UnitInformation, np.ndarray, np.ndarray]:
    """A linear unit over 5 compared columns and one nuisance column: column 1 = 2·column 0 −
    column 2 on every unit (a structural gauge direction), and columns 3, 4 trade with the
    nuisance column on a unit that holds 4 (a data gauge direction, when it holds it).
    ``slope`` replaces the 2 (a unit whose structural direction is turned a little, as when
    it is linearised at its own geometry).
    Fitted by least squares over the columns not ``held``; its design and targets."""
    base = rng.normal(size=(n_rows, 4))
    design = np.column_stack(
        [
            base[:, 0],
            slope * base[:, 0] - base[:, 1],
            base[:, 1],
            base[:, 2],
            base[:, 3],
            base[:, 3],
        ]
    )
    design[:, 3] += 0.3 * base[:, 3]
    target = design @ theta + (0.0 if noise is None else noise)
    kept = np.array([i not in held for i in range(design.shape[1])])
    estimate = np.zeros(design.shape[1])
    estimate[kept] = np.linalg.lstsq(design[:, kept], target, rcond=None)[0]
    residual = target - design @ estimate
    unit = UnitInformation(
        gram=design.T @ design,
        kept=kept,
        compared=np.array([0, 1, 2, 3, 4, -1], dtype=np.intp),
        estimate_compared=estimate[:N_COMPARED],
        sigma2=float(residual @ residual) / (n_rows - int(kept.sum())),
        n_rows=n_rows,
    )
    return unit, design, target


def test_units_that_hold_different_columns_agree_in_the_common_gauge() -> None:
    """Noise-free, one robot θ: units holding either of two interchangeable columns, or also
    a column only their data cannot tell from the nuisance, give the same common-gauge value
    of every column, which is a function of θ (cᵀθ); the gauge excludes both directions."""
    rng = np.random.default_rng(3)
    theta = rng.normal(size=6)
    units = [
        _unit(rng, theta, [1])[0],
        _unit(rng, theta, [0])[0],
        _unit(rng, theta, [2, 4])[0],
    ]
    gauge = common_gauge(units)
    assert gauge.dimension == N_COMPARED - 2
    values = np.array([common_gauge_values(gauge, u)[0] for u in units])
    np.testing.assert_allclose(values - values[0], 0.0, atol=1e-9)
    functionals = gauge.scale[:, None] * gauge.projector / gauge.scale[None, :]
    np.testing.assert_allclose(values[0], functionals.T @ theta[:N_COMPARED], atol=1e-9)
    assert gauge.share[3] > 0.5 and gauge.share[4] < 0.5


def test_the_projected_standard_error_is_the_scatter_of_the_value() -> None:
    """The standard error propagated through the projection matches the scatter of the
    common-gauge value over repeated noisy recordings of one unit."""
    theta = np.random.default_rng(0).normal(size=6)
    reference = [_unit(np.random.default_rng(s), theta, [1])[0] for s in (1, 2)]
    gauge = common_gauge(reference)
    values, errors = [], []
    for draw in range(400):
        rng = np.random.default_rng(1)  # the same configurations, fresh noise
        noise = 0.01 * np.random.default_rng(100 + draw).standard_normal(400)
        unit = _unit(rng, theta, [1], noise=noise)[0]
        value, error = common_gauge_values(gauge, unit)
        values.append(value)
        errors.append(error)
    scatter = np.std(values, axis=0, ddof=1)
    predicted = np.mean(errors, axis=0)
    moved = gauge.share > 0.0
    assert scatter[moved] == pytest.approx(predicted[moved], rel=0.15)


@pytest.mark.parametrize(("slope", "dimension"), [(2.001, 4), (2.5, 3)])
def test_nearly_parallel_gauge_directions_count_once(slope: float, dimension: int) -> None:
    """Two units whose structural directions differ by a small angle (well below the
    tolerance) leave one common direction out; clearly different ones leave out two."""
    rng = np.random.default_rng(8)
    theta = rng.normal(size=6)
    units = [_unit(rng, theta, [1])[0], _unit(rng, theta, [1], slope=slope)[0]]
    assert common_gauge(units).dimension == dimension
