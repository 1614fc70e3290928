"""ROS bags (ROS 1 ``.bag``, rosbag2 folders with sqlite3 or MCAP storage) to a recording of the
dataset contract, read with ``rosbags`` (no ROS install; imported only when a bag is read).

Joint readings come from a ``sensor_msgs/JointState`` topic; the measured pose from one source
(:class:`MeasureSource`): ``tf:PARENT:CHILD`` (the pose of CHILD in PARENT composed along
``/tf`` and ``/tf_static``, :mod:`schemas.dataset.tf_tree`), ``pose:TOPIC``
(``geometry_msgs/PoseStamped`` or ``TransformStamped``) or ``point:TOPIC``
(``geometry_msgs/PointStamped``: a position-only recording). Header stamps are the time.
Samples are the still segments of the joint readings (:mod:`schemas.dataset.still`). A
robot_calibration capture bag (``calibration-data:TOPIC[:CAMERA[:CHAIN]]``) is read message by
message instead: each ``CalibrationData`` holds the joint states and, per sensor, the features
seen; the pose of the target (a checkerboard) in the camera frame is the rigid fit of the CHAIN
sensor's features (the target's own points) to the CAMERA sensor's.
Every problem is one :class:`~solver.errors.DatasetError` line naming the fix.
"""

from __future__ import annotations

import io
import tempfile
import zipfile
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import TYPE_CHECKING, Any

import numpy as np
import pandas as pd
from numpy.typing import NDArray

from schemas.dataset.columns import one_line
from schemas.dataset.paths import bag_location
from schemas.dataset.records import POSITION_COLUMNS, QUATERNION_COLUMNS, PoseDataset
from schemas.dataset.ros_types import CALIBRATION_DATA
from schemas.dataset.still import (
    NS_PER_S,
    Measurements,
    Samples,
    StillSettings,
    synchronise,
    synchronise_captures,
)
from schemas.dataset.tf_tree import Edge, TfTree
from schemas.dataset.validate import dataset_from_frame
from solver.errors import DatasetError

if TYPE_CHECKING:
    from rosbags.highlevel import AnyReader

UPLOAD_SUFFIXES = (".bag", ".zip")
"""A bag sent as bytes: a ROS 1 ``.bag`` file, or a rosbag2 folder in a ``.zip`` archive."""
MAX_ARCHIVE_MEMBERS = 64
JOINT_STATE = "sensor_msgs/msg/JointState"
TF_MESSAGE = "tf2_msgs/msg/TFMessage"
POSE_TYPES = ("geometry_msgs/msg/PoseStamped", "geometry_msgs/msg/TransformStamped")
POINT_TYPE = "geometry_msgs/msg/PointStamped"
TF_TOPICS = ("/tf", "/tf_static")
SOURCE_FORMS = "tf:PARENT:CHILD, pose:TOPIC, point:TOPIC or calibration-data:TOPIC[:CAMERA[:CHAIN]]"
CAPTURE_SENSORS = ("camera", "arm")
"""robot_calibration's checkerboard finder's default sensor names (camera, chain)."""
MIN_FEATURES = 3
ROBOT_DESCRIPTION_TOPIC = "/robot_description"
STRING = "std_msgs/msg/String"


@dataclass(frozen=True)
class MeasureSource:
    """Where the measured pose comes from: ``kind`` tf (``frames`` = parent, child), pose or
    point (``topic``), calibration-data (``topic``; ``frames`` = camera and chain sensors)."""

    kind: str
    topic: str = ""
    frames: tuple[str, str] = ("", "")

    @classmethod
    def parse(cls, text: str) -> MeasureSource:
        kind, _, rest = text.partition(":")
        parts = rest.split(":")
        frames = [part.lstrip("/") for part in parts]  # tf2 frame ids have no leading slash
        if kind == "tf" and len(frames) == 2 and all(frames):
            return cls("tf", frames=(frames[0], frames[1]))
        if kind in ("pose", "point") and len(parts) == 1 and parts[0]:
            return cls(kind, topic=parts[0])
        if kind == "calibration-data" and 1 <= len(parts) <= 3 and all(parts):
            sensors = (*parts[1:], *CAPTURE_SENSORS[len(parts) - 1 :])
            return cls(kind, topic=parts[0], frames=(sensors[0], sensors[1]))
        raise DatasetError(f"--measure {text!r}: give {SOURCE_FORMS}")


