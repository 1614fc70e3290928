"""``kincal check``: is a calibration still valid? (issue 33)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from schemas.dataset.paths import check_recording_path
from service.cli.common import (
    Outputs,
    ReportOpt,
    ResultOutDirOpt,
    output_option,
    read_result,
)

if TYPE_CHECKING:
    from schemas.check import CheckResult

CheckOut = Annotated[Path | None, output_option("check.json", "The check JSON")]

SHORT_TABLE = 20
"""Checks of at most this many poses print their per-pose table."""

EXIT_DRIFTED = 3


def check(
    result_path: Annotated[Path, typer.Argument(metavar="RESULT", help="Result JSON.")],
    recording: Annotated[
        Path,
        typer.Argument(
            metavar="CHECK_RECORDING",
            help="A few new poses, with the columns kincal calibrate reads.",
        ),
    ],
    output: CheckOut = None,
    out_dir: ResultOutDirOpt = None,
    level: Annotated[
        float, typer.Option(help="Family-wise probability of a false alarm when it holds.")
    ] = 0.05,
    report: ReportOpt = None,
) -> None:
    """Test new poses against the calibration's own predictive uncertainty: holds (exit 0),
    drifted (exit 3, with the change located and sized) or inconclusive (exit 0).

    Each pose's d² under the total predictive covariance (Σ_E + Σ_n + Cov(θ̂) + model error);
    a global χ² test and score tests of candidate changes (joint offsets and scales, base,
    tool, link geometry), family-wise at the level; a pose far off (max-type test, Šidák) is
    set aside as a bad sample and the verdict taken on the rest; the drift located with its
    size and 95 % interval, and the smallest changes the check detects with 90 % probability
    (docs/check.md)."""
    check_recording_path(recording)
    outputs = Outputs(out_dir if out_dir is not None else result_path.parent)
    path = outputs.path(output, "check.json", "kincal.check/1")
    report_path = None if report is None else outputs.path(report, "check.html", None)
    result = read_result(result_path)
    from service.app.check import run_check
    from service.render.text import check_verdict_line, used_calibration_line

    out = run_check(result, recording, level=level, result_name=str(result_path))
    outputs.write_text(path, f"check of {len(out.poses)} poses", out.model_dump_json(indent=1))
    if report_path is not None:
        from service.render.check_report_html import render_check_report

        outputs.write_text(report_path, "HTML report", render_check_report(out))
    typer.echo(summary(out))
    typer.echo(outputs.listing())
    typer.echo(used_calibration_line(result.verdict))
    typer.echo(check_verdict_line(out))
    if out.verdict == "drifted":
        raise typer.Exit(EXIT_DRIFTED)


def summary(out: CheckResult) -> str:
    """The per-pose table (when short), the located change and the stated sizes."""
    from service.render import text

    lines = []
    if len(out.poses) <= SHORT_TABLE:
        limit = text.check_pose_limit(out)
        lines.append(
            f"pose  {'d²':>8}  {'mm':>7}  {'mrad':>7}   {f'({limit})' if limit else ''}".rstrip()
        )
        for pose in out.poses:
            mrad = "" if pose.rotation_mrad is None else f"{pose.rotation_mrad:7.2f}"
            flag = f"  {text.BAD_SAMPLE}" if pose.bad_sample else ""
            lines.append(
                f"{pose.index:4d}  {pose.d2:8.2f}  {pose.translation_mm:7.2f}  {mrad:>7}{flag}"
            )
    located = text.check_located_lines(out)
    lines += located[:1] + [f"  {line}" for line in located[1:]]
    sizes = text.check_sizes_line(out)
    if sizes is not None:
        lines.append(sizes)
    lines.append(f"advice: {out.advice}")
    return "\n".join(lines)
