"""Same numbers on every machine (issue 30): the covariance estimates and the held-out coverage
computed in subprocesses under every BLAS kernel this CPU can run, one and two BLAS threads,
numpy's SIMD dispatch cut back, and inputs changed by 1e-12 relative, against the same
computation in the default environment.

Two computations: the simulated position recording of tests/cross_machine/probe.py (the case
that ended in a failed REML on an AVX2-only CPU), and ``kincal calibrate`` with its defaults on
the real 21-pose TIAGo Vicon file (whose held-out coverage was 100 % on one CPU and 90 % on
another). A setting that does not apply here is skipped with its reason (an AVX-512 machine
runs the AVX-512 cases).
"""

from __future__ import annotations

import functools
import json
import os
import subprocess
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from tests.conftest import REPO
from tests.cross_machine import probe

pytestmark = pytest.mark.slow

PERTURBATION = 1e-12
DEFAULT_RTOL = 1e-6
FULL_RTOL = 5e-3
"""Full Σ: the cone program's answer is certified to a KKT residual of 1e-6 (1e-9 typical after
its polish on the PSD face) and the problem is weakly identified in some directions, so
solutions agree to ~1e-3 of their largest entry across BLAS kernels (measured 1.6e-3 on θ and
3.3e-4 on Σ_E on an AVX2 EPYC), not to rounding. Diagonal Σ (the default) is exact."""
OPENBLAS_CORES = (
    "Prescott",
    "Core2",
    "Nehalem",
    "Sandybridge",
    "Haswell",
    "Zen",
    "SkylakeX",
    "Cooperlake",
    "SapphireRapids",
)
AVX512 = "X86_V4 AVX512_ICL AVX512_SPR"
ONE_THREAD = (
    "1 BLAS thread: the reference run already is (importing solver sets OPENBLAS_NUM_THREADS=1 "
    "where the user set no thread count, and limits a BLAS loaded before it to one thread)"
)


@dataclass(frozen=True)
class Variant:
    label: str
    env: dict[str, str] = field(default_factory=dict)
    perturb: float = 0.0


def _python(code: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-c", code],
        env={**os.environ, **env},
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )


_ARCHITECTURE = (
    "import numpy; from threadpoolctl import threadpool_info; numpy.ones((64, 64)) @ "
    "numpy.ones((64, 64)); print([i.get('architecture') for i in threadpool_info() "
    "if i['internal_api'] == 'openblas'][0])"
)


@functools.cache
def variants() -> tuple[tuple[Variant, ...], tuple[str, ...]]:
    """The settings that apply on this CPU, and why the others were skipped."""
    default = _python(_ARCHITECTURE, {})
    assert default.returncode == 0, default.stderr
    seen = {default.stdout.strip()}
    found: list[Variant] = [Variant("2 BLAS threads", {"OPENBLAS_NUM_THREADS": "2"})]
    skipped: list[str] = [ONE_THREAD]
    for core in OPENBLAS_CORES:
        run = _python(_ARCHITECTURE, {"OPENBLAS_CORETYPE": core})
        architecture = run.stdout.strip()
        if run.returncode != 0:
            skipped.append(f"OPENBLAS_CORETYPE={core}: not supported by this CPU")
        elif architecture in seen:
            skipped.append(f"OPENBLAS_CORETYPE={core}: runs the {architecture} kernel, done")
        else:
            seen.add(architecture)
            found.append(Variant(f"OpenBLAS {architecture} kernel", {"OPENBLAS_CORETYPE": core}))
    features = _python(
        "import numpy; f = numpy._core._multiarray_umath.__cpu_features__; "
        "print(int(f.get('X86_V4', False)), int(f.get('X86_V3', False)))",
        {},
    ).stdout.split()
    if features and features[0] == "1":
        found.append(Variant("numpy without AVX-512", {"NPY_DISABLE_CPU_FEATURES": AVX512}))
    else:
        skipped.append("numpy without AVX-512: this CPU has no AVX-512, numpy does not use it")
    if len(features) > 1 and features[1] == "1":
        found.append(
            Variant("numpy without AVX2", {"NPY_DISABLE_CPU_FEATURES": f"X86_V3 {AVX512}"})
        )
    found.append(Variant(f"inputs × (1 ± {PERTURBATION:g})", perturb=PERTURBATION))
    return tuple(found), tuple(skipped)


@dataclass(frozen=True)
class Run:
    """One setting's numbers: the probe's estimates, and ``kincal calibrate`` of the TIAGo
    file (its exit code and result JSON)."""

    label: str
    estimates: dict[str, dict[str, Any]]
    tiago_exit: int
    tiago: dict[str, Any]


