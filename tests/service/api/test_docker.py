"""docker/Dockerfile: hadolint-clean, multi-stage, non-root, exec-form CMD, base image as ARG.

There is no Docker daemon here; docker/smoke.sh builds and runs the image with buildah.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO

DOCKERFILE = REPO / "docker" / "Dockerfile"


def _instructions() -> list[tuple[str, str]]:
    text = DOCKERFILE.read_text().replace("\\\n", " ")
    rows = [line.strip() for line in text.splitlines()]
    return [
        (row.split(maxsplit=1)[0].upper(), row.split(maxsplit=1)[1])
        for row in rows
        if row and not row.startswith("#")
    ]


def test_dockerfile_passes_hadolint() -> None:
    hadolint = Path(sys.executable).with_name("hadolint")
    result = subprocess.run(
        [str(hadolint), str(DOCKERFILE)], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stdout + result.stderr


def test_dockerfile_is_multi_stage_non_root_with_exec_form_cmd() -> None:
    instructions = _instructions()
    assert instructions[0][0] == "ARG" and instructions[0][1].startswith("BASE_IMAGE=")
    froms = [args for op, args in instructions if op == "FROM"]
    assert len(froms) >= 2 and all(f.startswith("${BASE_IMAGE}") for f in froms)
    final_user = [args for op, args in instructions if op == "USER"][-1]
    assert final_user.split(":")[0] not in ("root", "0")
    cmd = [args for op, args in instructions if op == "CMD"][-1]
    assert cmd.startswith("[") and '"serve"' in cmd
    assert any(op == "HEALTHCHECK" and "/healthz" in args for op, args in instructions)