class TooManyMessagesError(DatasetError):
    """A bag holds more messages on the topics a recording reads than the caller's limit
    (counted from the bag's index, before any message is decoded)."""

    def __init__(self, source: str, n_messages: int, limit: int) -> None:
        super().__init__(
            f"{source}: {n_messages} messages on the topics read is more than the limit of "
            f"{limit}; split the bag"
        )
        self.n_messages = n_messages
        self.limit = limit


@dataclass(frozen=True)
class BagRecording:
    """A bag read as a recording: the dataset and what synchronisation kept and dropped."""

    dataset: PoseDataset
    samples: Samples

    def report(self) -> str:
        """One line: samples kept, segments dropped per reason, messages while moving."""
        s = self.samples
        if s.n_captures is not None:
            return (
                f"{self.dataset.source}: {s.n_samples} samples (one per capture message); "
                f"dropped: {s.n_moving} of {s.n_captures} captures while moving, "
                f"{s.n_no_measurement} without a measurement"
            )
        return (
            f"{self.dataset.source}: {s.n_samples} samples (one per still segment); dropped: "
            f"{s.n_too_short} still segment(s) too short, {s.n_no_measurement} without a "
            f"measurement; {s.n_moving} of {s.n_messages} joint-state messages while moving"
        )


def read_bag(
    path: str | Path,
    joint_states: str | None,
    measure: MeasureSource,
    *,
    joint_names: Sequence[str] | None = None,
    other_joint_names: Sequence[str] = (),
    settings: StillSettings | None = None,
    capture: str | None = None,
    source: str | None = None,
    max_messages: int | None = None,
) -> BagRecording:
    """The bag at ``path`` as a recording: one sample per still segment of ``joint_states``
    with ``measure`` averaged inside it. ``joint_names``: the chain's URDF joints, in chain
    order (None: every joint of the topic, in its order); ``other_joint_names``: URDF joints off
    the chain, accepted and left out; ``capture``: a topic of any type whose messages (header
    stamp, else the time it was logged) mark the samples instead of the still segments;
    ``source``: the name messages give the bag (default: the path's); ``max_messages``: at most
    this many messages on the topics read (:class:`TooManyMessagesError` before decoding)."""
    path, settings = Path(path), settings or StillSettings()
    source = source or path.name
    captured = measure.kind == "calibration-data"
    with _open(path, source) as reader:
        topics = {name: info.msgtype or "?" for name, info in reader.topics.items()}
        counts = {name: info.msgcount for name, info in reader.topics.items()}
        listing = ", ".join(f"{t} ({topics[t]}, {counts[t]} messages)" for t in sorted(topics))
        read = set(_measure_topics(measure, topics))
        if not captured:  # a capture bag's joint states are in its captures
            if joint_states is None:
                raise DatasetError(f"{source}: give --joint-states, the JointState topic")
            _check_topic(joint_states, (JOINT_STATE,), "--joint-states", topics, listing, source)
            read |= {t for t in (joint_states, capture) if t is not None}
        n_messages = sum(int(counts.get(topic, 0)) for topic in read)
        if max_messages is not None and n_messages > max_messages:
            raise TooManyMessagesError(source, n_messages, max_messages)
        if captured:
            _check_topic(measure.topic, (CALIBRATION_DATA,), "--measure", topics, listing, source)
            names, samples = _calibration_data(reader, measure, joint_names, source)
            start_ns, empty = None, _no_capture(samples, measure)
        else:
            assert joint_states is not None
            measured = _measurements(reader, measure, topics, listing, source)  # cheaper reads
            captures = None
            if capture is not None:
                _check_topic(capture, (), "--capture", topics, listing, source)
                captures = _capture_stamps(reader, capture)
            names, stamps, joints = _joint_states(reader, joint_states, joint_names, source)
            samples = (
                synchronise(stamps, joints, measured, settings)
                if captures is None
                else synchronise_captures(stamps, joints, measured, captures, settings)
            )
            start_ns, empty = int(stamps[0]), _no_sample(samples, settings)
    if samples.n_samples == 0:
        raise DatasetError(f"{source}: {empty}")
    start_ns = int(samples.stamps_ns[0]) if start_ns is None else start_ns
    frame = _frame(names, samples, start_ns)
    dataset = dataset_from_frame(frame, names, source=source, other_joint_names=other_joint_names)
    return BagRecording(dataset, samples)


