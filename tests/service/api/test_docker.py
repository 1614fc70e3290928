"""docker/: hadolint-clean Dockerfile (multi-stage, non-root, exec-form CMD, base image as ARG),
its build-context filter, the compose file with PostgreSQL, and smoke.sh's syntax.

There is no Docker daemon here (nor buildah in CI); docker/smoke.sh builds and runs the image
with buildah where it is installed. Each check is also run on a broken Dockerfile, so that a
check which cannot fail is noticed.
"""

from __future__ import annotations

import fnmatch
import json
import shlex
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
import yaml

from tests.conftest import REPO

DOCKER = REPO / "docker"
DOCKERFILE = DOCKER / "Dockerfile"
HADOLINT = Path(sys.executable).with_name("hadolint")


def hadolint(path: Path) -> tuple[int, list[dict[str, Any]]]:
    """hadolint's exit status and findings (no config file: every rule at its default level)."""
    result = subprocess.run(
        [str(HADOLINT), "--no-color", "--format", "json", str(path)],
        capture_output=True,
        text=True,
        check=False,
        cwd=path.parent,
    )
    assert result.stdout.strip(), result.stderr
    return result.returncode, list(json.loads(result.stdout))


def instructions(text: str) -> list[tuple[str, str]]:
    """(INSTRUCTION, arguments) pairs; continuation lines joined, comments dropped."""
    rows = [line.strip() for line in text.splitlines()]
    joined = "\n".join(row for row in rows if not row.startswith("#")).replace("\\\n", " ")
    return [
        (row.split(maxsplit=1)[0].upper(), row.split(maxsplit=1)[1].strip())
        for row in joined.splitlines()
        if row.strip()
    ]


def structure_problems(text: str) -> list[str]:
    """What the issue asks of the Dockerfile that hadolint does not check."""
    ops = instructions(text)
    problems = []
    if not (ops and ops[0][0] == "ARG" and ops[0][1].startswith("BASE_IMAGE=")):
        problems.append("the first instruction is not ARG BASE_IMAGE=<default>")
    froms = [args for op, args in ops if op == "FROM"]
    if len(froms) < 2:
        problems.append("not multi-stage")
    if not all(f.split()[0] == "${BASE_IMAGE}" for f in froms):
        problems.append("a stage does not start from ${BASE_IMAGE}")
    final = ops[max(i for i, (op, _) in enumerate(ops) if op == "FROM") :]
    users = [args for op, args in final if op == "USER"]
    if not users or users[-1].split(":")[0] in ("root", "0"):
        problems.append("the final stage runs as root")
    cmds = [args for op, args in final if op == "CMD"]
    if not cmds:
        problems.append("no CMD")
    else:
        try:
            cmd = json.loads(cmds[-1])
        except json.JSONDecodeError:
            cmd = None
        if not (isinstance(cmd, list) and cmd[:2] == ["kincal", "serve"]):
            problems.append("CMD is not the exec form of kincal serve")
    checks = [args for op, args in final if op == "HEALTHCHECK"]
    if not checks or "/healthz" not in checks[-1] or "CMD [" not in checks[-1]:
        problems.append("no exec-form HEALTHCHECK on /healthz")
    env = dict(
        token.split("=", 1)
        for op, args in final
        if op == "ENV"
        for token in shlex.split(args)
        if "=" in token
    )
    exposed = [args for op, args in final if op == "EXPOSE"]
    if env.get("KINCAL_HOST") != "0.0.0.0" or exposed != [env.get("KINCAL_PORT")]:
        problems.append("KINCAL_HOST/KINCAL_PORT do not serve the EXPOSEd port on all interfaces")
    return problems


# --- the Dockerfile ----------------------------------------------------------------------------


def test_dockerfile_passes_hadolint() -> None:
    status, findings = hadolint(DOCKERFILE)
    assert (status, findings) == (0, [])


def test_hadolint_flags_a_bad_dockerfile(tmp_path: Path) -> None:
    bad = tmp_path / "Dockerfile"
    bad.write_text(
        "FROM debian\nRUN apt-get update && apt-get install -y curl\nUSER root\nCMD kincal serve\n"
    )
    status, findings = hadolint(bad)
    assert status != 0
    assert {"DL3006", "DL3009", "DL3015", "DL3002", "DL3025"} <= {f["code"] for f in findings}


def test_dockerfile_is_multi_stage_non_root_with_exec_form_cmd() -> None:
    assert structure_problems(DOCKERFILE.read_text()) == []


