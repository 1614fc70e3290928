"""The paper reproduction (benchmarks/reproduce_paper/, issue 4 item 5) on its quick settings:
it writes the report and figures, its statistics decide as documented, and the issue's
acceptance points are checked with the report's own rule (the whole 95 % bootstrap interval on
the right side of the bar)."""

from __future__ import annotations

import argparse
import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from benchmarks import reproduce_paper
from benchmarks.reproduce_paper import ApproachRun, StudyResult, StudySettings, cli
from benchmarks.reproduce_paper import results as paper_results
from benchmarks.results import read_results
from tests.conftest import computed_once

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _quick_study(out: Path) -> tuple[StudyResult, Path, list[str]]:
    lines: list[str] = []
    study = reproduce_paper.main(StudySettings.quick(), out, echo=lines.append)
    return study, out, lines


@pytest.fixture(scope="module")
def quick(tmp_path_factory: pytest.TempPathFactory) -> tuple[StudyResult, Path, list[str]]:
    """The quick study, run once for both xdist workers (its tests land on both)."""
    return computed_once(tmp_path_factory, "reproduce_paper", _quick_study)


def test_quick_study_writes_the_report_and_figures(
    quick: tuple[StudyResult, Path, list[str]],
) -> None:
    study, out, lines = quick
    assert sorted(p.name for p in out.iterdir()) == [
        "reproduce_paper.md",
        "reproduce_paper_runs.png",
        "reproduce_paper_sigma.png",
    ]
    for png in out.glob("*.png"):
        assert png.read_bytes()[:8] == PNG_SIGNATURE
    text = (out / "reproduce_paper.md").read_text(encoding="utf-8")
    for heading in (
        "## Table II",
        "## Fig. 4b",
        "## Manipulation experiment",
        "## Table III",
        "## The docking task's own score (task point)",
        "## Protocol variant: camera noise measured separately (paper §V-B)",
        "## Acceptance (issue 4)",
        "## Where the gap to the oracle comes from",
    ):
        assert heading in text
    assert "](reproduce_paper_sigma.png)" in text and "](reproduce_paper_runs.png)" in text
    assert f"share {100 * study.pooled.share_of_oracle:.1f} %" in text
    assert "\nshare of the oracle's reduction: " in "\n".join(lines)
    measured = study.known_noise.pooled["measured"]
    assert f"share {100 * measured.share_of_oracle:.1f} %" in text
    assert "\nvariant with Σ_n measured separately (§V-B): " in "\n".join(lines)
    docking = study.docking.pooled
    assert f"share {100 * docking.share_of_oracle:.1f} %" in text
    assert "\ndocking score: share of the oracle's reduction " in "\n".join(lines)
    # Table II: the calibration beats the nominal robot on every split, as in the paper.
    table = study.table
    for seed in table.seeds:
        assert table.errors["calibrated"][seed][0] < 0.5 * table.errors["before"][seed][0]
    # The recording and the experiment are what the docstring says.
    first = study.first
    assert first.result.outliers.n_input == 154
    assert set(first.recording.outlier_rows + 1) <= set(first.result.outliers.removed_rows)
    assert len(study.runs) == 40 and all(run.error_mm.shape == (10,) for run in study.runs)


def test_noise_experiment_sees_camera_noise_only_and_estimates_it_without_bias(
    quick: tuple[StudyResult, Path, list[str]],
) -> None:
    """Paper §V-B simulated: a standing arm keeps its perturbation, so detections of one
    configuration differ by camera noise and detector failures only; the failures are screened
    (rarely one good detection with them) and the mean-subtracted sample variance is unbiased
    (40 repetitions; without the per-configuration degrees of freedom it would be 11 % low)."""
    robot = quick[0].first.recording.true_robot
    q = np.zeros((2, robot.chain.n_joints))
    quiet = dataclasses.replace(robot, noise_std=np.zeros(6), outlier_fraction=0.0)
    detected, gross = quiet.detect_static(q, 4, np.random.default_rng(0))
    assert detected.shape == (2, 4, 4, 4) and not gross.any()
    np.testing.assert_allclose(detected, np.broadcast_to(detected[:, :1], detected.shape))
    rigid = dataclasses.replace(quiet, perturbation_std=np.zeros_like(robot.perturbation_std))
    np.testing.assert_allclose(
        rigid.detect_static(q, 1, np.random.default_rng(0))[0][:, 0], robot.mean_pose(q)
    )
    ratios = []
    for seed in range(40):
        experiment = reproduce_paper.measure_camera_noise(robot, seed)
        assert not np.any(experiment.kept & experiment.gross)  # every failure screened
        assert np.count_nonzero(~experiment.kept & ~experiment.gross) <= 1
        ratios.append(experiment.std**2 / robot.noise_std**2)
    assert abs(np.mean(ratios) - 1.0) < 0.06, np.mean(ratios, axis=0)


