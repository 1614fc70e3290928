"""Issue 34's acceptance through ``kincal``: the real FR3 recording written as a ROS 1, a rosbag2
sqlite3 and a rosbag2 MCAP bag calibrates as the CSV does (held-out error within 1e-6 m), ``kincal
import`` writes the CSV's rows, and a bad bag is exit code 2 with one line naming the fix."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import pytest

from schemas.dataset import read_dataset
from tests.conftest import REPO
from tests.schemas.bag_writer import FR3_POSES, PANDA_JOINTS, STORAGES, Truth, fr3_bags
from tests.schemas.test_rosbag import assert_same_rows
from tests.service.cli_support import run, run_ok

BAG_FLAGS = ["--robot", "panda", "--joint-states", "/joint_states"]
TF = ["--measure", "tf:camera_link:board"]


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, Truth]]:
    return fr3_bags(tmp_path_factory)


@pytest.fixture(scope="module")
def csv_result(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    out = tmp_path_factory.mktemp("csv") / "calibration.json"
    with contextlib.redirect_stdout(io.StringIO()):
        run_ok(["calibrate", FR3_POSES, "--robot", "panda", "-o", out])
    result: dict[str, Any] = json.loads(out.read_bytes())
    return result


@pytest.mark.parametrize("storage", STORAGES)
def test_calibrating_a_bag_equals_calibrating_the_csv(
    bags: dict[str, tuple[Path, Truth]],
    csv_result: dict[str, Any],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    storage: str,
) -> None:
    path, truth = bags[storage]
    out = tmp_path / "calibration.json"
    heldout = storage == "ros1"  # one storage is enough for the slow part
    flags = [*BAG_FLAGS, *TF, *([] if heldout else ["--no-heldout"])]
    code, text, err = run(["calibrate", path, *flags, "-o", out], capsys, monkeypatch)
    assert code == 0, err
    report = (
        f"{path.name}: 114 samples (one per still segment); dropped: 1 still segment(s) too short, "
        f"1 without a measurement; {truth.n_moving} of {truth.n_messages} joint-state messages "
        "while moving"
    )
    assert report in text
    if storage == "ros1":  # the example docs/ros.md shows
        assert report in (REPO / "docs" / "ros.md").read_text(encoding="utf-8")
    result = json.loads(out.read_bytes())
    for side in ("train", "heldout") if heldout else ("train",):
        got, want = result["fit"]["after"][side], csv_result["fit"]["after"][side]
        assert got["n_samples"] == want["n_samples"]
        assert got["translation_mean_mm"] == pytest.approx(want["translation_mean_mm"], abs=1e-3)
        assert got["rotation_mean_deg"] == pytest.approx(want["rotation_mean_deg"], abs=1e-6)


def test_import_writes_the_recording_the_csv_holds(
    bags: dict[str, tuple[Path, Truth]],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out = tmp_path / "recording.parquet"
    path, _ = bags["ros1"]
    code, text, err = run(["import", path, *BAG_FLAGS, *TF, "-o", out], capsys, monkeypatch)
    assert code == 0, err
    assert f"{out}  recording, 114 samples" in text
    written = read_dataset(out, PANDA_JOINTS)
    assert_same_rows(written, read_dataset(FR3_POSES, PANDA_JOINTS))


def test_import_without_a_robot_names_the_columns_by_the_topic(
    bags: dict[str, tuple[Path, Truth]],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out = tmp_path / "recording.csv"
    args = ["import", bags["mcap"][0], "--joint-states", "/joint_states", "--measure"]
    code, _, err = run([*args, "point:/tracker_point", "-o", out], capsys, monkeypatch)
    assert code == 0, err
    header = out.read_text().splitlines()[0].split(",")
    assert header[:3] == ["sample_id", "panda_joint7", "panda_joint6"]  # the topic's order
    assert "panda_finger_joint1" in header and "qw" not in header


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--joint-states", "/joints", *TF], "no topic '/joints' in the bag; its topics: "),
        (
            ["--joint-states", "/joint_states", "--measure", "tf:camera_link:robot_base"],
            "never connected in the tf tree",
        ),
        (["--joint-states", "/joint_states", *TF, "--still-window", "5"], "no still segment"),
        (["--joint-states", "/joint_states"], "give --joint-states TOPIC and --measure SOURCE"),
        (["--joint-states", "/joint_states", *TF, "--capture", "/nope"], "no topic '/nope'"),
    ],
)
def test_a_bad_bag_is_exit_code_2_and_one_line(
    bags: dict[str, tuple[Path, Truth]],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    args: list[str],
    message: str,
) -> None:
    for command in ("calibrate", "import"):
        cli_args = [command, bags["sqlite3"][0], "--robot", "panda", *args, "--out-dir", tmp_path]
        code, out, err = run(cli_args, capsys, monkeypatch)
        assert code == 2, (command, out, err)
        assert err.startswith("kincal: error: ") and message in err, err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_a_bag_of_another_robot_is_refused_listing_both_joint_sets(
    bags: dict[str, tuple[Path, Truth]],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    args = ["calibrate", bags["ros1"][0], "--robot", "ur10", "--joint-states", "/joint_states"]
    code, _, err = run([*args, *TF, "--out-dir", tmp_path], capsys, monkeypatch)
    assert code == 2 and len(err.strip().splitlines()) == 1
    assert (
        "names joints panda_finger_joint1" in err and "chain joints are shoulder_pan_joint" in err
    )


def test_bag_options_without_a_bag_are_refused(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    args = ["calibrate", FR3_POSES, "--robot", "panda", "--joint-states", "/joint_states"]
    code, _, err = run(args, capsys, monkeypatch)
    assert code == 2 and "fr3_poses.csv is not one" in err