def read_robot_description(path: str | Path, *, source: str | None = None) -> str | None:
    """The URDF a bag carries on :data:`ROBOT_DESCRIPTION_TOPIC` (``std_msgs/String``, as
    robot_calibration records it: usually one latched message): the text of its last message;
    None when the bag has no such topic or no message on it."""
    path = Path(path)
    source = source or path.name
    with _open(path, source) as reader:
        info = reader.topics.get(ROBOT_DESCRIPTION_TOPIC)
        if info is None:
            return None
        if info.msgtype != STRING:
            raise DatasetError(
                f"{source}: topic {ROBOT_DESCRIPTION_TOPIC!r} holds {info.msgtype}, not {STRING} "
                "(a URDF); pass --robot NAME or --urdf FILE"
            )
        text = None
        for _, msg in _messages(reader, ROBOT_DESCRIPTION_TOPIC):
            text = str(msg.data)
    return text


def _measure_topics(measure: MeasureSource, topics: dict[str, str]) -> tuple[str, ...]:
    """The topics ``measure`` reads in a bag with ``topics``."""
    if measure.kind == "tf":
        return tuple(topic for topic in TF_TOPICS if topic in topics)
    return (measure.topic,)  # pose, point, calibration-data


def read_bag_bytes(
    data: bytes,
    suffix: str,
    joint_states: str | None,
    measure: MeasureSource,
    *,
    source: str,
    max_unpacked_bytes: int,
    **options: Any,
) -> BagRecording:
    """A bag received as bytes (an upload) as a recording, read by :func:`read_bag` with
    ``options`` from a temporary folder: ``suffix`` ``.bag`` (a ROS 1 bag file) or ``.zip`` (a
    rosbag2 folder: its ``metadata.yaml`` and storage files, at the archive's top or in one
    folder). An archive is refused before anything is unpacked when it holds more than
    :data:`MAX_ARCHIVE_MEMBERS` files, more than ``max_unpacked_bytes`` unpacked, or a path
    outside its folder."""
    with tempfile.TemporaryDirectory(prefix="kincal-bag-") as folder:
        if suffix == ".bag":
            path = Path(folder) / "upload.bag"
            path.write_bytes(data)
        elif suffix == ".zip":
            path = _unpack_rosbag2(data, Path(folder), source, max_unpacked_bytes)
        else:
            raise DatasetError(f"{source}: a bag is a .bag file or a rosbag2 folder as a .zip")
        return read_bag(path, joint_states, measure, source=source, **options)


