"""Where robot descriptions come from: built-in names, a user URDF file (or a URDF's text, e.g.
the one a ROS bag carries) or a DH table."""

from __future__ import annotations

import os
import site
import sys
from dataclasses import dataclass
from pathlib import Path

from schemas.urdf_outline import UrdfOutline, check_urdf_limits
from solver.errors import ModelError


@dataclass(frozen=True)
class RobotDescription:
    """A URDF and the chain to calibrate in it."""

    name: str
    urdf_xml: str
    base_frame: str
    tip_frame: str


# name -> (URDF path inside example-robot-data's share folder, base frame, tip frame)
BUILTIN_ROBOTS: dict[str, tuple[str, str, str]] = {
    "kinova": ("robots/kinova_description/robots/kinova.urdf", "base", "j2s6s200_end_effector"),
    "panda": ("robots/panda_description/urdf/panda.urdf", "panda_link0", "panda_link8"),
    "ur10": ("robots/ur_description/urdf/ur10_robot.urdf", "base_link", "tool0"),
}


def example_robot_data_dir() -> Path:
    """The share folder of the ``example-robot-data`` wheel (it ships URDFs, no Python module).

    ``KINCAL_EXAMPLE_ROBOT_DATA`` overrides the search.
    """
    override = os.environ.get("KINCAL_EXAMPLE_ROBOT_DATA")
    candidates = [Path(override)] if override else []
    roots = [*site.getsitepackages(), site.getusersitepackages(), *sys.path]
    candidates += [Path(r) / "cmeel.prefix" / "share" / "example-robot-data" for r in roots]
    for candidate in candidates:
        if (candidate / "robots").is_dir():
            return candidate
    raise ModelError(
        "example-robot-data URDFs not found; install the 'example-robot-data' package or set "
        "KINCAL_EXAMPLE_ROBOT_DATA to its share/example-robot-data folder"
    )


def load_robot(
    name: str | None = None,
    *,
    urdf_path: str | Path | None = None,
    base_frame: str | None = None,
    tip_frame: str | None = None,
    dh_path: str | Path | None = None,
) -> RobotDescription:
    """A built-in robot by name, a URDF file with explicit base and tip frames, or a DH /
    modified-DH table (YAML, :class:`schemas.dh.DhRobot`; its URDF is generated)."""
    if dh_path is not None:
        if urdf_path is not None:
            raise ModelError("give --urdf or --dh, not both")
        return load_dh_robot(Path(dh_path))
    if urdf_path is not None:
        if base_frame is None or tip_frame is None:
            raise ModelError("--urdf needs --base FRAME and --tip FRAME")
        path = Path(urdf_path)
        try:
            xml = path.read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as exc:
            raise ModelError(
                f"cannot read URDF {path}: {getattr(exc, 'strerror', None) or exc}"
            ) from exc
        return urdf_robot(xml, name or path.stem, base_frame, tip_frame)[0]
    if name is None:
        raise ModelError(
            "give --robot NAME (one of: " + ", ".join(BUILTIN_ROBOTS) + ") or --urdf FILE"
        )
    if name not in BUILTIN_ROBOTS:
        raise ModelError(f"unknown robot {name!r}; built-in robots: {', '.join(BUILTIN_ROBOTS)}")
    relative, default_base, default_tip = BUILTIN_ROBOTS[name]
    xml = (example_robot_data_dir() / relative).read_text(encoding="utf-8")
    return RobotDescription(name, xml, base_frame or default_base, tip_frame or default_tip)


def urdf_robot(
    urdf_xml: str,
    name: str | None,
    base_frame: str | None = None,
    tip_frame: str | None = None,
) -> tuple[RobotDescription, UrdfOutline]:
    """The robot of a URDF's text and its outline, measured (:func:`check_urdf_limits`) before
    Pinocchio can crash on it; ``name`` None: the URDF's ``<robot name>``; a frame not given is
    the arm's (:meth:`UrdfOutline.arm_frames`: the root link, the link of the last joint before
    the tree branches)."""
    outline = check_urdf_limits(urdf_xml, base_frame or "", tip_frame or "")
    if base_frame is None or tip_frame is None:
        arm_base, arm_tip = outline.arm_frames()
        base_frame, tip_frame = base_frame or arm_base, tip_frame or arm_tip
    description = RobotDescription(name or outline.name or "robot", urdf_xml, base_frame, tip_frame)
    return description, outline


def load_dh_robot(path: Path) -> RobotDescription:
    """The robot of a DH table file (YAML): its generated URDF and its base and tip frames."""
    from schemas.dh import parse_dh_robot

    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise ModelError(
            f"cannot read DH table {path}: {getattr(exc, 'strerror', None) or exc}"
        ) from exc
    table = parse_dh_robot(text, path.name)
    return RobotDescription(table.name, table.urdf(), table.base_frame, table.tip_frame)
