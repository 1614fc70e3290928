"""Run the study and write the report and figures (:func:`main`); the command-line arguments."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from benchmarks.reproduce_paper.report import headline, write_report
from benchmarks.reproduce_paper.results import write_study_results
from benchmarks.reproduce_paper.settings import StudySettings
from benchmarks.reproduce_paper.study import StudyResult, run_study

DOCS = Path(__file__).resolve().parents[2] / "docs"
"""Where ``--write-results`` puts the figures docs/reproduce_paper.md shows."""


def main(
    settings: StudySettings = StudySettings(),
    out: Path = Path("out/reproduce_paper"),
    figures: Path | None = None,
    *,
    echo: Callable[[str], None] = print,
    write: str | None = None,
) -> StudyResult:
    """Run the study, write the report and the figures, print the headline numbers.
    ``write``: the command line to record in ``docs/results/reproduce_paper_*.json`` (written
    with their tables when given; the figures then go to ``docs/`` unless ``figures`` is
    given)."""
    study = run_study(settings, echo=echo)
    if write is not None and figures is None:
        figures = DOCS
    report = write_report(study, out, figures)
    echo(headline(study))
    echo(f"wrote {report}")
    if write is not None:
        for path in write_study_results(study, write):
            echo(f"wrote {path}")
    return study


def settings_from_arguments(arguments: argparse.Namespace) -> StudySettings:
    settings = StudySettings.quick() if arguments.quick else StudySettings()
    changes = {
        "n_runs": arguments.runs,
        "n_recordings": arguments.recordings,
        "n_executions": arguments.executions,
    }
    return dataclasses.replace(settings, **{k: v for k, v in changes.items() if v is not None})


def argument_parser(description: str) -> argparse.ArgumentParser:
    """The arguments of ``python -m benchmarks.reproduce_paper``."""
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.reproduce_paper", description=description
    )
    parser.add_argument("--out", type=Path, default=Path("out/reproduce_paper"))
    parser.add_argument("--figures", type=Path, default=None, help="PNG folder (default --out)")
    parser.add_argument("--runs", type=int, default=None, help="manipulation runs per recording")
    parser.add_argument("--recordings", type=int, default=None, help="independent recordings")
    parser.add_argument("--executions", type=int, default=None, help="executions per approach")
    parser.add_argument("--quick", action="store_true", help="the reduced study of the test")
    parser.add_argument(
        "--write-results",
        action="store_true",
        help="also write docs/results/reproduce_paper_*.{json,md} and the figures in docs/",
    )
    return parser


def run(description: str, argv: Sequence[str] | None = None) -> StudyResult:
    """Parse the command line (``argv``, default ``sys.argv[1:]``) and run :func:`main`."""
    arguments = argument_parser(description).parse_args(argv)
    write = None
    if arguments.write_results:
        given = sys.argv[1:] if argv is None else list(argv)
        write = " ".join(["python -m benchmarks.reproduce_paper", *given])
    return main(settings_from_arguments(arguments), arguments.out, arguments.figures, write=write)
