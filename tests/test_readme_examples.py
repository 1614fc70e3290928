"""The README is a guide (issue 28): short, the two commands first, a tour that starts with the
dataset contract — and every shell block of it runs as written, in order, in a fresh copy of
the repository, writing only under out/. Its numbers are the benchmark's and the tour's own."""

from __future__ import annotations

import json
import os
import re
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks.results import read_results
from schemas.calibration import CalibrationResult
from tests.conftest import assert_quoted_output

REPO = Path(__file__).parents[1]
README = (REPO / "README.md").read_text(encoding="utf-8")

NOT_RUN_HERE = {
    "make test": "this suite itself (running it here would recurse)",
    "make demo": "tests/test_examples.py runs the demo's study (run_demo)",
}
"""The two bootstrap commands of the first block, and where each is covered instead."""


def shell_blocks(markdown: str) -> list[str]:
    return re.findall(r"```bash\n(.*?)```", markdown, flags=re.S)


def _runnable(blocks: list[str]) -> str:
    lines = []
    for block in blocks:
        for line in block.splitlines():
            command = line.split("#")[0].strip()
            if command in NOT_RUN_HERE:
                continue
            lines.append(line)
    return "\n".join(lines) + "\n"


def test_the_readme_is_a_guide() -> None:
    lines = README.splitlines()
    assert len(lines) <= 250
    assert shell_blocks(README)[0].split("#")[0].strip() == "make demo"
    assert all(command in shell_blocks(README)[0] for command in NOT_RUN_HERE)
    order = [
        "## Five-minute tour",
        "### 1. Calibrate your own robot",
        "| `x, y, z` |",  # the dataset contract, before the first command that reads one
        "kincal calibrate data/real",
        "kincal predict",
        "kincal rank",
        "### 2. Discover",
        "### 3. Choose the poses",
        "### 4. Serve it over HTTP",
        "## The verdict and exit codes",
        "## One real robot",
        "## Where to go next",
    ]
    positions = [README.index(marker) for marker in order]
    assert positions == sorted(positions)
    for link in re.findall(r"\]\((docs/[^)#]+)", README):
        assert (REPO / link).is_file(), link


def _fr3_row() -> list[str]:
    (row,) = [line for line in README.splitlines() if line.startswith("| FR3 eye-in-hand")]
    return [cell.strip() for cell in row.strip("|").split("|")]


def test_the_real_robot_table_is_the_benchmarks() -> None:
    """The README's row equals the FR3 row of docs/results/real_robots.json as rendered."""
    _, rows = read_results("real_robots")
    (fr3,) = [r for r in rows if r["recording"].startswith("FR3 eye-in-hand")]
    assert _fr3_row()[1:] == [
        f"{fr3['samples']} ({fr3['used']})",
        f"{fr3['before_mm']:.2f} / {fr3['before_deg']:.3f}",
        f"{fr3['after_mm']:.2f} / {fr3['after_deg']:.3f}",
        f"{fr3['improved']} of {fr3['splits']}",
        fr3["verdict"],
    ]


def test_the_readmes_wall_time_is_the_speed_benchmarks() -> None:
    """The FR3 command's wall time the README quotes is docs/results/cli_speed.json's median."""
    _, rows = read_results("cli_speed")
    (fr3,) = [r for r in rows if r["recording"].startswith("FR3 eye-in-hand")]
    assert f"The whole\ncommand takes {fr3['median_s']:.1f} s on a 2-core machine" in README


def _fresh_copy(destination: Path) -> None:
    """The files a clone has (tracked, and new ones not ignored), with their times (so make
    finds .venv up to date), and the suite's .venv."""
    listed = subprocess.run(
        ["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
        cwd=REPO,
        capture_output=True,
        check=True,
    ).stdout.decode()
    for name in filter(None, listed.split("\0")):
        source = REPO / name
        if source.is_file():
            (destination / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy2(source, destination / name)
    (destination / ".venv").symlink_to(Path(sys.executable).parents[1])


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.mark.slow
def test_every_shell_block_of_the_readme_runs_as_written(tmp_path: Path) -> None:
    copy = tmp_path / "kincal"
    _fresh_copy(copy)
    before = {p.relative_to(copy) for p in copy.rglob("*") if ".venv" not in p.parts}
    port = _free_port()
    env = {
        **os.environ,
        "KINCAL_PORT": str(port),  # the service's port and the tour's URL: a free one here
        "KINCAL_URL": f"http://127.0.0.1:{port}",
        "KINCAL_DATA_DIR": str(tmp_path / "service"),
    }
    done = subprocess.run(
        ["bash", "-euo", "pipefail", "-c", _runnable(shell_blocks(README))],
        cwd=copy,
        env=env,
        capture_output=True,
        text=True,
        timeout=1200,
        check=False,
    )
    assert done.returncode == 0, f"--- stdout\n{done.stdout}\n--- stderr\n{done.stderr}"
    out = copy / "out"
    for produced in (
        "fr3_poses/calibration.json",
        "fr3_poses/report.html",
        "fr3_poses/predictions.csv",
        "fr3_poses/ranking.json",
        "fr3_poses/fr3_calibrated.urdf",
        "panda_right/findings.json",
        "design/design.json",
        "design/poses.csv",
        "http_tour/report.html",
        "http_tour/ranking.json",
        "http_tour/fr3_calibrated.urdf",
    ):
        assert (out / produced).stat().st_size > 0, produced
    # Python's bytecode caches (git-ignored, written wherever the environment allows) are not
    # the tour's outputs
    created = {
        p.relative_to(copy)
        for p in copy.rglob("*")
        if ".venv" not in p.parts and "__pycache__" not in p.parts
    } - before
    assert {p.parts[0] for p in created} == {"out"}, "the tour writes under out/ only"
    assert f"listening on http://127.0.0.1:{port}" in done.stdout
    assert "verdict: ok: fit to use (exit code 0)" in done.stdout
    # the calibration output the README quotes is the tour's own
    assert_quoted_output(re.findall(r"```text\n(.*?)```", README, re.S)[0], done.stdout)
    # the README quotes the tour's own calibration (2 decimals mm, 3 deg)
    result = CalibrationResult.model_validate_json((out / "fr3_poses/calibration.json").read_text())
    before_fit, after_fit = result.fit.before.heldout, result.fit.after.heldout
    assert before_fit is not None and after_fit is not None
    assert _fr3_row()[2:4] == [
        f"{before_fit.translation_mean_mm:.2f} / {before_fit.rotation_mean_deg:.3f}",
        f"{after_fit.translation_mean_mm:.2f} / {after_fit.rotation_mean_deg:.3f}",
    ]
    ranking = json.loads((out / "http_tour/ranking.json").read_text())
    assert len(ranking) == 5


def test_ci_runs_the_readmes_test_command_with_the_browser_the_tests_need() -> None:
    """CI runs `.ci/run` on a fresh clone: it ends in the README's test command, and installs
    Debian's chromium first where it is missing, so the headless-browser tests run there rather
    than skip (tests/service/api/test_docs_browser.py)."""
    script = (REPO / ".ci" / "run").read_text(encoding="utf-8")
    commands = [line.strip() for line in script.splitlines() if line.strip()]
    test_command = next(
        line.split("#")[0].strip()
        for line in shell_blocks(README)[0].splitlines()
        if line.startswith("make test")
    )
    assert commands[-1] == test_command
    assert "apt-get install -y -qq chromium" in script
