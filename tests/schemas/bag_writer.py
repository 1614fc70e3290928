"""ROS bags written from a recording, as a hand-eye or tracker setup records them: 500 Hz
``/joint_states`` that hold each recorded configuration still (with jitter far below the still
tolerance) and move between captures, 30 Hz ``/tf`` camera_link → mid → board (the first edge
static on ``/tf_static``, the second carrying the recorded pose composed with its inverse), plus
a hold too short to count and a hold while the measurement is not published; and the robot's
URDF on ``/robot_description`` (``std_msgs/String``, one latched message), as robot_calibration
records it."""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation, Slerp

from schemas.dataset import PoseDataset, read_dataset
from tests.conftest import REAL_DATA, computed_once, robot

FR3_POSES = REAL_DATA / "philnad_fr3_eye_in_hand" / "fr3_poses.csv"
PANDA_JOINTS = tuple(f"panda_joint{i}" for i in range(1, 8))
NS = 1_000_000_000
START_NS = 1_700_000_000 * NS
JOINT_DT_NS = 2_000_000  # 500 Hz
TF_DT_NS = NS // 30
HOLD = 150  # joint-state messages per hold: 0.3 s
MOVE = 100  # a move's length in messages: 0.2 s, 99 of them between two holds
SHORT_HOLD = 50  # 0.1 s: shorter than the default still window (0.2 s)
JITTER_RAD = 2e-8  # alternating, so a hold's mean is its configuration
DETOUR_RAD = 0.1  # every joint swings out and back between captures (two captures may share one)
FINGERS = ("panda_finger_joint1", "panda_finger_joint2")
CAMERA_M_MID = (np.array([0.1, -0.05, 0.3]), np.array([0.2, -0.1, 0.3, 0.9]) / np.sqrt(0.95))
SHORT_AFTER, UNMEASURED_AFTER = 20, 50  # the extra holds follow these rows


