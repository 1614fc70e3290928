"""The arm a URDF describes when no frames are named (a ROS bag's /robot_description): the root
link to the link of the last joint before the tree branches, for every built-in robot; a tree
that branches before any movable joint is refused naming --base/--tip."""

from __future__ import annotations

import pytest

from schemas.robots import urdf_robot
from schemas.urdf_outline import outline_urdf
from solver.errors import ModelError
from tests.conftest import chain, robot

ARMS = {
    "panda": ("panda_link0", "panda_link7"),  # the hand's fingers branch off after the flange
    "kinova": ("base", "j2s6s200_link_6"),
    "ur10": ("world", "wrist_3_link"),  # tool0 and ee_link: fixed children of the last link
}


@pytest.mark.parametrize("name", sorted(ARMS))
def test_the_arm_of_a_builtin_urdf_moves_the_builtin_chains_joints(name: str) -> None:
    description, outline = urdf_robot(robot(name).urdf_xml, None)
    assert (description.base_frame, description.tip_frame) == ARMS[name]
    assert description.name == outline.name == name
    joints = outline.movable_joints_between(*ARMS[name])
    assert joints == list(chain(name).joint_names)


def _joint(name: str, kind: str, parent: str, child: str) -> str:
    return (
        f"<joint name='{name}' type='{kind}'><parent link='{parent}'/><child link='{child}'/>"
        "<axis xyz='0 0 1'/></joint>"
    )


def test_two_arms_on_one_torso_are_refused_naming_the_branch() -> None:
    links = "".join(f"<link name='{n}'/>" for n in ("torso", "l1", "r1"))
    joints = _joint("left", "revolute", "torso", "l1") + _joint("right", "revolute", "torso", "r1")
    outline = outline_urdf(f"<robot name='twins'>{links}{joints}</robot>")
    with pytest.raises(
        ModelError, match="branches at torso into left, right before any movable joint"
    ):
        outline.arm_frames()


def test_given_frames_win_and_the_rest_is_the_arms() -> None:
    description, _ = urdf_robot(robot("panda").urdf_xml, "fr3", tip_frame="panda_link8")
    assert (description.name, description.base_frame) == ("fr3", "panda_link0")
    assert description.tip_frame == "panda_link8"
