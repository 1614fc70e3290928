"""ROS bags to recordings (issue 34): the tf tree's maths, still segments, and the real FR3
recording read back from a ROS 1, a rosbag2 sqlite3 and a rosbag2 MCAP bag."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from schemas.dataset import PoseDataset, read_dataset
from schemas.dataset.rosbag import BagRecording, MeasureSource, read_bag, read_robot_description
from schemas.dataset.still import (
    Measurements,
    StillSettings,
    mean_quaternion,
    still_segments,
    synchronise,
)
from schemas.dataset.tf_tree import (
    Edge,
    Placement,
    TfTree,
    compose,
    interpolate,
    invert,
    slerp,
)
from service.cli import common
from solver.errors import DatasetError
from tests.conftest import robot
from tests.schemas.bag_writer import FINGERS, FR3_POSES, PANDA_JOINTS, STORAGES, Truth, fr3_bags

RNG = np.random.default_rng(34)


def _random_quaternions(n: int) -> NDArray[np.float64]:
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _random_placements(n: int) -> Placement:
    return RNG.normal(size=(n, 3)), Rotation.from_quat(_random_quaternions(n))


def _matrix(pose: Placement) -> NDArray[np.float64]:
    p, r = pose
    m = np.tile(np.eye(4), (len(p), 1, 1))
    m[:, :3, :3] = r.as_matrix()
    m[:, :3, 3] = p
    return m


def test_compose_and_invert_are_the_homogeneous_matrices_product_and_inverse() -> None:
    a, b = _random_placements(50), _random_placements(50)
    np.testing.assert_allclose(_matrix(compose(a, b)), _matrix(a) @ _matrix(b), atol=1e-12)
    np.testing.assert_allclose(_matrix(invert(a)), np.linalg.inv(_matrix(a)), atol=1e-12)


def test_slerp_ends_at_its_ends_and_halves_the_arc() -> None:
    r0 = Rotation.from_quat(_random_quaternions(20))
    r1 = Rotation.from_quat(_random_quaternions(20))
    np.testing.assert_allclose(slerp(r0, r1, np.zeros(20)).as_quat(), r0.as_quat(), atol=1e-15)
    np.testing.assert_allclose((slerp(r0, r1, np.ones(20)).inv() * r1).magnitude(), 0, atol=1e-7)
    arc = (r0.inv() * r1).magnitude()  # the shorter arc, ≤ π
    middle = slerp(r0, r1, np.full(20, 0.5))
    np.testing.assert_allclose((r0.inv() * middle).magnitude(), arc / 2, atol=1e-12)
    np.testing.assert_allclose((middle.inv() * r1).magnitude(), arc / 2, atol=1e-12)


def _edge(parent: str, child: str, stamps: list[int], static: bool = False) -> Edge:
    p = RNG.normal(size=(len(stamps), 3))
    q = _random_quaternions(len(stamps))
    return Edge(parent, child, np.array(stamps, dtype=np.int64), p, q, static)


def test_a_chain_composes_up_to_the_common_ancestor_and_down() -> None:
    edges = {
        "base": _edge("world", "base", [0], static=True),
        "camera": _edge("base", "camera", [0], static=True),
        "mid": _edge("world", "mid", [0, 10, 20]),
        "board": _edge("mid", "board", [0], static=True),
    }
    tree = TfTree(edges, "test.bag")
    stamps = np.array([0, 10, 20], dtype=np.int64)
    poses = tree.pose("camera", "board", stamps)
    world_camera = compose(*(interpolate(edges[f], stamps)[:2] for f in ("base", "camera")))
    world_board = compose(*(interpolate(edges[f], stamps)[:2] for f in ("mid", "board")))
    want = compose(invert(world_camera), world_board)
    np.testing.assert_allclose(poses.translation_m, want[0], atol=1e-12)
    got = Rotation.from_quat(poses.quaternion_xyzw)
    np.testing.assert_allclose(got.as_matrix(), want[1].as_matrix(), atol=1e-12)
    assert poses.valid.all()
    np.testing.assert_array_equal(tree.dynamic_stamps("camera", "board"), stamps)
    assert not tree.pose("camera", "board", np.array([25], dtype=np.int64)).valid[0]


def test_frames_of_two_trees_are_refused_naming_the_roots() -> None:
    tree = TfTree(
        {"a": _edge("world", "a", [0], True), "b": _edge("tracker", "b", [0, 1])}, "x.bag"
    )
    with pytest.raises(DatasetError, match=r"never connected.*roots: tracker, world"):
        tree.chain("a", "b")
    with pytest.raises(DatasetError, match="'nowhere' is not in the tf tree"):
        tree.chain("a", "nowhere")


def test_mean_quaternion_ignores_signs_and_keeps_the_first_ones() -> None:
    q = _random_quaternions(1)
    flipped = np.vstack([q, -q, q, -q])
    np.testing.assert_allclose(mean_quaternion(flipped), q[0], atol=1e-15)
    np.testing.assert_allclose(mean_quaternion(-flipped), -q[0], atol=1e-15)


def test_still_segments_are_the_runs_below_the_tolerance() -> None:
    stamps = np.arange(10, dtype=np.int64) * 10_000_000  # 100 Hz
    joints = np.array([0, 0, 0, 0.1, 0.2, 0.2, 0.2, 0.2, 0.3, 0.3])[:, None]
    assert still_segments(stamps, joints, 1e-3) == [(0, 3), (4, 8), (8, 10)]
    measured = Measurements(np.array([15_000_000, 55_000_000]), np.ones((2, 3)), None)
    samples = synchronise(stamps, joints, measured, StillSettings(1e-3, 0.02, 0.0))
    assert (samples.n_samples, samples.n_too_short, samples.n_no_measurement) == (2, 1, 0)
    assert samples.n_moving == 1  # the message at 0.1 rad
    np.testing.assert_array_equal(samples.joint_positions[:, 0], [0.0, 0.2])


def test_the_cli_defaults_are_the_still_settings() -> None:
    defaults = StillSettings()
    cli = (common.STILL_TOLERANCE_RAD_S, common.STILL_WINDOW_S, common.CLOCK_TOLERANCE_S)
    assert cli == (defaults.tolerance_rad_s, defaults.window_s, defaults.clock_tolerance_s)


# --- the FR3 recording through bags --------------------------------------------------------


@pytest.fixture(scope="module")
def bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, Truth]]:
    return fr3_bags(tmp_path_factory)


@pytest.fixture(scope="module")
def recorded() -> PoseDataset:
    return read_dataset(FR3_POSES, PANDA_JOINTS)


def _read(path: Path, measure: str) -> BagRecording:
    return read_bag(
        path,
        "/joint_states",
        MeasureSource.parse(measure),
        joint_names=PANDA_JOINTS,
        other_joint_names=FINGERS,
    )


def assert_same_rows(got: PoseDataset, want: PoseDataset, *, atol: float = 1e-9) -> None:
    """Joints and positions within ``atol``; quaternions equal up to their sign."""
    assert got.joint_names == want.joint_names and got.n_samples == want.n_samples
    np.testing.assert_allclose(got.joint_positions, want.joint_positions, rtol=0, atol=atol)
    np.testing.assert_allclose(got.position_m, want.position_m, rtol=0, atol=atol)
    if want.quaternion_xyzw is None:
        assert got.quaternion_xyzw is None
        return
    assert got.quaternion_xyzw is not None
    sign = np.sign(np.sum(got.quaternion_xyzw * want.quaternion_xyzw, axis=1))[:, None]
    np.testing.assert_allclose(sign * got.quaternion_xyzw, want.quaternion_xyzw, atol=atol)


@pytest.mark.parametrize("storage", STORAGES)
def test_every_bag_storage_carries_the_robots_urdf_the_last_message_counting(
    bags: dict[str, tuple[Path, Truth]], storage: str
) -> None:
    assert read_robot_description(bags[storage][0]) == robot("panda").urdf_xml


@pytest.mark.parametrize("storage", STORAGES)
def test_every_bag_storage_gives_back_the_recording_and_drops_exactly_the_moving(
    bags: dict[str, tuple[Path, Truth]], recorded: PoseDataset, storage: str
) -> None:
    path, truth = bags[storage]
    recording = _read(path, "tf:camera_link:board")
    assert_same_rows(recording.dataset, recorded)
    samples = recording.samples
    assert (samples.n_messages, samples.n_moving) == (truth.n_messages, truth.n_moving)
    assert (samples.n_too_short, samples.n_no_measurement) == (1, 1)
    assert recording.dataset.time_s is not None and np.all(np.diff(recording.dataset.time_s) > 0)


def test_measurements_near_a_holds_ends_are_left_to_the_clock_tolerance() -> None:
    stamps = np.arange(0, 301, 10, dtype=np.int64) * 1_000_000  # still for 0.3 s
    at = np.array([10, 150, 295]) * 1_000_000
    measured = Measurements(at, np.array([[1.0, 0, 0], [2.0, 0, 0], [6.0, 0, 0]]), None)
    joints = np.zeros((len(stamps), 2))
    samples = synchronise(stamps, joints, measured, StillSettings(clock_tolerance_s=0.02))
    np.testing.assert_array_equal(samples.position_m, [[2.0, 0, 0]])
    samples = synchronise(stamps, joints, measured, StillSettings(clock_tolerance_s=0.0))
    np.testing.assert_array_equal(samples.position_m, [[3.0, 0, 0]])  # the mean of all three


@pytest.mark.parametrize("storage", ["ros1", "mcap"])
def test_one_sample_per_capture_message_while_still(
    bags: dict[str, tuple[Path, Truth]], recorded: PoseDataset, storage: str
) -> None:
    path, truth = bags[storage]
    recording = read_bag(
        path,
        "/joint_states",
        MeasureSource.parse("tf:camera_link:board"),
        joint_names=PANDA_JOINTS,
        capture="/capture",
    )
    assert_same_rows(recording.dataset, recorded)
    samples = recording.samples
    assert (samples.n_captures, samples.n_moving, samples.n_no_measurement) == (
        truth.n_captures,
        2,  # the capture amid a move, and amid the hold shorter than the window
        1,
    )
    assert "114 samples (one per capture message); dropped: 2 of 117 captures while moving, 1 " in (
        recording.report()
    )


@pytest.mark.parametrize(
    ("measure", "rotation"),
    [
        ("pose:/board_pose", True),
        ("pose:/board_transform", True),
        ("point:/tracker_point", False),
    ],
)
def test_pose_and_point_topics_are_measurements_too(
    bags: dict[str, tuple[Path, Truth]], recorded: PoseDataset, measure: str, rotation: bool
) -> None:
    recording = _read(bags["mcap"][0] / "fr3_mcap.mcap", measure)  # its storage file will do
    want = recorded
    if not rotation:
        want = PoseDataset(
            recorded.joint_names, recorded.joint_positions, recorded.position_m, None
        )
    assert_same_rows(recording.dataset, want)
    assert recording.dataset.measures_rotation is rotation


@pytest.mark.parametrize(
    ("joint_states", "measure", "message"),
    [
        ("/joints", "tf:/camera_link:board", "no topic '/joints' in the bag; its topics: "),
        ("/tf", "tf:camera_link:board", "'/tf' holds tf2_msgs/msg/TFMessage, --joint-states"),
        ("/joint_states", "pose:/tf", "--measure pose:… needs geometry_msgs/msg/PoseStamped"),
        ("/joint_states", "tf:camera_link:robot_base", "roots: camera_link, world"),
        ("/joint_states", "tf:camera_link:mid", "is static"),
    ],
)
def test_a_wrong_topic_or_frame_is_refused_naming_what_the_bag_holds(
    bags: dict[str, tuple[Path, Truth]], joint_states: str, measure: str, message: str
) -> None:
    with pytest.raises(DatasetError, match=message.replace("(", r"\(")) as caught:
        read_bag(bags["ros1"][0], joint_states, MeasureSource.parse(measure))
    assert "\n" not in str(caught.value)


def test_joint_names_that_are_not_the_robots_are_refused_listing_both(
    bags: dict[str, tuple[Path, Truth]],
) -> None:
    with pytest.raises(
        DatasetError, match=r"names joints panda_finger_joint1.*chain joints are a, b"
    ):
        read_bag(
            bags["sqlite3"][0],
            "/joint_states",
            MeasureSource.parse("tf:camera_link:board"),
            joint_names=("a", "b"),
        )


def test_a_bag_without_a_long_enough_hold_is_refused(bags: dict[str, tuple[Path, Truth]]) -> None:
    with pytest.raises(DatasetError, match="no still segment to sample: 116 still segment"):
        read_bag(
            bags["ros1"][0],
            "/joint_states",
            MeasureSource.parse("tf:camera_link:board"),
            settings=StillSettings(window_s=5.0),
        )


@pytest.mark.parametrize(
    "text", ["tf:a", "pose:", "camera:x", "tf:a:b:c", "calibration-data:/c:a:b:c"]
)
def test_a_malformed_source_is_refused(text: str) -> None:
    forms = "tf:PARENT:CHILD, pose:TOPIC, point:TOPIC or calibration-data:TOPIC"
    with pytest.raises(DatasetError, match=f"give {forms}"):
        MeasureSource.parse(text)


def test_not_a_bag_is_one_line(tmp_path: Path) -> None:
    fake = tmp_path / "broken.bag"
    fake.write_bytes(b"not a bag at all")
    with pytest.raises(DatasetError, match=r"broken\.bag: cannot read as a ROS bag") as caught:
        read_bag(fake, "/joint_states", MeasureSource.parse("tf:a:b"))
    assert "\n" not in str(caught.value)