def _header(types: Any, ros1: bool, stamp: int, frame: str) -> Any:
    """A ``std_msgs/Header`` at ``stamp`` ns in ``frame`` (ROS 1's with its ``seq``)."""
    time = types["builtin_interfaces/msg/Time"](sec=stamp // NS, nanosec=stamp % NS)
    extra = {"seq": 0} if ros1 else {}
    return types["std_msgs/msg/Header"](stamp=time, frame_id=frame, **extra)


def _se3(pose: tuple[NDArray[np.float64], NDArray[np.float64]]) -> pin.SE3:
    """A (translation m, quaternion x, y, z, w) pose as Pinocchio's SE3."""
    return pin.XYZQUATToSE3(np.concatenate([pose[0], pose[1]]))


@dataclass(frozen=True)
class Truth:
    """What reading the bag must find."""

    n_messages: int
    n_moving: int
    n_too_short: int = 1
    n_no_measurement: int = 1
    n_captures: int = 0
    """/capture: one message amid every hold (the extra two too) and amid the first move."""


@dataclass(frozen=True)
class _Stretch:
    n: int
    joints: Callable[[NDArray[np.float64]], NDArray[np.float64]]  # u (m,) in [0, 1) -> (m, k)
    pose: Callable[[float], tuple[NDArray[np.float64], NDArray[np.float64]]]
    moving: bool
    measured: bool = True


def _hold(q: NDArray[np.float64], pose: Any, n: int = HOLD, measured: bool = True) -> _Stretch:
    return _Stretch(n, lambda u: np.tile(q, (len(u), 1)), lambda _: pose, False, measured)


def _move(q0: Any, q1: Any, pose0: Any, pose1: Any) -> _Stretch:
    def joints(u: NDArray[np.float64]) -> NDArray[np.float64]:
        s = (1 - np.cos(np.pi * u)) / 2
        return q0 + np.outer(s, q1 - q0) + DETOUR_RAD * np.sin(np.pi * u)[:, None] ** 2

    def pose(u: float) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        s = np.array([(1 - np.cos(np.pi * u)) / 2])
        p = pose0[0] + s[0] * (pose1[0] - pose0[0])
        ends = Rotation.from_quat(np.stack([pose0[1], pose1[1]]))
        return p, Slerp([0.0, 1.0], ends)(s).as_quat()[0]

    return _Stretch(MOVE, joints, pose, True)


def _stretches(ds: PoseDataset) -> list[_Stretch]:
    assert ds.quaternion_xyzw is not None
    q, poses = ds.joint_positions, list(zip(ds.position_m, ds.quaternion_xyzw, strict=True))
    stretches = [_hold(q[0], poses[0])]
    for k in range(1, len(q)):
        extra = {SHORT_AFTER: SHORT_HOLD, UNMEASURED_AFTER: HOLD}.get(k - 1)
        if extra is not None:  # an extra hold half-way, then on to row k
            mid_q = (q[k - 1] + q[k]) / 2
            mid_pose = _move(q[k - 1], q[k], poses[k - 1], poses[k]).pose(0.5)
            stretches += [
                _move(q[k - 1], mid_q, poses[k - 1], mid_pose),
                _hold(mid_q, mid_pose, extra, measured=k - 1 != UNMEASURED_AFTER),
                _move(mid_q, q[k], mid_pose, poses[k]),
            ]
        else:
            stretches.append(_move(q[k - 1], q[k], poses[k - 1], poses[k]))
        stretches.append(_hold(q[k], poses[k]))
    return stretches


def _streams(ds: PoseDataset, seed: int) -> tuple[list[Any], list[Any], list[int], Truth]:
    """(stamp ns, joints) of every joint-state message, (stamp ns, cameraMboard) of every
    measurement, the capture times ns, and the truth."""
    rng = np.random.default_rng(seed)
    joint_msgs: list[tuple[int, NDArray[np.float64]]] = []
    tf_msgs: list[tuple[int, Any]] = []
    moving = 0
    start = 0  # message index where the stretch starts
    captures: list[int] = []
    for stretch in _stretches(ds):
        first = 1 if stretch.moving else 0  # a move's first message is the previous hold's last
        u = np.arange(first, stretch.n) / stretch.n
        joints = stretch.joints(u)
        if not stretch.moving:
            joints = joints + JITTER_RAD * (-1.0) ** np.arange(len(u))[:, None]
        moving += len(u) if stretch.moving else 0
        for i, row in enumerate(joints):
            jitter = int(rng.integers(-200_000, 200_000))  # ±0.2 ms
            joint_msgs.append((START_NS + (start + i) * JOINT_DT_NS + jitter, row))
        t0, t1 = START_NS + start * JOINT_DT_NS, START_NS + (start + len(u)) * JOINT_DT_NS
        if not stretch.moving or len(captures) == 1:  # every hold, and the first move
            captures.append((t0 + t1) // 2)
        if stretch.measured:
            for t in range(-(-(t0 - START_NS) // TF_DT_NS), -(-(t1 - START_NS) // TF_DT_NS)):
                stamp = START_NS + t * TF_DT_NS
                pose = stretch.pose((stamp - t0) / (t1 - t0) if stretch.moving else 0.0)
                jitter = int(rng.integers(-1_000_000, 1_000_000))
                if not stretch.moving:  # stays inside the hold
                    jitter = 0
                tf_msgs.append((stamp + jitter, pose))
        start += len(u)
    return joint_msgs, tf_msgs, captures, Truth(len(joint_msgs), moving, n_captures=len(captures))


ROBOT_DESCRIPTION = "/robot_description"
STORAGES = {"ros1": "fr3.bag", "sqlite3": "fr3_sqlite3", "mcap": "fr3_mcap"}
"""Each storage and the name of its bag (a file for ROS 1, a rosbag2 folder otherwise)."""


def fr3_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, tuple[Path, Truth]]:
    """The real FR3 recording written as a bag of each storage, once per test run, with the
    built-in panda's URDF (the FR3's joints) on /robot_description."""

    def write_all(folder: Path) -> dict[str, tuple[Path, Truth]]:
        ds = read_dataset(FR3_POSES, PANDA_JOINTS)
        urdf_xml = robot("panda").urdf_xml
        return {
            storage: (folder / name, write_bag(folder / name, ds, storage, urdf_xml=urdf_xml))
            for storage, name in STORAGES.items()
        }

    return computed_once(tmp_path_factory, "fr3-bags", write_all)


def _store(storage: str) -> tuple[Any, Callable[[Any, str], Any]]:
    """The typestore a ``storage`` (ros1, sqlite3, mcap) bag is written with (ROS 1 Noetic's, with
    tf2_msgs; else ROS 2 Humble's) and its serializer."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ros1 = storage == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    if ros1:  # noetic's store lacks tf2_msgs
        tf_msg = "geometry_msgs/TransformStamped[] transforms"
        store.register(get_types_from_msg(tf_msg, "tf2_msgs/msg/TFMessage"))
    return store, store.serialize_ros1 if ros1 else store.serialize_cdr


def _writer(path: Path, storage: str) -> Any:
    """rosbags' writer of a ``storage`` bag at ``path`` (ROS 1 file; rosbag2 folder, version 9)."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2

    if storage == "ros1":
        return Writer1(path)
    plugin = StoragePlugin.SQLITE3 if storage == "sqlite3" else StoragePlugin.MCAP
    return Writer2(path, version=9, storage_plugin=plugin)


def write_robot_description_bag(path: Path, storage: str, text: str) -> None:
    """A bag holding only ``text`` on /robot_description (a bad URDF's bag: the robot is read
    before any other topic)."""
    store, serialize = _store(storage)
    kind = "std_msgs/msg/String"
    with _writer(path, storage) as writer:
        connection = writer.add_connection(ROBOT_DESCRIPTION, kind, typestore=store)
        writer.write(connection, START_NS, serialize(store.types[kind](data=text), kind))


def write_bag(
    path: Path,
    ds: PoseDataset,
    storage: str,
    *,
    seed: int = 34,
    skip: tuple[str, ...] = (),
    urdf_xml: str | None = None,
) -> Truth:
    """``ds`` (the panda's joints) as a bag: ``storage`` ros1 (``path`` a .bag file), sqlite3 or
    mcap (``path`` a rosbag2 folder); ``skip``: topics left out (a bad bag); ``urdf_xml``: the
    robot's URDF, on /robot_description twice (an outdated one first: the last one counts)."""
    ros1 = storage == "ros1"
    store, serialize = _store(storage)
    types = store.types

    header = functools.partial(_header, types, ros1)

    def transform(stamp: int, parent: str, child: str, pose: Any) -> Any:
        p, q = pose
        return types["geometry_msgs/msg/TransformStamped"](
            header=header(stamp, parent),
            child_frame_id=child,
            transform=types["geometry_msgs/msg/Transform"](
                translation=types["geometry_msgs/msg/Vector3"](x=p[0], y=p[1], z=p[2]),
                rotation=types["geometry_msgs/msg/Quaternion"](x=q[0], y=q[1], z=q[2], w=q[3]),
            ),
        )

    def tf_message(transforms: list[Any]) -> Any:
        return types["tf2_msgs/msg/TFMessage"](transforms=transforms)

    joint_msgs, tf_msgs, captures, truth = _streams(ds, seed)
    names = [*reversed(ds.joint_names), *FINGERS]  # not the chain's order
    static = [
        transform(START_NS, "camera_link", "mid", CAMERA_M_MID),
        transform(START_NS, "world", "robot_base", (np.zeros(3), np.array([0, 0, 0, 1.0]))),
    ]
    messages: list[tuple[str, int, Any]] = [("/tf_static", START_NS, tf_message(static))]
    if urdf_xml is not None:
        description = types["std_msgs/msg/String"]
        messages += [
            (ROBOT_DESCRIPTION, START_NS - 2, description(data="<robot name='outdated'/>")),
            (ROBOT_DESCRIPTION, START_NS - 1, description(data=urdf_xml)),
        ]
    messages += [
        (
            "/joint_states",
            stamp,
            types["sensor_msgs/msg/JointState"](
                header=header(stamp, ""),
                name=names,
                position=np.concatenate([q[::-1], [0.04, 0.04]]),
                velocity=np.zeros(0),
                effort=np.zeros(0),
            ),
        )
        for stamp, q in joint_msgs
    ]
    # composed by Pinocchio, not by the reader's own tf maths (schemas/dataset/tf_tree.py)
    mid_m_camera = _se3(CAMERA_M_MID).inverse()
    for stamp, pose in tf_msgs:
        mid_m_board_xyzquat = pin.SE3ToXYZQUAT(mid_m_camera * _se3(pose))
        mid_m_board = (mid_m_board_xyzquat[:3], mid_m_board_xyzquat[3:])
        position = types["geometry_msgs/msg/Point"](x=pose[0][0], y=pose[0][1], z=pose[0][2])
        x, y, z, w = pose[1]
        rotation = types["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)
        messages += [
            ("/tf", stamp, tf_message([transform(stamp, "mid", "board", mid_m_board)])),
            (
                "/board_pose",
                stamp,
                types["geometry_msgs/msg/PoseStamped"](
                    header=header(stamp, "camera_link"),
                    pose=types["geometry_msgs/msg/Pose"](position=position, orientation=rotation),
                ),
            ),
            ("/board_transform", stamp, transform(stamp, "camera_link", "board", pose)),
            (
                "/tracker_point",
                stamp,
                types["geometry_msgs/msg/PointStamped"](
                    header=header(stamp, "camera_link"), point=position
                ),
            ),
        ]
    empty = types["std_msgs/msg/Empty"](structure_needs_at_least_one_member=0)
    messages += [("/capture", stamp, empty) for stamp in captures]  # no header: the log time
    messages.sort(key=lambda m: m[1])
    kinds = {
        "/joint_states": "sensor_msgs/msg/JointState",
        "/tf": "tf2_msgs/msg/TFMessage",
        "/tf_static": "tf2_msgs/msg/TFMessage",
        "/board_pose": "geometry_msgs/msg/PoseStamped",
        "/board_transform": "geometry_msgs/msg/TransformStamped",
        "/tracker_point": "geometry_msgs/msg/PointStamped",
        "/capture": "std_msgs/msg/Empty",
        ROBOT_DESCRIPTION: "std_msgs/msg/String",
    }
    with _writer(path, storage) as writer:
        connections = {
            topic: writer.add_connection(topic, kind, typestore=store)
            for topic, kind in kinds.items()
            if topic not in skip and (topic != ROBOT_DESCRIPTION or urdf_xml is not None)
        }
        for topic, stamp, message in messages:
            if topic in connections:
                writer.write(connections[topic], stamp, serialize(message, kinds[topic]))
    return truth


CAPTURE_TOPIC = "/calibration_data"
BOARD_CORNERS_M = np.array(
    [[0.025 * i, 0.025 * j, 0.0] for j in range(3) for i in range(4)], dtype=float
)
"""A 4 × 3 checkerboard's inner corners in its own frame (robot_calibration's 'arm' sensor)."""


def capture_bags(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """The real FR3 recording as a capture bag of each storage (ros1, sqlite3), once per run."""

    def write_all(folder: Path) -> dict[str, Path]:
        ds = read_dataset(FR3_POSES, PANDA_JOINTS)
        bags = {"ros1": folder / "captures.bag", "sqlite3": folder / "captures_sqlite3"}
        for storage, path in bags.items():
            assert write_capture_bag(path, ds, storage) == 115
        return bags

    return computed_once(tmp_path_factory, "capture-bags", write_all)


def write_capture_bag(path: Path, ds: PoseDataset, storage: str) -> int:
    """``ds`` as robot_calibration records a checkerboard capture run: one
    ``robot_calibration_msgs/CalibrationData`` per row on :data:`CAPTURE_TOPIC` (joint states
    in another order with the fingers; the 'camera' sensor's features are the corners the
    camera sees, placed by Pinocchio's SE3 from the row's pose; the 'arm' sensor's are the
    corners in the board frame), plus one capture whose camera saw two corners only. ``storage``
    ros1 (a .bag, its message definitions inside, as ROS 1 writes them) or sqlite3 (a rosbag2
    folder of version 5, without definitions, as ROS 2 Humble writes it). Returns the number of
    captures."""
    from rosbags.rosbag1 import Writer as Writer1
    from rosbags.rosbag2 import StoragePlugin
    from rosbags.rosbag2 import Writer as Writer2
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    ros1 = storage == "ros1"
    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    upstream = {  # robot_calibration_msgs 0.8 as published
        "robot_calibration_msgs/msg/CameraParameter": "string name\nfloat64 value",
        "robot_calibration_msgs/msg/ExtendedCameraInfo": (
            "sensor_msgs/CameraInfo  camera_info\nCameraParameter[]       parameters"
        ),
        "robot_calibration_msgs/msg/Observation": (
            "string sensor_name\ngeometry_msgs/PointStamped[] features\n"
            "ExtendedCameraInfo ext_camera_info\nsensor_msgs/PointCloud2 cloud\n"
            "sensor_msgs/Image image"
        ),
        "robot_calibration_msgs/msg/CalibrationData": (
            "sensor_msgs/JointState  joint_states\nObservation[]           observations"
        ),
    }
    for name, text in upstream.items():
        store.register(get_types_from_msg(text, name))
    types = store.types
    serialize = store.serialize_ros1 if ros1 else store.serialize_cdr

    header = functools.partial(_header, types, ros1)

    def features(stamp: int, frame: str, points: NDArray[np.float64]) -> list[Any]:
        point = types["geometry_msgs/msg/Point"]
        return [
            types["geometry_msgs/msg/PointStamped"](
                header=header(stamp, frame), point=point(x=p[0], y=p[1], z=p[2])
            )
            for p in points
        ]

    def empty(kind: str) -> Any:
        fields = store.fielddefs[kind][1]
        return types[kind](**{name: _empty_field(store, f) for name, f in fields})

    def capture(stamp: int, q: NDArray[np.float64], seen: NDArray[np.float64]) -> Any:
        observation = types["robot_calibration_msgs/msg/Observation"]
        extras = {
            "ext_camera_info": empty("robot_calibration_msgs/msg/ExtendedCameraInfo"),
            "cloud": empty("sensor_msgs/msg/PointCloud2"),
            "image": empty("sensor_msgs/msg/Image"),
        }
        return types["robot_calibration_msgs/msg/CalibrationData"](
            joint_states=types["sensor_msgs/msg/JointState"](
                header=header(stamp, ""),
                name=[*reversed(ds.joint_names), *FINGERS],
                position=np.concatenate([q[::-1], [0.04, 0.04]]),
                velocity=np.zeros(0),
                effort=np.zeros(0),
            ),
            observations=[
                observation(
                    sensor_name="camera",
                    features=features(stamp, "camera_link", seen),
                    **extras,
                ),
                observation(
                    sensor_name="arm",
                    features=features(stamp, "checkerboard", BOARD_CORNERS_M[: len(seen)]),
                    **extras,
                ),
            ],
        )

    assert ds.quaternion_xyzw is not None
    messages = []
    for i, q in enumerate(ds.joint_positions):
        camera_m_board = _se3((ds.position_m[i], ds.quaternion_xyzw[i]))
        seen = np.array([camera_m_board.act(corner) for corner in BOARD_CORNERS_M])
        messages.append(capture(START_NS + i * NS, q, seen))
    messages.insert(5, capture(START_NS + 5 * NS - NS // 2, ds.joint_positions[5], seen[:2]))
    kind = "robot_calibration_msgs/msg/CalibrationData"
    writer: Any = (
        Writer1(path) if ros1 else Writer2(path, version=8, storage_plugin=StoragePlugin.SQLITE3)
    )
    with writer:
        connection = writer.add_connection(CAPTURE_TOPIC, kind, typestore=store)
        for message in messages:
            stamp = message.joint_states.header.stamp
            writer.write(connection, stamp.sec * NS + stamp.nanosec, serialize(message, kind))
    if not ros1:  # as Humble records: no definitions, no type hash
        import sqlite3

        (database,) = path.glob("*.db3")
        with contextlib.closing(sqlite3.connect(database)) as connection, connection:
            connection.execute("DELETE FROM message_definitions")
            connection.execute("UPDATE topics SET type_description_hash = ''")
    return len(messages)


def _empty_field(store: Any, field: Any) -> Any:
    """A field's empty value (0, '', an empty array or an empty message) from its definition."""
    from rosbags.typesys.base import Nodetype

    node, detail = field
    if node == Nodetype.BASE:
        return "" if detail[0] == "string" else 0
    if node == Nodetype.NAME:
        return store.types[detail](
            **{n: _empty_field(store, f) for n, f in store.fielddefs[detail][1]}
        )
    if node in (Nodetype.ARRAY,):
        return np.zeros(detail[1]) if detail[0][0] == Nodetype.BASE else []
    return np.zeros(0) if detail[0][0] == Nodetype.BASE else []
