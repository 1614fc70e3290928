"""The README's "Using it" shell examples run as written (in a scratch folder that sees the
repository's data/ and .venv), and produce the files they promise."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).parents[1]


def section_shell_blocks(markdown: str, heading: str) -> list[str]:
    """The ```bash blocks of the level-2 section ``heading`` (up to the next level-2 one)."""
    start = markdown.index(f"\n## {heading}\n")
    end = markdown.find("\n## ", start + 1)
    section = markdown[start : end if end != -1 else None]
    return re.findall(r"```bash\n(.*?)```", section, flags=re.S)


def test_the_using_it_section_has_the_examples_this_test_runs() -> None:
    (block,) = section_shell_blocks((REPO / "README.md").read_text(), "Using it")
    for command in ("kincal simulate", "kincal calibrate", "kincal predict", "kincal rank"):
        assert command in block
    assert "configs.csv" in block.split("kincal predict")[0], "configs.csv is made before use"


@pytest.mark.slow
def test_every_shell_example_of_using_it_runs_as_written(tmp_path: Path) -> None:
    blocks = section_shell_blocks((REPO / "README.md").read_text(), "Using it")
    (tmp_path / "data").symlink_to(REPO / "data")
    (tmp_path / ".venv").symlink_to(Path(sys.executable).parents[1])
    for block in blocks:
        done = subprocess.run(
            ["bash", "-euo", "pipefail", "-c", block],
            cwd=tmp_path,
            capture_output=True,
            text=True,
            timeout=600,
            check=False,
        )
        assert done.returncode == 0, (
            f"{block}\n--- stdout\n{done.stdout}\n--- stderr\n{done.stderr}"
        )
    for produced in (
        "sim.csv",
        "truth.json",
        "fr3.json",
        "fr3_calibrated.urdf",
        "fr3_report.html",
        "configs.csv",
        "poses.csv",
        "ranking.json",
        "target_ranking.json",
        "positioner.json",
        "fr3_offsets.json",
        "fr3.urdf",
        "offsets.yaml",
        "master_calibration.yaml",
    ):
        assert (tmp_path / produced).stat().st_size > 0, produced
    assert "<html" in (tmp_path / "fr3_report.html").read_text().lower()