def _run(scores: dict[str, np.ndarray], error_mm: np.ndarray, recording: int = 1) -> ApproachRun:
    m = error_mm.size
    return ApproachRun(
        recording=recording,
        run=0,
        attempts=1,
        joint_positions=np.zeros((m, 6)),
        scores=scores,
        error_mm=error_mm,
        scatter_mm=error_mm,
        bias_mm=np.zeros(m),
        true_xy_std_mm=error_mm,
    )


def test_acceptance_rules_decide_both_ways_on_constructed_runs() -> None:
    """The rule the acceptance tests use can fail: a score that ranks like the oracle meets it,
    one that ranks backwards or like noise does not."""
    rng = np.random.default_rng(0)
    runs = []
    for _ in range(40):
        error = np.sort(rng.uniform(0.3, 0.6, 10))  # the oracle's order is the true order
        oracle = error**2
        runs.append((error, oracle))

    def comparison(ours: list[np.ndarray], gp: list[np.ndarray]) -> reproduce_paper.Comparison:
        return reproduce_paper.compare(
            [
                _run({"ours": o, "gp": g, "oracle": truth}, error)
                for (error, truth), o, g in zip(runs, ours, gp, strict=True)
            ],
            bootstrap=500,
        )

    noise = [rng.normal(size=10) for _ in runs]
    good = comparison([truth for _, truth in runs], noise)
    assert good.share_of_oracle == pytest.approx(1.0) and good.reduction_verdict == "met"
    assert good.correlation_verdict == "met"
    backwards = comparison([-truth for _, truth in runs], noise)
    assert backwards.share_of_oracle < 0.0 and backwards.reduction_verdict == "not met"
    assert backwards.correlation_verdict == "not met"
    same = comparison(noise, noise)
    assert same.pearson_gap == 0.0 and same.correlation_verdict != "met"


def test_two_level_bootstrap_resamples_recordings_then_runs() -> None:
    groups = [1] * 5 + [2] * 5 + [3] * 5
    index = reproduce_paper.bootstrap_indices(groups, 200, np.random.default_rng(1))
    assert index.shape == (200, 15)
    blocks = np.asarray(groups)[index].reshape(200, 3, 5)
    assert np.all(blocks == blocks[:, :, :1])  # each block of 5 draws comes from one recording
    assert len(np.unique(blocks[:, :, 0])) == 3
    assert np.any(blocks[:, 0, 0] == blocks[:, 1, 0])  # recordings drawn with replacement
    with pytest.raises(ValueError, match="equal numbers"):
        reproduce_paper.bootstrap_indices([1, 1, 2], 10, np.random.default_rng(2))


