"""What a URDF holds, read by a streaming, safe XML parse before Pinocchio ever sees it.

Pinocchio's URDF reader recurses along the kinematic tree (a chain of ~4000 joints overflows
the stack and kills the process) and building a chain costs time growing faster than the cube
of its length (200 joints: a minute). So untrusted URDFs are measured here first: how many
joints and links they declare, and how many movable joints lie between two frames. The parse
refuses DTDs, entities and external references (defusedxml) and keeps no tree in memory.
"""

from __future__ import annotations

import io
from dataclasses import dataclass, field
from xml.etree.ElementTree import ParseError

import defusedxml.ElementTree as SafeET
from defusedxml import DefusedXmlException

from solver.errors import ModelError

DEFAULT_MAX_URDF_JOINTS = 512
"""Most ``<joint>`` elements in a URDF (the largest shipped robot, TALOS, has ~60)."""


class UrdfLimitError(ModelError):
    """A URDF or chain is larger than a configured limit."""


@dataclass(frozen=True)
class UrdfOutline:
    """The ``<joint>``/``<link>`` structure of a URDF (no geometry)."""

    n_joints: int
    n_links: int
    parent_of_link: dict[str, tuple[str, str, str]] = field(repr=False)
    """child link -> (joint name, joint type, parent link)."""
    child_of_joint: dict[str, str] = field(repr=False)
    name: str = ""
    """The ``<robot name>``."""

    def movable_joints_between(self, base_frame: str, tip_frame: str) -> list[str] | None:
        """Non-fixed joints on the path from ``base_frame`` up to ``tip_frame``, base first;
        None when the frames are not links/joints on one branch (Pinocchio then says why)."""
        link = self.child_of_joint.get(tip_frame, tip_frame)
        base = self.child_of_joint.get(base_frame, base_frame)
        joints: list[str] = []
        seen: set[str] = set()
        while link != base:
            if link in seen or link not in self.parent_of_link:
                return None
            seen.add(link)
            name, kind, link = self.parent_of_link[link]
            if kind != "fixed":
                joints.append(name)
        return joints[::-1]

    def root_links(self) -> list[str]:
        """Links that are a joint's parent and no joint's child, sorted."""
        parents = {parent for _, _, parent in self.parent_of_link.values()}
        return sorted(parents - self.parent_of_link.keys())

    def arm_frames(self) -> tuple[str, str]:
        """The base and tip frames of the arm when none are named: the root link, and the child
        link of the last movable joint on the trunk, the path from the root that goes on while
        exactly one child joint leads to movable joints (a gripper's fingers or a second arm
        branch off: the trunk ends there). :class:`ModelError` naming ``--base``/``--tip`` when
        the tree has not one root or no movable joint on its trunk."""
        roots = self.root_links()
        if len(roots) != 1:
            raise ModelError(
                f"urdf: {len(roots)} root links ({', '.join(roots) or 'none'}), not one; "
                "give --base FRAME and --tip FRAME"
            )
        children: dict[str, list[tuple[str, str, str]]] = {}
        for link, (joint, kind, parent) in self.parent_of_link.items():
            children.setdefault(parent, []).append((joint, kind, link))
        leading: set[str] = set()  # joints that are movable or have a movable joint after them
        for link, (_, kind, _) in self.parent_of_link.items():
            if kind == "fixed":
                continue
            above = link  # mark the joints up to the root, or to one already marked
            while above in self.parent_of_link and self.parent_of_link[above][0] not in leading:
                leading.add(self.parent_of_link[above][0])
                above = self.parent_of_link[above][2]
        link, tip, seen = roots[0], "", set()
        onward: list[tuple[str, str, str]] = []
        while link not in seen:
            seen.add(link)
            onward = [step for step in children.get(link, []) if step[0] in leading]
            if len(onward) != 1:
                break
            _, kind, link = onward[0]
            tip = link if kind != "fixed" else tip
        if tip:
            return roots[0], tip
        if onward:
            raise ModelError(
                f"urdf: the tree branches at {link} into {', '.join(j for j, _, _ in onward)} "
                "before any movable joint, so which arm is meant is not clear; give --base FRAME "
                "and --tip FRAME"
            )
        raise ModelError(f"urdf: no movable joint below the root link {roots[0]}: not an arm")


def outline_urdf(urdf_xml: str) -> UrdfOutline:
    """Stream through ``urdf_xml`` and collect its joints and links; :class:`ModelError` naming
    the problem if it is not a safe, well-formed ``<robot>`` document."""
    parent_of_link: dict[str, tuple[str, str, str]] = {}
    child_of_joint: dict[str, str] = {}
    n_joints = n_links = depth = 0
    name = ""
    try:
        events = SafeET.iterparse(
            io.BytesIO(urdf_xml.encode("utf-8")), events=("start", "end"), forbid_dtd=True
        )
        for event, element in events:
            if event == "start":
                depth += 1
                if depth == 1 and element.tag != "robot":
                    raise ModelError(
                        f"urdf: the root element is <{element.tag}>, expected <robot>; send a "
                        "URDF document"
                    )
                if depth == 1:
                    name = element.get("name", "")
                continue
            depth -= 1
            if depth == 1 and element.tag == "link":
                n_links += 1
            elif depth == 1 and element.tag == "joint":
                n_joints += 1
                _record_joint(element, parent_of_link, child_of_joint)
            if depth <= 1:
                element.clear()  # keep no subtree in memory
    except DefusedXmlException as exc:
        raise ModelError(
            f"urdf: {type(exc).__name__}: DTDs, entity declarations and external references are "
            "not allowed in a URDF; remove them"
        ) from exc
    except ParseError as exc:
        raise ModelError(f"urdf: not well-formed XML ({exc}); fix the XML") from exc
    return UrdfOutline(n_joints, n_links, parent_of_link, child_of_joint, name)


def _record_joint(
    element: SafeET.Element,
    parent_of_link: dict[str, tuple[str, str, str]],
    child_of_joint: dict[str, str],
) -> None:
    parent, child = element.find("parent"), element.find("child")
    name, kind = element.get("name", ""), element.get("type", "")
    if parent is None or child is None:
        return  # Pinocchio names the malformed joint
    child_link, parent_link = child.get("link", ""), parent.get("link", "")
    parent_of_link.setdefault(child_link, (name, kind, parent_link))
    child_of_joint.setdefault(name, child_link)


def check_urdf_limits(
    urdf_xml: str,
    base_frame: str,
    tip_frame: str,
    *,
    max_urdf_joints: int = DEFAULT_MAX_URDF_JOINTS,
    max_chain_joints: int | None = None,
) -> UrdfOutline:
    """The outline of ``urdf_xml``; :class:`UrdfLimitError` if it declares more than
    ``max_urdf_joints`` joints or (when given) the chain base -> tip has more than
    ``max_chain_joints`` movable joints."""
    outline = outline_urdf(urdf_xml)
    if outline.n_joints > max_urdf_joints:
        raise UrdfLimitError(
            f"urdf: {outline.n_joints} <joint> elements, more than the limit of "
            f"{max_urdf_joints}; remove the joints the calibration does not need (or ask the "
            "operator to raise KINCAL_MAX_URDF_JOINTS)"
        )
    if max_chain_joints is not None:
        chain = outline.movable_joints_between(base_frame, tip_frame)
        if chain is not None and len(chain) > max_chain_joints:
            raise UrdfLimitError(
                f"base_frame/tip_frame: the chain has {len(chain)} joints, more than the limit "
                f"of {max_chain_joints}; choose base/tip frames spanning fewer joints"
            )
    return outline
