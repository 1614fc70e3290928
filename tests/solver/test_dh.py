"""DH / modified-DH chains (solver.dh): the generated URDF's forward kinematics (Pinocchio, through
kincal's chain) equal the table's direct product, and the table derived from any chain
reproduces that chain's forward kinematics."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from solver.dh import DhRow, dh_forward_kinematics, dh_table_of_links, dh_urdf
from solver.kinematics import ChainParameters, forward_kinematics
from solver.lie import se3_exp
from solver.measurement.models import nominal_pose
from solver.model import build_chain, sample_configurations

angles = st.floats(-np.pi, np.pi, allow_nan=False)
lengths = st.floats(-0.6, 0.6, allow_nan=False)


def _pose(twist: list[float]) -> np.ndarray:
    return np.asarray(se3_exp(np.asarray(twist, dtype=float)), dtype=float)


@st.composite
def tables(draw: st.DrawFn) -> tuple[str, list[DhRow], np.ndarray, np.ndarray]:
    convention = draw(st.sampled_from(["dh", "mdh"]))
    k = draw(st.integers(1, 6))
    rows = []
    for i in range(k):
        kind = draw(st.sampled_from(["revolute", "revolute", "prismatic"]))
        limits = (-np.pi, np.pi) if kind == "revolute" else (-0.3, 0.3)
        rows.append(
            DhRow(
                f"j{i + 1}", kind, draw(lengths), draw(angles), draw(lengths), draw(angles), *limits
            )
        )
    twist = st.lists(st.floats(-1.0, 1.0, allow_nan=False), min_size=6, max_size=6)
    return convention, rows, _pose(draw(twist)), _pose(draw(twist))


@settings(max_examples=25, deadline=None)
@given(tables())
def test_generated_urdf_has_the_tables_forward_kinematics(
    table: tuple[str, list[DhRow], np.ndarray, np.ndarray],
) -> None:
    convention, rows, base, tool = table
    urdf = dh_urdf("t", rows, convention, base, tool, base_frame="base", tip_frame="tip")  # type: ignore[arg-type]
    chain = build_chain(urdf, "base", "tip")
    q = sample_configurations(chain, 20, np.random.default_rng(0))
    expected = dh_forward_kinematics(rows, convention, base, tool, q)  # type: ignore[arg-type]
    assert np.abs(nominal_pose(chain, q) - expected).max() < 1e-12
    for other in ("dh", "mdh"):  # and back: the table of the chain, in either convention
        again = dh_table_of_links(chain, chain.nominal_links, other)  # type: ignore[arg-type]
        got = dh_forward_kinematics(again.rows, other, again.base, again.tool, q)  # type: ignore[arg-type]
        assert np.abs(got - expected).max() < 1e-9


@pytest.mark.parametrize("convention", ["dh", "mdh"])
@pytest.mark.parametrize("robot", ["ur10", "panda", "kinova"])
def test_table_of_a_perturbed_chain_reproduces_its_forward_kinematics(
    convention: str, robot: str
) -> None:
    from tests.conftest import robot as load

    description = load(robot)
    chain = build_chain(description.urdf_xml, description.base_frame, description.tip_frame)
    rng = np.random.default_rng(3)
    params = ChainParameters.nominal(chain).with_link_corrections(
        rng.normal(0.0, 0.01, (chain.n_links, 6))
    )
    table = dh_table_of_links(chain, params.links, convention)  # type: ignore[arg-type]
    q = sample_configurations(chain, 50, rng)
    loads = np.zeros((q.shape[0], len(chain.compliance_axes)))
    expected = forward_kinematics(chain, params, q, loads)
    got = dh_forward_kinematics(table.rows, table.convention, table.base, table.tool, q)
    assert np.abs(got - expected).max() < 1e-9
