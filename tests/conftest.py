"""Shared fixtures: built-in robots and their chains are built once per test session."""

from __future__ import annotations

import fcntl
import functools
import math
import os
import pickle
import re
import shutil
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import pytest
from hypothesis import settings

import solver  # noqa: F401  (BLAS threading defaults before numpy loads)
from schemas.calibration import CalibrationResult
from schemas.robots import BUILTIN_ROBOTS, RobotDescription, load_robot
from solver.model import KinematicChain, build_chain

T = TypeVar("T")

REPO = Path(__file__).resolve().parents[1]
REAL_DATA = REPO / "data" / "real"

settings.register_profile("ci", deadline=None, max_examples=40, derandomize=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@functools.cache
def robot(name: str) -> RobotDescription:
    return load_robot(name)


@functools.cache
def chain(name: str, virtual_first: bool = False) -> KinematicChain:
    description = robot(name)
    probe = build_chain(description.urdf_xml, description.base_frame, description.tip_frame)
    return build_chain(
        description.urdf_xml,
        description.base_frame,
        description.tip_frame,
        virtual_axes_at=[probe.joint_names[0]] if virtual_first else [],
    )


@pytest.fixture(params=sorted(BUILTIN_ROBOTS))
def builtin_name(request: pytest.FixtureRequest) -> str:
    return str(request.param)


def comparable_result(result: CalibrationResult) -> dict[str, Any]:
    """A result as JSON data without what legitimately differs between two identical runs
    (creation time, solver times, the dataset's source name)."""
    document = result.model_dump(mode="json")
    document.pop("created_utc")
    document["solver"].pop("time_s")
    if document.get("covariance") is not None:
        document["covariance"]["solver"].pop("time_s")
    document["dataset"].pop("source")
    return document


def assert_documents_close(got: Any, want: Any, where: str = "", rel: float = 1e-9) -> None:
    """Equal JSON structure, numbers equal to ``rel`` relative (e.g. a different summation
    order)."""
    if isinstance(want, dict):
        assert isinstance(got, dict) and got.keys() == want.keys(), where
        for key in want:
            assert_documents_close(got[key], want[key], f"{where}.{key}", rel)
    elif isinstance(want, list):
        assert isinstance(got, list) and len(got) == len(want), where
        for i, (a, b) in enumerate(zip(got, want, strict=True)):
            assert_documents_close(a, b, f"{where}[{i}]", rel)
    elif isinstance(want, float) and not isinstance(got, bool):
        assert isinstance(got, (int, float)), where
        if where.endswith(".condition_number"):
            # the smallest eigenvalue of a Gram carries rounding of relative size κ²·eps
            rel = max(rel, want * want * 1e-15)
        assert math.isclose(got, want, rel_tol=rel, abs_tol=1e-15), (where, got, want)
    else:
        assert got == want, (where, got, want)


NUMBER = re.compile(r"[-+]?\d+(?:\.\d+)?")


def assert_quoted_output(quoted: str, printed: str) -> None:
    """Every non-blank line of ``quoted`` (output a page quotes; "..." stands for what it
    leaves out, a whole line or part of one) is a line of ``printed``: the same words, and
    each number within one unit of the last digit the page shows (a rounding on the edge may
    fall either way on another CPU)."""
    lines = [line.rstrip() for line in printed.splitlines()]
    for line in quoted.splitlines():
        if not line.strip() or line.strip() == "...":
            continue
        pattern = re.compile(_line_pattern(line.rstrip()))
        shown = NUMBER.findall(line.replace("...", " "))
        found = [m.groups() for m in map(pattern.fullmatch, lines) if m is not None]
        assert any(_within_last_digit(shown, got) for got in found), line


def _line_pattern(line: str) -> str:
    """A regex of ``line``: its numbers captured, each "..." any text."""
    pieces = []
    for piece in line.split("..."):
        parts = NUMBER.split(piece)
        pieces.append(r"([-+]?\d+(?:\.\d+)?)".join(re.escape(part) for part in parts))
    return ".*?".join(pieces)


def _within_last_digit(shown: list[str], got: tuple[str, ...]) -> bool:
    for quoted, printed in zip(shown, got, strict=True):
        unit = 10.0 ** -len(quoted.partition(".")[2]) if "." in quoted else 1.0
        if abs(float(quoted) - float(printed)) > unit * 1.000001:
            return False
    return True


def computed_once(
    tmp_path_factory: pytest.TempPathFactory, name: str, compute: Callable[[Path], T]
) -> T:
    """``compute(folder)`` once per test run, however many xdist workers need it: the first
    worker computes it (writing its files into ``folder``) under an exclusive lock and pickles
    the value next to the folder; the others wait for the lock and unpickle it (the file-lock
    pattern of the pytest-xdist docs). For an expensive module fixture whose tests land on
    both workers; the value must pickle, and its tests must not change ``folder``."""
    root = tmp_path_factory.getbasetemp()
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = root.parent  # the run's folder, shared by its workers
    folder, pickled = root / f"once-{name}", root / f"once-{name}.pickle"
    with (root / f"once-{name}.lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if pickled.is_file():
            value: T = pickle.loads(pickled.read_bytes())
            return value
        shutil.rmtree(folder, ignore_errors=True)  # what a failed attempt left
        folder.mkdir()
        value = compute(folder)
        pickled.with_suffix(".part").write_bytes(pickle.dumps(value))
        pickled.with_suffix(".part").rename(pickled)
        return value


# --- every collected test ran -------------------------------------------------------------
# A scheduler that drops tests and still exits 0 is a green run that tested less: xdist's
# --dist loadfile runs one test per node id, and the schemathesis operations share theirs (58
# of 1140 tests never ran). The controller counts the teardowns it saw (reports, not node ids)
# and fails a run that would pass with fewer than it collected.

_FINISHED = [0]


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    if report.when == "teardown":
        _FINISHED[0] += 1


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    config = session.config
    if exitstatus != 0 or hasattr(config, "workerinput") or config.option.collectonly:
        return
    missing = session.testscollected - _FINISHED[0]
    if session.testscollected and missing > 0:
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
        reporter = config.pluginmanager.get_plugin("terminalreporter")
        if reporter is not None:
            reporter.write_line(
                f"ERROR: {missing} of the {session.testscollected} collected tests never ran "
                "(the scheduler dropped them): this run proves less than it says",
                red=True,
            )
