"""Issue 34's acceptance through ``kincal``: the real FR3 recording written as a ROS 1, a rosbag2
sqlite3 and a rosbag2 MCAP bag calibrates as the CSV does (held-out error within 1e-6 m), ``kincal
import`` writes the CSV's rows, and a bad bag is exit code 2 with one line naming the fix.
Without --robot/--urdf/--dh the URDF a bag carries on /robot_description is the robot: the
calibration equals --robot panda's, and ``kincal import`` writes that URDF next to the
recording."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import pytest

from schemas.dataset import read_dataset
from tests.conftest import REPO, robot
from tests.schemas.bag_writer import (
    FR3_POSES,
    PANDA_JOINTS,
    STORAGES,
    Truth,
    capture_bags,
    fr3_bags,
    write_robot_description_bag,
)
from tests.schemas.test_rosbag import assert_same_rows
from tests.service.cli_support import run, run_ok

BAG_FLAGS = ["--robot", "panda", "--joint-states", "/joint_states"]
TF = ["--measure", "tf:camera_link:board"]
ROBOT_LINE = (
    "robot: the URDF on /robot_description in {} (13 links; chain panda_link0 → panda_link7, "
    "7 joints)"
)
"""What kincal says of the bag's URDF: the panda's tip is the link of its last joint before the
hand's fingers branch off (a link fixed to the flange: the same calibration)."""


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


@pytest.fixture(scope="module")
def ros1_result(
    bags: dict[str, tuple[Path, Truth]], tmp_path_factory: pytest.TempPathFactory
) -> tuple[dict[str, Any], str]:
    """The ROS 1 bag calibrated with --robot panda and held-out splits: result and output."""
    out = tmp_path_factory.mktemp("ros1") / "calibration.json"
    with contextlib.redirect_stdout(io.StringIO()) as printed:
        run_ok(["calibrate", bags["ros1"][0], *BAG_FLAGS, *TF, "-o", out])
    return json.loads(out.read_bytes()), printed.getvalue()


