"""robot_calibration capture bags (issue 34): the real FR3 recording written as
``robot_calibration_msgs/CalibrationData`` messages — a checkerboard's corners as the camera sees
them (placed by Pinocchio) and in the board's own frame — in a ROS 1 bag (definitions inside)
and in a rosbag2 sqlite3 bag without definitions (as ROS 2 Humble records), read back to the
CSV's rows through ``kincal import`` / ``kincal calibrate`` (and an HTTP upload:
tests/service/api/test_bag_upload.py); the capture
whose camera saw two corners is dropped and counted; wrong sensor names are one line naming
the sensors the bag holds."""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import pytest

from schemas.dataset import read_dataset
from schemas.dataset.rosbag import MeasureSource, read_bag
from solver.errors import DatasetError
from tests.schemas.bag_writer import CAPTURE_TOPIC, FR3_POSES, PANDA_JOINTS, capture_bags
from tests.schemas.test_rosbag import assert_same_rows
from tests.service.cli_support import run, run_ok

STORAGES = ("ros1", "sqlite3")
MEASURE = f"calibration-data:{CAPTURE_TOPIC}"


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    return capture_bags(tmp_path_factory)


@pytest.mark.parametrize("storage", STORAGES)
def test_a_capture_bag_gives_back_the_recording_one_row_per_capture(
    bags: dict[str, Path], storage: str
) -> None:
    recording = read_bag(
        bags[storage], None, MeasureSource.parse(MEASURE), joint_names=PANDA_JOINTS
    )
    assert_same_rows(recording.dataset, read_dataset(FR3_POSES, PANDA_JOINTS))
    samples = recording.samples
    assert (samples.n_captures, samples.n_no_measurement, samples.n_moving) == (115, 1, 0)
    assert "114 samples (one per capture message)" in recording.report()


def test_a_bag_without_definitions_is_read_with_the_shipped_ones(bags: dict[str, Path]) -> None:
    from rosbags.highlevel import AnyReader
    from rosbags.highlevel.anyreader import AnyReaderError

    with pytest.raises(AnyReaderError, match="no type definitions"), AnyReader([bags["sqlite3"]]):
        pass  # rosbags alone cannot decode what Humble recorded


def test_sensors_the_bag_does_not_hold_are_named_with_those_it_does(
    bags: dict[str, Path],
) -> None:
    measure = MeasureSource.parse(f"{MEASURE}:rgbd:arm")
    with pytest.raises(DatasetError, match=r"hold the sensors arm, camera, not rgbd and arm"):
        read_bag(bags["ros1"], None, measure, joint_names=PANDA_JOINTS)
    with pytest.raises(DatasetError, match="calibration-data:TOPIC"):
        MeasureSource.parse("calibration-data:")


def test_kincal_import_and_calibrate_read_a_capture_bag_without_joint_states(
    bags: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    flags = ["--robot", "panda", "--measure", MEASURE]
    out = tmp_path / "recording.parquet"
    with contextlib.redirect_stdout(io.StringIO()):
        run_ok(["import", bags["sqlite3"], *flags, "-o", out])
    assert_same_rows(read_dataset(out, PANDA_JOINTS), read_dataset(FR3_POSES, PANDA_JOINTS))
    results = {}
    for name, source in (("bag", bags["ros1"]), ("csv", FR3_POSES)):
        result = tmp_path / f"{name}.json"
        extra = flags[2:] if name == "bag" else []
        code, _, err = run(
            ["calibrate", source, "--robot", "panda", *extra, "--no-heldout", "-o", result],
            capsys,
            monkeypatch,
        )
        assert code == 0, err
        results[name] = json.loads(result.read_bytes())["evaluation"]
    assert results["bag"] == pytest.approx(results["csv"], abs=1e-9)
