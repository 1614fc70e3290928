"""Message types a bag may hold without their definitions, for rosbags' typestore.

rosbag2 sqlite3 bags recorded before ROS 2 Iron carry no message definitions: they are read with
ROS 2 Humble's standard messages. ``robot_calibration_msgs`` (robot_calibration 0.8,
Apache-2.0) is not among them: its messages are given here as that package publishes them (the
interface, needed to decode a ``CalibrationData`` capture; no ROS install).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rosbags.typesys.store import Typestore

CALIBRATION_DATA = "robot_calibration_msgs/msg/CalibrationData"
ROBOT_CALIBRATION_MSGS = {
    "robot_calibration_msgs/msg/CameraParameter": "string name\nfloat64 value\n",
    "robot_calibration_msgs/msg/ExtendedCameraInfo": (
        "sensor_msgs/CameraInfo camera_info\nrobot_calibration_msgs/CameraParameter[] parameters\n"
    ),
    "robot_calibration_msgs/msg/Observation": (
        "string sensor_name\n"
        "geometry_msgs/PointStamped[] features\n"
        "robot_calibration_msgs/ExtendedCameraInfo ext_camera_info\n"
        "sensor_msgs/PointCloud2 cloud\n"
        "sensor_msgs/Image image\n"
    ),
    CALIBRATION_DATA: (
        "sensor_msgs/JointState joint_states\nrobot_calibration_msgs/Observation[] observations\n"
    ),
}


def typestore() -> Typestore:
    """ROS 2 Humble's messages and robot_calibration's."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    types = {}
    for name, text in ROBOT_CALIBRATION_MSGS.items():
        types.update(get_types_from_msg(text, name))
    store.register(types)
    return store