def _run(variant: Variant, folder: Path) -> Run:
    """Both computations in one subprocess under ``variant`` (one interpreter start each)."""
    args = ["--perturb", str(variant.perturb), "--calibrate-tiago", str(folder)]
    run = subprocess.run(
        [sys.executable, "-m", "tests.cross_machine.probe", *args],
        env={**os.environ, **variant.env},
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=600,
        check=False,
    )
    assert run.returncode == 0, f"{variant.label}: {run.stderr[-2000:]}"
    found = json.loads(run.stdout)
    tiago = json.loads((folder / "tiago.json").read_text(encoding="utf-8"))
    return Run(variant.label, found["estimates"], found["tiago_exit"], tiago)


def _all_runs(folder: Path) -> tuple[Run, list[Run]]:
    """The default environment's run and every setting's (one test consumes them all: a
    second test waiting for them on the other xdist worker idled it for 37 s)."""
    reference = _run(Variant("default"), folder / "default")
    found, _ = variants()
    return reference, [_run(v, folder / f"variant{k}") for k, v in enumerate(found)]


def _relative(a: object, b: object) -> float:
    """max |a − b| / max |a| over two nested lists of numbers."""
    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return float(np.max(np.abs(x - y)) / max(float(np.max(np.abs(x))), 1e-300))


def test_the_settings_that_apply_are_found_and_the_others_said() -> None:
    found, skipped = variants()
    labels = [v.label for v in found]
    assert "2 BLAS threads" in labels and ONE_THREAD in skipped
    assert any(v.perturb for v in found)
    assert any("OpenBLAS" in label for label in labels)  # at least one other kernel runs
    for reason in skipped:
        print(f"skipped: {reason}")


PERTURBATION_SEEDS = range(16)
"""Draws of the 1e-12 perturbation: before the null-space rule was solved exactly, draws 1 and 2
moved the default estimate by 5.8e-6 on an AVX-512 CPU (the noise's z variance held at its
floor instead of sharing a sum it is interchangeable in), as did draw 13 of the first 16; the
cross-setting test's own draw (12) did so in one full run with OpenBLAS's Haswell kernel."""


def test_the_default_estimate_does_not_move_with_the_last_bits_of_its_inputs() -> None:
    """The diagonal REML estimate of the probe's recording, inputs × (1 ± 1e-12) under several
    draws, in this process: θ within rounding of the unperturbed estimate's."""
    cases = (("diag", "reml"),)
    expected = probe.estimates(0.0, cases)
    for seed in PERTURBATION_SEEDS:
        got = probe.estimates(PERTURBATION, cases, seed=seed)
        for case, found in got.items():
            assert found["status"] == "optimal", (seed, case)
            error = _relative(expected[case]["theta"], found["theta"])
            assert error <= DEFAULT_RTOL, f"draw {seed}, {case}: θ moved by {error:.2e}"


def test_covariances_and_kincal_calibrate_are_the_same_under_every_setting(
    tmp_path: Path,
) -> None:
    """Both computations under every setting against the default environment's."""
    reference, others = _all_runs(tmp_path)
    for case, found in reference.estimates.items():
        assert found["status"] == "optimal" and found["moment_status"] == "optimal", case
    failures = []
    for other in others:
        for case, expected in reference.estimates.items():
            got = other.estimates[case]
            tolerance = DEFAULT_RTOL if case.startswith("diag") else FULL_RTOL
            for key in ("theta", "ee_covariance"):
                error = _relative(expected[key], got[key])
                if not error <= tolerance:
                    failures.append(f"{other.label}, {case}, {key}: {error:.2e} > {tolerance:g}")
            if got["status"] != "optimal":
                failures.append(f"{other.label}, {case}: status {got['status']}")
    for run in (reference, *others):
        assert run.tiago_exit in (0, 3), f"{run.label}: exit {run.tiago_exit}"
        for name in ("covariance", "predictive"):
            assert run.tiago[name] is not None, (run.label, name)
    for other in others:
        matrices = [
            [frame["matrix"] for frame in result["covariance"]["frames"]]
            + [result["covariance"]["noise"]["matrix"]]
            for result in (reference.tiago, other.tiago)
        ]
        error = _relative(*matrices)
        if not error <= DEFAULT_RTOL:
            failures.append(f"{other.label}: covariances differ by {error:.2e}")
        coverage = [result["predictive"]["coverage"] for result in (reference.tiago, other.tiago)]
        inside = [[level["observed"] for level in c["levels"]] for c in coverage]
        if inside[0] != inside[1]:
            failures.append(f"{other.label}: coverage {inside[1]} against {inside[0]}")
        mean = [c["mean_mahalanobis_sq"] for c in coverage]
        if abs(mean[0] - mean[1]) > DEFAULT_RTOL * abs(mean[0]):
            failures.append(f"{other.label}: mean d² {mean[1]} against {mean[0]}")
        if other.tiago["covariance"]["solver"]["status"] != "optimal":
            failures.append(f"{other.label}: REML {other.tiago['covariance']['solver']}")
    assert not failures, "\n".join(failures)
