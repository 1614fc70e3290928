"""Issue 28: ``kincal --help`` and ``kincal calibrate --help`` answer without loading the maths
or the web stack, list the options in panels with their choices, and ``kincal --version``
works. The time itself is measured by ``benchmarks/cli_latency.py`` (no timed assertions)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from service import kincal_version
from service.cli.help_text import GENERATED, generated_source
from tests.service.cli_support import help_text, run

HEAVY = (
    "pinocchio",
    "cvxpy",
    "fastapi",
    "matplotlib",
    "pandas",
    "numpy",
    "scipy",
    "sqlalchemy",
    "rosbags",
)
"""Packages ``kincal --help`` must not import: each costs 0.1-2 s."""

PANELS = (
    "Recording and robot",
    "Model",
    "Measurement",
    "Outliers",
    "Covariance",
    "Held-out",
    "Execution",
    "Output",
)


def _run_and_list_modules(*args: str) -> tuple[set[str], int, str]:
    """``kincal *args`` in a fresh interpreter: the top-level packages it imported, its exit
    code and its stderr."""
    script = (
        "import json, sys\n"
        f"sys.argv = ['kincal', *{list(args)!r}]\n"
        "from service.cli import main\n"
        "code = 0\n"
        "try:\n"
        "    main()\n"
        "except SystemExit as exc:\n"
        "    code = int(exc.code or 0)\n"
        "print(json.dumps([code, sorted({m.split('.')[0] for m in sys.modules})]))\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True
    )
    code, loaded = json.loads(done.stdout.splitlines()[-1])
    return set(loaded), code, done.stderr


@pytest.mark.parametrize(
    "args",
    [
        ("--help",),
        ("calibrate", "--help"),
        ("import", "--help"),
        ("check", "--help"),
        ("--version",),
    ],
)
def test_help_loads_none_of_the_heavy_packages(args: tuple[str, ...]) -> None:
    loaded, code, _ = _run_and_list_modules(*args)
    assert code == 0
    assert "typer" in loaded and "service" in loaded
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))


BAG_FLAGS = ["--joint-states", "/joint_states", "--measure", "tf:camera:board"]


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["calibrate", "missing.csv", "--robot", "kinova"], "missing.csv: file not found"),
        (["calibrate", "rows.txt", "--robot", "kinova"], "rows.txt: unsupported file type '.txt'"),
        (["discover", "missing.parquet", "--robot", "kinova"], "missing.parquet: file not found"),
        (["check", "missing.json", "missing.csv"], "missing.csv: file not found"),
        (["check", "missing.json", "rows.csv"], "cannot read calibration result"),
        (["predict", "missing.json", "missing.csv"], "missing.csv: file not found"),
        (["predict", "missing.json", "rows.csv"], "cannot read calibration result"),
        (["rank", "missing.json", "missing.csv"], "missing.csv: file not found"),
        (["import", "missing.bag", *BAG_FLAGS], "missing.bag: file not found"),
        (["calibrate", "missing.bag", "--robot", "kinova", *BAG_FLAGS], "missing.bag: file not"),
        (["export", "missing.json", "-o", "out.urdf"], "cannot read calibration result"),
        (["fleet", "rows.csv", "--robot", "kinova"], "rows.csv: not a folder"),
        (["fleet", "units.d", "--check", "missing.d"], "--check missing.d: not a folder"),
        (["design", "--robot", "kinova", "--candidates", "missing.csv"], "missing.csv: file not"),
        (["design", "--robot", "kinova", "--task", "missing.csv"], "missing.csv: file not found"),
        (["design", "--robot", "kinova", "--config", "missing.toml"], "cannot read config"),
        (["design", "--result", "missing.json", "--recording", "rows.csv"], "cannot read calib"),
        (["design", "--check", "5", "--result", "missing.json"], "cannot read calibration result"),
    ],
)
def test_a_refused_file_loads_none_of_the_heavy_packages(
    tmp_path: Path, args: list[str], message: str
) -> None:
    """Issue 29: a recording (file or ROS bag), configurations file, result, config file or
    fleet folder refused for its path (missing, unknown format, not a folder) is refused with
    one line and exit code 2 before pandas, numpy, scipy or Pinocchio load (0.2 s instead of
    1–1.85 s)."""
    for name in ("rows.txt", "rows.csv"):
        (tmp_path / name).write_text("x,y,z\n0,0,0\n", encoding="utf-8")
    (tmp_path / "units.d").mkdir()
    command = [args[0], *(str(tmp_path / a) if "." in a else a for a in args[1:])]
    loaded, code, stderr = _run_and_list_modules(*command)
    assert code == 2 and f"kincal: error: {message}" in stderr.replace(f"{tmp_path}/", ""), stderr
    assert len(stderr.strip().splitlines()) == 1
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))


def test_calibrate_help_groups_the_options_in_panels_with_their_choices(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    code, text, _ = run(["calibrate", "--help"], capsys, monkeypatch)
    assert code == 0
    positions = [text.index(f"─ {panel} ─") for panel in PANELS]
    assert positions == sorted(positions), "panels in the documented order"
    words = help_text(text)
    for choices in ("model|sigma|none", "diag|full|none", "auto|clarabel|pgd|nnls", "all|rotation"):
        assert choices in words, choices
    assert "[default: every revolute joint]" in words  # not "None = ... [default none]"
    assert "<str>" not in text.split("─ Outliers ─")[1].split("│")[2]  # a choice, not <str>


def test_version(capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch) -> None:
    code, out, _ = run(["--version"], capsys, monkeypatch)
    assert code == 0 and out.strip() == f"kincal {kincal_version()}"


def test_the_generated_help_is_what_the_models_say() -> None:
    assert GENERATED.read_text(encoding="utf-8") == generated_source(), (
        "the options, effects or settings changed: run `python service/cli/help_text.py`"
    )


def test_the_check_loads_no_optimiser_solver_plots_or_web_stack() -> None:
    """Issue 33: a 10-pose ``kincal check`` is mostly start-up. The module it runs loads
    neither scipy's optimisers (0.14 s; the predictive model's error fit imports them when it
    runs) nor scipy.stats, cvxpy, matplotlib, SQLAlchemy or FastAPI."""
    script = "import json, sys, service.app.check; print(json.dumps(sorted(sys.modules)))"
    done = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True
    )
    loaded = set(json.loads(done.stdout))
    heavy = {"scipy.optimize", "scipy.stats", "cvxpy", "matplotlib", "sqlalchemy", "fastapi"}
    assert "service.app.check" in loaded
    assert not loaded & heavy, sorted(loaded & heavy)
