"""solver.distributions gives scipy.stats' numbers to the last bit without importing it, and
``kincal discover`` no longer imports scipy.stats (~0.5 s of every start)."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import scipy.stats
from hypothesis import given, settings
from hypothesis import strategies as st

from solver import distributions
from tests.conftest import REAL_DATA, REPO

probabilities = st.floats(1e-12, 1.0 - 1e-12)
dofs = st.integers(1, 5000)
small_dofs = st.integers(1, 8)


@settings(max_examples=300, deadline=None)
@given(probabilities, small_dofs, dofs, st.floats(0.0, 60.0), st.floats(0.0, 500.0))
def test_every_function_is_scipy_stats_to_the_bit(
    p: float, m: int, dof: int, x: float, noncentrality: float
) -> None:
    """Equal numbers, NaN where scipy.stats gives NaN (Boost's non-central F at 1 denominator
    degree of freedom and a tiny λ)."""
    pairs = [
        (distributions.chi2_quantile(p, m), scipy.stats.chi2.ppf(p, m)),
        (distributions.chi2_quantile(0.5, dof), scipy.stats.chi2.median(dof)),
        (distributions.chi2_isf(p, dof), scipy.stats.chi2.isf(p, dof)),
        (distributions.chi2_survival(x * 3.0, m), scipy.stats.chi2.sf(x * 3.0, m)),
        (distributions.t_sf(x - 30.0, dof), scipy.stats.t.sf(x - 30.0, dof)),
        (distributions.f_isf(p, m, dof), scipy.stats.f.isf(p, m, dof)),
        (
            distributions.ncf_sf(x, m, dof, noncentrality),
            scipy.stats.ncf.sf(x, m, dof, noncentrality),
        ),
    ]
    for ours, theirs in pairs:
        np.testing.assert_array_equal(ours, theirs)


def test_without_the_private_ufunc_the_non_central_f_comes_from_scipy_stats(monkeypatch) -> None:
    monkeypatch.setattr(distributions, "_NCF_SF", None)
    for x, m, dof, noncentrality in ((2.1, 1, 40, 3.0), (0.7, 2, 300, 12.5), (9.0, 6, 17, 0.0)):
        expected = scipy.stats.ncf.sf(x, m, dof, noncentrality)
        assert distributions.ncf_sf(x, m, dof, noncentrality) == expected


def test_kincal_discover_does_not_import_scipy_stats(tmp_path) -> None:
    """A whole ``kincal discover`` of a shipped recording, in a fresh interpreter."""
    recording = REAL_DATA / "figaroh_ur10_experiment" / "calibration.csv"
    code = (
        "import sys\n"
        "from service.cli import main\n"
        f"sys.argv = ['kincal', 'discover', {str(recording)!r}, '--robot', 'ur10', "
        f"'--out-dir', {str(tmp_path)!r}]\n"
        "try:\n    main()\nexcept SystemExit:\n    pass\n"
        "print('scipy.stats' in sys.modules)\n"
    )
    run = subprocess.run(
        [sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=600
    )
    assert run.returncode == 0, run.stderr[-2000:]
    assert "named" in run.stdout or "nothing" in run.stdout, run.stdout[-2000:]
    assert run.stdout.strip().splitlines()[-1] == "False", run.stdout[-2000:]