@pytest.mark.parametrize("storage", STORAGES)
def test_calibrating_a_bag_equals_calibrating_the_csv(
    bags: dict[str, tuple[Path, Truth]],
    csv_result: dict[str, Any],
    ros1_result: tuple[dict[str, Any], str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    storage: str,
) -> None:
    path, truth = bags[storage]
    out = tmp_path / "calibration.json"
    heldout = storage == "ros1"  # one storage is enough for the slow part
    if heldout:
        result, text = ros1_result
        assert "/robot_description" not in text  # --robot wins, silently
    else:  # the robot: the panda's URDF the bag carries
        flags = [*BAG_FLAGS[2:], *TF, "--no-heldout", "-o", out]
        code, text, err = run(["calibrate", path, *flags], capsys, monkeypatch)
        assert code == 0, err
        assert ROBOT_LINE.format(path.name) in text.splitlines()
        result = json.loads(out.read_bytes())
    report = (
        f"{path.name}: 114 samples (one per still segment); dropped: 1 still segment(s) too short, "
        f"1 without a measurement; {truth.n_moving} of {truth.n_messages} joint-state messages "
        "while moving"
    )
    assert report in text
    if storage == "ros1":  # the example docs/ros.md shows
        assert report in (REPO / "docs" / "ros.md").read_text(encoding="utf-8")
    sides = ("train", "heldout") if heldout else ("train",)
    assert_same_fit(result, csv_result, sides, translation_mm=1e-3, rotation_deg=1e-6)


def assert_same_fit(
    got: dict[str, Any],
    want: dict[str, Any],
    sides: tuple[str, ...],
    *,
    translation_mm: float,
    rotation_deg: float,
) -> None:
    """Two results' mean errors after calibration, per side (train, heldout), within these."""
    for side in sides:
        got_fit, want_fit = got["fit"]["after"][side], want["fit"]["after"][side]
        assert got_fit["n_samples"] == want_fit["n_samples"], side
        tolerances = {"translation_mean_mm": translation_mm, "rotation_mean_deg": rotation_deg}
        for key, tolerance in tolerances.items():
            assert got_fit[key] == pytest.approx(want_fit[key], rel=0, abs=tolerance), (side, key)


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
    assert "/robot_description" not in text and not out.with_suffix(".urdf").exists()
    written = read_dataset(out, PANDA_JOINTS)
    assert_same_rows(written, read_dataset(FR3_POSES, PANDA_JOINTS))


def test_without_a_robot_option_the_bags_urdf_is_the_robot(
    bags: dict[str, tuple[Path, Truth]],
    ros1_result: tuple[dict[str, Any], str],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    path = bags["ros1"][0]
    out = tmp_path / "calibration.json"
    args = ["calibrate", path, *BAG_FLAGS[2:], *TF, "-o", out]
    code, text, err = run(args, capsys, monkeypatch)
    assert code == 0, err
    assert text.splitlines()[0] == ROBOT_LINE.format(path.name)
    assert ROBOT_LINE.format(path.name) in (REPO / "docs" / "ros.md").read_text(encoding="utf-8")
    got, want = json.loads(out.read_bytes()), ros1_result[0]
    assert got["robot"]["name"] == "panda" and got["robot"]["tip_frame"] == "panda_link7"
    assert got["robot"]["urdf_sha256"] == want["robot"]["urdf_sha256"]
    assert_same_fit(got, want, ("train", "heldout"), translation_mm=1e-9, rotation_deg=1e-9)


def test_import_writes_the_bags_urdf_next_to_the_recording(
    bags: dict[str, tuple[Path, Truth]],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out, urdf = tmp_path / "recording.csv", tmp_path / "recording.urdf"
    path = bags["mcap"][0]
    args = ["import", path, *BAG_FLAGS[2:], "--measure", "point:/tracker_point", "-o", out]
    urdf.write_text("<robot name='mine'/>")
    code, text, err = run(args, capsys, monkeypatch)
    assert code == 2 and f"{urdf} already holds another file" in err  # the user's: kept
    assert urdf.read_text() == "<robot name='mine'/>" and not out.exists()
    urdf.unlink()
    code, text, err = run(args, capsys, monkeypatch)
    assert code == 0, err
    assert ROBOT_LINE.format(path.name) in text.splitlines()
    assert f"{urdf}  the robot's URDF (from /robot_description)" in text
    assert f"--urdf {urdf} --base panda_link0 --tip panda_link7" in text
    assert urdf.read_text(encoding="utf-8") == robot("panda").urdf_xml
    header = out.read_text().splitlines()[0].split(",")
    assert header[1:8] == list(PANDA_JOINTS) and "panda_finger_joint1" not in header
    code, text, err = run(args, capsys, monkeypatch)  # the same URDF again: replaced, listed
    assert code == 0 and f"{urdf}  the robot's URDF (from /robot_description) (replaced)" in text


def test_import_of_a_bag_without_a_robot_names_the_columns_by_the_topic(
    tmp_path_factory: pytest.TempPathFactory,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    out = tmp_path / "recording.csv"
    bag = capture_bags(tmp_path_factory)["ros1"]  # no /robot_description
    args = ["import", bag, "--measure", "calibration-data:/calibration_data", "-o", out]
    code, text, err = run(args, capsys, monkeypatch)
    assert code == 0, err
    header = out.read_text().splitlines()[0].split(",")
    assert header[:3] == ["sample_id", "panda_joint7", "panda_joint6"]  # the topic's order
    assert "panda_finger_joint1" in header and "robot:" not in text
    assert not out.with_suffix(".urdf").exists()
    code, _, err = run(["calibrate", bag, *args[2:4], "-o", out], capsys, monkeypatch)
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert (
        "captures.bag: no robot given and no URDF on /robot_description in the bag; pass "
        "--robot NAME or --urdf FILE --base FRAME --tip FRAME, or record /robot_description"
    ) in err


@pytest.mark.parametrize(
    ("urdf_xml", "message"),
    [
        ("<robot name='x'><link name='a'></robot>", ": not well-formed XML (mismatched tag"),
        ("<robto name='x'/>", ": the root element is <robto>, expected <robot>"),
        (
            "<robot name='x'><link name='a'/><link name='b'/><joint name='j' type='fixed'>"
            "<parent link='a'/><child link='b'/></joint></robot>",
            ": no movable joint below the root link a: not an arm",
        ),
    ],
)
def test_a_bad_urdf_on_the_topic_is_exit_code_2_and_one_line(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    urdf_xml: str,
    message: str,
) -> None:
    bag = tmp_path / "bad.bag"
    write_robot_description_bag(bag, "ros1", urdf_xml)
    for command in ("calibrate", "import"):
        args: list[object] = [command, bag, *BAG_FLAGS[2:], *TF, "--out-dir", tmp_path]
        code, out, err = run(args, capsys, monkeypatch)
        assert code == 2, (command, out, err)
        assert err.startswith("kincal: error: the URDF on /robot_description in bad.bag" + message)
        assert err.strip().endswith("or pass --robot NAME / --urdf FILE instead"), err
        assert len(err.strip().splitlines()) == 1 and "Traceback" not in err


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
        cli_args: list[object] = [
            command,
            bags["sqlite3"][0],
            "--robot",
            "panda",
            *args,
            "--out-dir",
            tmp_path,
        ]
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