def _unpack_rosbag2(data: bytes, folder: Path, source: str, max_unpacked_bytes: int) -> Path:
    """The rosbag2 folder of a zip archive, unpacked into ``folder`` (checked first)."""
    try:
        archive = zipfile.ZipFile(io.BytesIO(data))
    except zipfile.BadZipFile as exc:
        raise DatasetError(f"{source}: not a zip archive ({exc}); zip the rosbag2 folder") from exc
    with archive:
        members = [info for info in archive.infolist() if not info.is_dir()]
        if len(members) > MAX_ARCHIVE_MEMBERS:
            raise DatasetError(
                f"{source}: {len(members)} files in the archive; a rosbag2 folder holds its "
                f"metadata.yaml and storage files (at most {MAX_ARCHIVE_MEMBERS})"
            )
        unpacked = sum(info.file_size for info in members)
        if unpacked > max_unpacked_bytes:
            raise DatasetError(
                f"{source}: {unpacked} bytes unpacked is more than the limit of "
                f"{max_unpacked_bytes}; split the bag"
            )
        for info in members:
            name = PurePosixPath(info.filename)
            if name.is_absolute() or ".." in name.parts:
                raise DatasetError(f"{source}: {info.filename!r} points outside the archive")
        metadata = [PurePosixPath(info.filename) for info in members]
        metadata = [name for name in metadata if name.name == "metadata.yaml"]
        if len(metadata) != 1:
            raise DatasetError(
                f"{source}: {len(metadata)} metadata.yaml files in the archive; zip one "
                "rosbag2 folder (its metadata.yaml and storage files)"
            )
        archive.extractall(folder, members)
    return folder.joinpath(*metadata[0].parent.parts)


def _calibration_data(
    reader: AnyReader, measure: MeasureSource, joint_names: Sequence[str] | None, source: str
) -> tuple[tuple[str, ...], Samples]:
    """One sample per ``CalibrationData`` message of ``measure.topic`` that holds every wanted
    joint and both sensors' features (the same number, at least :data:`MIN_FEATURES`): its
    joint positions and the target's pose in the camera frame (:func:`rigid_fit`)."""
    camera, chain = measure.frames
    wanted: tuple[str, ...] | None = None if joint_names is None else tuple(joint_names)
    seen_joints: set[str] = set()
    seen_sensors: set[str] = set()
    stamps: list[int] = []
    rows: list[NDArray[np.float64]] = []
    placements: list[tuple[NDArray[np.float64], NDArray[np.float64]]] = []
    n_messages = 0
    for logged_ns, msg in _messages(reader, measure.topic):
        n_messages += 1
        names = tuple(msg.joint_states.name)
        seen_joints.update(names)
        wanted = wanted or names
        index = _columns_of(wanted, names)
        features = {o.sensor_name: o.features for o in msg.observations}
        seen_sensors.update(features)
        seen, model = features.get(camera, []), features.get(chain, [])
        if index is None or len(msg.joint_states.position) != len(names):
            continue
        if len(seen) != len(model) or len(seen) < MIN_FEATURES:
            continue
        stamp = _stamp_ns(msg.joint_states.header)
        stamps.append(stamp if stamp > 0 else logged_ns)
        rows.append(np.asarray(msg.joint_states.position, dtype=float)[index])
        placements.append(rigid_fit(_points(model), _points(seen)))
    if wanted is None or (not rows and not set(wanted) <= seen_joints):
        raise DatasetError(
            f"{source}: the captures of {measure.topic} name joints "
            f"{', '.join(sorted(seen_joints)) or '(none)'}; the robot's chain joints are "
            f"{', '.join(wanted or ())}; pass the robot the bag was recorded with"
        )
    if not rows and not {camera, chain} <= seen_sensors:
        raise DatasetError(
            f"{source}: the captures of {measure.topic} hold the sensors "
            f"{', '.join(sorted(seen_sensors)) or '(none)'}, not {camera} and {chain}; give "
            "--measure calibration-data:TOPIC:CAMERA:CHAIN with the camera's sensor and the "
            "sensor whose features are the target's own points"
        )
    by_time = np.argsort(np.asarray(stamps, dtype=np.int64), kind="stable")
    n = len(rows)
    samples = Samples(
        joint_positions=np.asarray(rows, dtype=float).reshape(n, len(wanted))[by_time],
        position_m=np.asarray([p for p, _ in placements], dtype=float).reshape(n, 3)[by_time],
        quaternion_xyzw=np.asarray([q for _, q in placements]).reshape(n, 4)[by_time],
        stamps_ns=np.asarray(stamps, dtype=np.int64)[by_time],
        n_messages=n_messages,
        n_moving=0,
        n_too_short=0,
        n_no_measurement=n_messages - n,
        n_captures=n_messages,
    )
    return wanted, samples


