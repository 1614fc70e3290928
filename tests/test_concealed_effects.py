"""benchmarks/concealed_effects.py runs on tiny settings and writes its outputs (cannot rot)."""

from __future__ import annotations

import csv
from pathlib import Path

from benchmarks import concealed_effects


def test_concealed_effects_benchmark_runs_and_writes_table_and_csv(tmp_path: Path) -> None:
    lines: list[str] = []
    text, rows, numbers = concealed_effects.main(
        seeds=1,
        n=120,
        workers=1,
        names=["null", "backlash", "gear_dent"],
        bootstrap=5,
        out_dir=tmp_path,
        timing_n=130,
        timing_seeds=1,
        echo=lines.append,
    )
    assert text.startswith("| Scenario |") and text.count("\n") == 4
    assert rows["null"]["detected"] == 1.0 and rows["null"]["named_any"] == 0.0
    assert rows["backlash"]["detected"] == 1.0 and rows["backlash"]["heldout_ratio"] < 1.1
    assert rows["gear_dent"]["fdr"] == 0.0
    assert numbers["null_false_alarm"] == 0.0 and numbers["timing_max_s"] > 0.0
    assert any("false-discovery rate" in line for line in lines)
    with (tmp_path / "runs.csv").open() as handle:
        runs = list(csv.DictReader(handle))
    assert [r["scenario"] for r in runs] == ["null", "backlash", "gear_dent", "two_effects"]
    assert runs[1]["named"] == "backlash@j2s6s200_joint_2" and runs[1]["detected"] == "1"
    assert (tmp_path / "table.md").read_text().startswith(text)
    assert {r["scenario"] for r in csv.DictReader((tmp_path / "scenarios.csv").open())} == {
        "null",
        "backlash",
        "gear_dent",
    }


def test_judging_counts_wrong_names_and_accepts_only_the_right_joint() -> None:
    described = concealed_effects.scenarios(tuple(f"j{i}" for i in range(6)))
    run = concealed_effects.RunResult(
        "backlash", 0, 100, [("backlash", 2)], [], [], [], [], [], 1.0, 1.0, 1.0, 0.1
    )
    assert concealed_effects.judge(described["backlash"], run) == (False, 1)
    collinear = concealed_effects.RunResult(
        "collinear",
        0,
        100,
        [],
        [[("joint_compliance", 1), ("gear_periodic", 1)]],
        [],
        [],
        [],
        [],
        1.0,
        1.0,
        1.0,
        0.1,
    )
    assert concealed_effects.judge(described["collinear"], collinear) == (True, 0)


def test_real_benchmark_runs_on_a_shipped_recording_and_prints_its_table() -> None:
    """``concealed_effects.py --real`` on a tiny input: one effect, one seed, in the UR10e
    (21 usable samples: the sign-flip test states sizes there too; the FR3 goes through
    ``kincal discover`` in tests/service/test_discover_concealed_real.py)."""
    from benchmarks import concealed_real

    lines: list[str] = []
    text, rows, runs = concealed_real.main(
        seeds=1,
        workers=1,
        recordings=["ur10e"],
        effects=["backlash_direction"],
        sizes=(2.0,),
        echo=lines.append,
    )
    assert text.startswith("| Recording |") and len(rows) == 1 and len(runs) == 1
    assert {run.recording for run in runs} == {"ur10e"}
    assert all(run.truth > 0 and run.joint is not None for run in runs)
    assert any("unmodified UR10e: nothing named" in line for line in lines)


def test_real_benchmark_runs_on_a_ball_in_socket_recording_and_names_what_it_leaves_out() -> None:
    """``concealed_effects.py --real --recordings platonics``: the platonics Panda read as
    ``kincal discover --measurement point --point-distance 0.05`` reads it; a direction
    backlash at its stated detectability is concealed in the joint readings and the run is
    tabled; the pose-side link bending is not concealed and the note says why."""
    from benchmarks import concealed_real

    lines: list[str] = []
    text, rows, runs = concealed_real.main(
        seeds=1,
        workers=1,
        recordings=["platonics"],
        effects=["backlash_direction", "link_bending"],
        sizes=(1.0,),
        echo=lines.append,
    )
    assert text.startswith("| Recording |") and list(rows) == [
        ("platonics", "backlash_direction", 1.0)
    ]
    (run,) = runs
    assert run.joint is not None and run.truth > 0
    base = concealed_real.baseline("platonics")
    assert base.data.measurement is not None and base.data.measurement.name == "point"
    label = concealed_real.RECORDINGS["platonics"].label
    assert f"unmodified {label}: nothing named" in text
    assert f"{label}, not concealed: link_bending (the ball is held in a socket" in text