def _replace(old: str, new: str) -> Callable[[str], str]:
    def mutate(text: str) -> str:
        assert old in text, old
        return text.replace(old, new)

    return mutate


def _single_stage(text: str) -> str:
    """Only the final stage, without the COPY from the build stage."""
    final = text[text.rindex("\nFROM ") :]
    return text[: text.index("\nFROM ")] + final.replace("COPY --from=build ", "COPY ")


BROKEN: dict[str, tuple[Callable[[str], str], str]] = {
    "hard-coded base": (
        _replace("FROM ${BASE_IMAGE} AS build", "FROM python:3.11-slim-bookworm AS build"),
        "a stage does not start from ${BASE_IMAGE}",
    ),
    "no base argument": (_replace("ARG BASE_IMAGE=", "ARG OTHER="), "ARG BASE_IMAGE"),
    "single stage": (_single_stage, "not multi-stage"),
    "root": (_replace("USER 10001:10001", "USER root"), "the final stage runs as root"),
    "shell-form CMD": (
        _replace('CMD ["kincal", "serve"]', "CMD kincal serve"),
        "CMD is not the exec form of kincal serve",
    ),
    "no healthcheck": (_replace("HEALTHCHECK ", "# HEALTHCHECK "), "HEALTHCHECK"),
    "port mismatch": (_replace("EXPOSE 8000", "EXPOSE 8080"), "KINCAL_HOST/KINCAL_PORT"),
}


@pytest.mark.parametrize("name", sorted(BROKEN))
def test_structure_check_catches_a_broken_dockerfile(name: str) -> None:
    mutate, problem = BROKEN[name]
    problems = structure_problems(mutate(DOCKERFILE.read_text()))
    assert any(problem in found for found in problems), problems


# --- build context, compose, smoke.sh ----------------------------------------------------------


def ignored(path: str, patterns: list[str]) -> bool:
    """Whether the build context filter leaves ``path`` out (last matching pattern wins)."""
    verdict = False
    parts = path.split("/")
    prefixes = ["/".join(parts[: i + 1]) for i in range(len(parts))]
    for pattern in patterns:
        negated = pattern.startswith("!")
        glob = pattern.lstrip("!").rstrip("/").replace("**/", "*")
        if any(fnmatch.fnmatch(p, glob) for p in prefixes):
            verdict = not negated
    return verdict


def test_build_context_has_what_the_dockerfile_copies_and_no_more() -> None:
    patterns = [
        line.strip()
        for line in (DOCKER / "Dockerfile.dockerignore").read_text().splitlines()
        if line.strip() and not line.startswith("#")
    ]
    sources = [
        source.rstrip("/")
        for op, args in instructions(DOCKERFILE.read_text())
        if op == "COPY" and not args.startswith("--from")
        for source in args.split()[:-1]
    ]
    assert sources, "no COPY from the build context"
    for source in sources:
        assert (REPO / source).exists(), source
        assert not ignored(f"{source}/x.py" if (REPO / source).is_dir() else source, patterns)
    for left_out in (".venv/bin/python", ".git/config", "tests/conftest.py", "data/real/a.csv"):
        assert ignored(left_out, patterns), left_out
    assert ignored("service/__pycache__/x.pyc", patterns)


def test_compose_runs_the_image_on_postgresql() -> None:
    compose = yaml.safe_load((DOCKER / "compose.yaml").read_text())
    kincal, db = compose["services"]["kincal"], compose["services"]["db"]
    assert (REPO / "docker" / kincal["build"]["context"] / kincal["build"]["dockerfile"]).samefile(
        DOCKERFILE
    )
    url = kincal["environment"]["KINCAL_DATABASE_URL"]
    assert url.startswith("postgresql+psycopg://") and "@db:5432/" in url
    assert kincal["depends_on"]["db"]["condition"] == "service_healthy"
    assert db["image"].startswith("postgres:") and "pg_isready" in str(db["healthcheck"]["test"])
    assert all(str(port).startswith("127.0.0.1:") for port in kincal["ports"])
    assert any(str(v).endswith(":/var/lib/kincal") for v in kincal["volumes"])


def test_smoke_script_is_valid_bash() -> None:
    bash = shutil.which("bash")
    assert bash is not None
    result = subprocess.run(
        [bash, "-n", str(DOCKER / "smoke.sh")], capture_output=True, text=True, check=False
    )
    assert result.returncode == 0, result.stderr