def _points(features: Sequence[Any]) -> NDArray[np.float64]:
    return np.array([[f.point.x, f.point.y, f.point.z] for f in features], dtype=float)


def rigid_fit(
    model_m: NDArray[np.float64], seen_m: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The rigid transform ``cameraMtarget`` that best maps the target's own points (k, 3) m onto
    the same points as the camera sees them (k, 3) m in least squares: translation (3,) m and
    quaternion x,y,z,w (scipy's ``Rotation.align_vectors`` on the centred points)."""
    from scipy.spatial.transform import Rotation

    model_centre, seen_centre = model_m.mean(axis=0), seen_m.mean(axis=0)
    rotation, _ = Rotation.align_vectors(seen_m - seen_centre, model_m - model_centre)
    return seen_centre - rotation.apply(model_centre), rotation.as_quat()


def _no_capture(samples: Samples, measure: MeasureSource) -> str:
    camera, chain = measure.frames
    return (
        f"none of the {samples.n_messages} captures of {measure.topic} holds the robot's joints "
        f"and at least {MIN_FEATURES} features of both {camera} and {chain} (the same number); "
        "check the capture run's finder"
    )


def _no_sample(samples: Samples, settings: StillSettings) -> str:
    """Why no sample was kept, and what to change."""
    if samples.n_captures is not None:
        return (
            f"no capture to sample: {samples.n_captures} capture message(s), {samples.n_moving} "
            f"while moving, {samples.n_no_measurement} without a measurement; capture while the "
            f"robot holds still for {settings.window_s:g} s around the message with the "
            "measurement published, or lower --still-window"
        )
    found = samples.n_too_short + samples.n_no_measurement
    what = (
        f"{found} still segment(s), {samples.n_too_short} too short and "
        f"{samples.n_no_measurement} without a measurement"
        if found
        else f"the robot never holds still ({samples.n_messages} joint-state messages)"
    )
    return (
        f"no still segment to sample: {what}; record holds of at least {settings.window_s:g} s "
        "with the measurement published, or raise --still-tolerance (now "
        f"{settings.tolerance_rad_s:g} rad/s) / lower --still-window"
    )


def _capture_stamps(reader: AnyReader, topic: str) -> NDArray[np.int64]:
    """The header stamp of every message of ``topic``, or the time it was logged."""
    return np.array(
        [
            _stamp_ns(msg.header) if hasattr(msg, "header") else logged
            for logged, msg in _messages(reader, topic)
        ],
        dtype=np.int64,
    )


@contextmanager
def _open(path: Path, source: str) -> Iterator[AnyReader]:
    """The bag opened with rosbags' AnyReader; a storage file of a rosbag2 folder opens its
    folder."""
    from rosbags.highlevel import AnyReader

    from schemas.dataset.ros_types import typestore

    path = bag_location(path, source)
    try:
        reader = AnyReader([path], default_typestore=typestore())
        reader.open()
    except Exception as exc:  # rosbags' reader errors, a truncated file: one line
        raise DatasetError(
            f"{source}: cannot read as a ROS bag ({type(exc).__name__}: {one_line(exc)}); pass "
            "a ROS 1 .bag file or a rosbag2 folder (metadata.yaml with sqlite3 or mcap files)"
        ) from exc
    try:
        yield reader
    finally:
        reader.close()


def _check_topic(
    topic: str, types: Sequence[str], option: str, topics: dict[str, str], listing: str, source: str
) -> None:
    if topic not in topics:
        raise DatasetError(
            f"{source}: no topic {topic!r} in the bag; its topics: {listing or 'none'}; "
            f"pass one of them to {option}"
        )
    if types and topics[topic] not in types:
        raise DatasetError(
            f"{source}: topic {topic!r} holds {topics[topic]}, {option} needs "
            f"{' or '.join(types)}; its topics: {listing}"
        )


def _messages(reader: AnyReader, topic: str) -> Iterator[tuple[int, Any]]:
    """(time logged ns, message) of every message of ``topic``."""
    connections = [c for c in reader.connections if c.topic == topic]
    for connection, logged_ns, raw in reader.messages(connections=connections):
        try:
            yield logged_ns, reader.deserialize(raw, connection.msgtype)
        except Exception as exc:
            raise DatasetError(
                f"{topic}: a message cannot be decoded ({one_line(exc)}); re-record the topic"
            ) from exc


def _stamp_ns(header: Any) -> int:
    return int(header.stamp.sec) * NS_PER_S + int(header.stamp.nanosec)


def _joint_states(
    reader: AnyReader, topic: str, joint_names: Sequence[str] | None, source: str
) -> tuple[tuple[str, ...], NDArray[np.int64], NDArray[np.float64]]:
    """Joint names, stamps (n,) ns sorted, positions (n, k) of the messages holding every
    wanted joint (messages of other joints on the same topic, e.g. a gripper, are skipped)."""
    wanted: tuple[str, ...] | None = None if joint_names is None else tuple(joint_names)
    seen: set[str] = set()
    order: dict[tuple[str, ...], NDArray[np.intp] | None] = {}
    stamps: list[int] = []
    rows: list[NDArray[np.float64]] = []
    for _, msg in _messages(reader, topic):
        names = tuple(msg.name)
        if wanted is None and names:
            wanted = names
        if names not in order:
            seen.update(names)
            order[names] = _columns_of(wanted or (), names)
        index = order[names]
        if index is None or len(msg.position) != len(names):
            continue
        stamps.append(_stamp_ns(msg.header))
        rows.append(np.asarray(msg.position, dtype=float)[index])
    if joint_names is None and not rows:
        raise DatasetError(
            f"{source}: {topic} holds no joint positions; pass the arm's joint-state topic"
        )
    if wanted is None or not rows:
        missing = [] if wanted is None else [n for n in wanted if n not in seen]
        raise DatasetError(
            f"{source}: {topic} names joints {', '.join(sorted(seen)) or '(none)'}; the robot's "
            f"chain joints are {', '.join(wanted or ())}"
            + (
                f" ({', '.join(missing)} never published)"
                if 0 < len(missing) < len(wanted or ())
                else ""
            )
            + "; pass the robot the bag was recorded with (--robot/--urdf), or the arm's "
            "joint-state topic"
        )
    stamp_array = np.asarray(stamps, dtype=np.int64)
    by_time = np.argsort(stamp_array, kind="stable")
    return wanted, stamp_array[by_time], np.asarray(rows)[by_time]


def _columns_of(wanted: Sequence[str], names: tuple[str, ...]) -> NDArray[np.intp] | None:
    """Where each wanted joint is in a message's ``names``; None if one is missing."""
    if not wanted or not set(wanted) <= set(names):
        return None
    return np.array([names.index(n) for n in wanted])


def _measurements(
    reader: AnyReader, measure: MeasureSource, topics: dict[str, str], listing: str, source: str
) -> Measurements:
    if measure.kind == "tf":
        _check_topic("/tf", (TF_MESSAGE,), "--measure tf:…", topics, listing, source)
        tree = _tf_tree(reader, topics, source)
        parent, child = measure.frames
        stamps = tree.dynamic_stamps(parent, child)
        if len(stamps) == 0:
            raise DatasetError(
                f"{source}: {child!r} in {parent!r} is static (only /tf_static joins them); "
                "name the frames of the measured transform"
            )
        poses = tree.pose(parent, child, stamps)
        valid = poses.valid
        return Measurements(stamps[valid], poses.translation_m[valid], poses.quaternion_xyzw[valid])
    types = POSE_TYPES if measure.kind == "pose" else (POINT_TYPE,)
    _check_topic(measure.topic, types, f"--measure {measure.kind}:…", topics, listing, source)
    stamps_list, positions, quaternions = [], [], []
    for _, msg in _messages(reader, measure.topic):
        stamps_list.append(_stamp_ns(msg.header))
        if measure.kind == "point":
            positions.append([msg.point.x, msg.point.y, msg.point.z])
            continue
        pose = getattr(msg, "pose", None)
        if pose is not None:
            position, orientation = pose.position, pose.orientation
        else:
            position, orientation = msg.transform.translation, msg.transform.rotation
        positions.append([position.x, position.y, position.z])
        quaternions.append([orientation.x, orientation.y, orientation.z, orientation.w])
    by_time = np.argsort(np.asarray(stamps_list, dtype=np.int64), kind="stable")
    return Measurements(
        np.asarray(stamps_list, dtype=np.int64)[by_time],
        np.asarray(positions, dtype=float).reshape(-1, 3)[by_time],
        None if measure.kind == "point" else np.asarray(quaternions).reshape(-1, 4)[by_time],
    )


def _tf_tree(reader: AnyReader, topics: dict[str, str], source: str) -> TfTree:
    samples: dict[tuple[str, bool], list[tuple[str, int, list[float]]]] = {}
    for topic in TF_TOPICS:
        if topics.get(topic) != TF_MESSAGE:
            continue
        for _, msg in _messages(reader, topic):
            for tf in msg.transforms:
                t, r = tf.transform.translation, tf.transform.rotation
                key = (tf.child_frame_id.lstrip("/"), topic == "/tf_static")
                samples.setdefault(key, []).append(
                    (
                        tf.header.frame_id.lstrip("/"),
                        _stamp_ns(tf.header),
                        [t.x, t.y, t.z, r.x, r.y, r.z, r.w],
                    )
                )
    edges: dict[str, Edge] = {}
    for (child, static), entries in sorted(samples.items(), key=lambda kv: kv[0][1]):
        parents = {parent for parent, _, _ in entries}
        parents |= {edges[child].parent} if child in edges else set()
        if len(parents) > 1:
            raise DatasetError(
                f"{source}: frame {child!r} has several parents in the tf tree "
                f"({', '.join(sorted(parents))}); "
                "a tf frame has one parent: fix the recording's tf publishers"
            )
        entries.sort(key=lambda e: e[1])
        values = np.array([v for _, _, v in entries])
        edges[child] = Edge(
            parents.pop(),
            child,
            np.array([s for _, s, _ in entries], dtype=np.int64),
            values[:, :3],
            values[:, 3:] / np.linalg.norm(values[:, 3:], axis=1, keepdims=True),
            static,
        )
    return TfTree(edges, source)


def _frame(names: Sequence[str], samples: Samples, start_ns: int) -> pd.DataFrame:
    data: dict[str, Any] = {"sample_id": np.arange(samples.n_samples)}
    data |= {n: samples.joint_positions[:, i] for i, n in enumerate(names)}
    data |= {c: samples.position_m[:, i] for i, c in enumerate(POSITION_COLUMNS)}
    if samples.quaternion_xyzw is not None:
        data |= {c: samples.quaternion_xyzw[:, i] for i, c in enumerate(QUATERNION_COLUMNS)}
    data["t"] = (samples.stamps_ns - start_ns).astype(float) / NS_PER_S
    return pd.DataFrame(data)
