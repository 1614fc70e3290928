"""``kincal check``: is a calibration still valid? (issue 33)."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Annotated

import typer

from service.cli.common import Outputs, ResultOutDirOpt, output_option, read_result

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
) -> None:
    """Test new poses against the calibration's own predictive uncertainty: holds (exit 0),
    drifted (exit 3, with the change located and sized) or inconclusive (exit 0).

    Each pose's d² under the total predictive covariance (Σ_E + Σ_n + Cov(θ̂) + model error);
    a global χ² test and score tests of candidate changes (joint offsets and scales, base,
    tool, link geometry), family-wise at the level; a pose far off (max-type test, Šidák) is
    set aside as a bad sample and the verdict taken on the rest; the drift located with its
    size and 95 % interval, and the smallest changes the check detects with 90 % probability
    (docs/check.md)."""
    from service.app.check import run_check

    outputs = Outputs(out_dir if out_dir is not None else result_path.parent)
    path = outputs.path(output, "check.json", "kincal.check/1")
    result = read_result(result_path)
    out = run_check(result, recording, level=level, result_name=str(result_path))
    outputs.write_text(path, f"check of {len(out.poses)} poses", out.model_dump_json(indent=1))
    typer.echo(summary(out))
    typer.echo(outputs.listing())
    typer.echo(f"check: {out.verdict}: {out.reason}")
    if out.verdict == "drifted":
        raise typer.Exit(EXIT_DRIFTED)


def summary(out: CheckResult) -> str:
    """The per-pose table (when short), the located change and the stated sizes."""
    from service.render.text import check_size, located_sizes

    lines = []
    if len(out.poses) <= SHORT_TABLE:
        limit = "" if out.max_threshold is None else f"(one pose's limit {out.max_threshold:.1f})"
        lines.append(f"pose  {'d²':>8}  {'mm':>7}  {'mrad':>7}   {limit}".rstrip())
        for pose in out.poses:
            mrad = "" if pose.rotation_mrad is None else f"{pose.rotation_mrad:7.2f}"
            flag = "  bad sample: re-measure" if pose.bad_sample else ""
            lines.append(
                f"{pose.index:4d}  {pose.d2:8.2f}  {pose.translation_mm:7.2f}  {mrad:>7}{flag}"
            )
    if out.located is not None:
        located = out.located
        lines.append(
            f"located: {located.name}: {located_sizes(located)} "
            f"(95 %; adjusted p = {located.adjusted_p_value:.2g})"
        )
        if located.indistinguishable_from:
            lines.append(
                "  these check poses cannot tell it apart from: "
                + ", ".join(located.indistinguishable_from)
            )
    elif out.verdict == "drifted":
        lines.append("located: no single candidate change is significant")
    sizes = ", ".join(
        f"{s.name} {check_size(s.size, s.unit)}{'' if s.located else ' (detected only)'}"
        for s in out.stated_sizes
    )
    if out.stated_sizes:
        lines.append(f"detected and located with {out.power:.0%} probability: {sizes}")
    lines.append(f"advice: {out.advice}")
    return "\n".join(lines)