def test_module_entry_point_takes_the_documented_arguments(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``python -m benchmarks.reproduce_paper`` starts, describes the study and passes its
    arguments to ``main`` (stubbed here: the study itself runs in the ``quick`` fixture)."""
    done = subprocess.run(
        [sys.executable, "-m", "benchmarks.reproduce_paper", "--help"],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).resolve().parents[1],
    )
    assert done.stdout.startswith("usage: python -m benchmarks.reproduce_paper ")
    assert "Reproduction of the paper's experiments" in done.stdout
    options = ("--out", "--figures", "--runs", "--recordings", "--executions", "--quick")
    for option in (*options, "--write-results"):
        assert option in done.stdout
    calls: list[tuple[StudySettings, Path, Path | None, str | None]] = []
    monkeypatch.setattr(
        cli,
        "main",
        lambda settings, out, figures, write: calls.append((settings, out, figures, write)),
    )
    cli.run("study", ["--quick", "--runs", "7", "--out", str(tmp_path)])
    quick = dataclasses.replace(StudySettings.quick(), n_runs=7)
    assert calls == [(quick, tmp_path, None, None)]
    cli.run("study", ["--write-results"])
    assert calls[-1] == (
        StudySettings(),
        Path("out/reproduce_paper"),
        None,
        "python -m benchmarks.reproduce_paper --write-results",
    )


def test_command_line_settings() -> None:
    arguments = argparse.Namespace(quick=True, runs=7, recordings=None, executions=50)
    settings = reproduce_paper.settings_from_arguments(arguments)
    assert settings == dataclasses.replace(StudySettings.quick(), n_runs=7, n_executions=50)
    arguments = argparse.Namespace(quick=False, runs=None, recordings=2, executions=None)
    assert reproduce_paper.settings_from_arguments(arguments).n_recordings == 2


def test_our_score_correlates_with_the_observed_error_better_than_the_gp(
    quick: tuple[StudyResult, Path, list[str]],
) -> None:
    """Issue 4 acceptance (Table III): the whole 95 % interval of mean Pearson r, ours minus
    the GP's, is above zero."""
    study = quick[0]
    assert study.pooled.correlation_verdict == "met", study.pooled.pearson_gap_ci


def test_true_covariances_reach_the_oracles_reduction_on_the_same_candidates(
    quick: tuple[StudyResult, Path, list[str]],
) -> None:
    """Control for the experiment: scoring the same candidates with the true Σ on the
    calibrated geometry meets the 80 % bar, so the experiment can show it and a shortfall of
    ours is the covariance calibration's."""
    study = quick[0]
    control = next(a for a in study.ablations if a.label.startswith("true Σ"))
    assert control.comparison.reduction_verdict == "met", control.comparison.share_ci


def test_docking_score_reaches_80_percent_of_the_oracles_reduction(
    quick: tuple[StudyResult, Path, list[str]],
) -> None:
    """Issue 4 acceptance, scored with the task's own score (the x-y variance of the docking
    point, ``DOCKING_TASK``): ours reduces the observed error by ≥ 80 % of what the oracle's
    choice does, and correlates with it better than the GP. The quick study's 40 runs are too
    few for the report's interval rule on the share (the full study's 600 runs decide it in
    docs/reproduce_paper.md), so its point estimate is checked here; the correlation clears
    the interval rule already."""
    docking = quick[0].docking
    assert docking.pooled.share_of_oracle >= 0.8, docking.pooled.share_ci
    assert docking.pooled.correlation_verdict == "met", docking.pooled.pearson_gap_ci
    # The oracle with the task's own score chooses better than with the paper's W.
    oracle = quick[0].pooled.selections["oracle"].reduction_pct
    assert docking.pooled.selections["oracle"].reduction_pct > oracle
    assert 0.0 < docking.rotation_share < 1.0


@pytest.mark.xfail(
    strict=True,
    reason="with the paper's W (rad² of roll and pitch added to m² of x and y) the selection "
    "by covariances calibrated from the paper-sized recording (154 samples) reaches only part "
    "of the oracle's reduction, also with the camera noise measured separately; the docking "
    "task's own score reaches it (full study and causes: docs/reproduce_paper.md)",
)
def test_paper_weights_selection_reaches_80_percent_of_the_oracles_reduction(
    quick: tuple[StudyResult, Path, list[str]],
) -> None:
    """The same bar with the paper's W: the whole 95 % interval of the share ≥ 0.8."""
    study = quick[0]
    assert study.pooled.reduction_verdict == "met", study.pooled.share_ci


def test_the_quoted_tables_hold_for_what_the_quick_study_shares_with_the_full_one(
    quick: tuple[StudyResult, Path, list[str]],
) -> None:
    """docs/reproduce_paper.md's tables (``docs/results/reproduce_paper_*.json``, the full
    study) against the quick study, which shares recording 1 and its calibration with it (no
    run of its own): the outlier counts exactly; Table II's errors on splits 1 and 2 (before and
    ours) within 0.005 mm and 0.005 deg (the table shows 0.01); every frame's σ calibrated on
    all kept samples within 0.005 mm or mrad (shown to 0.01). The quick study's manipulation
    runs are fewer and shorter, so those tables are only checked as rendered
    (tests/test_quoted_numbers.py)."""
    study = quick[0]
    _, recordings = read_results("reproduce_paper_recordings")
    assert paper_results.recording_rows(study)[0] == recordings[0]
    _, table = read_results("reproduce_paper_table_ii")
    quoted = {row["method"]: row for row in table}
    for row in paper_results.table_ii_rows(study):
        want = quoted[row["method"]]
        for seed, mm, deg in zip(
            row["seeds"], row["translation_mm"], row["rotation_deg"], strict=True
        ):
            i = want["seeds"].index(seed)
            assert mm == pytest.approx(want["translation_mm"][i], abs=0.005), (row["method"], seed)
            assert deg == pytest.approx(want["rotation_deg"][i], abs=0.005), (row["method"], seed)
    _, sigma = read_results("reproduce_paper_sigma")
    assert [row["frame"] for row in sigma][:-1] == list(
        study.first.recording.true_robot.chain.joint_names
    )
    for row, got in zip(sigma, study.sigma_full, strict=True):
        assert got == pytest.approx(row["default"], abs=0.005e-3, nan_ok=True), row["frame"]
