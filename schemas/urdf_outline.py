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


def outline_urdf(urdf_xml: str) -> UrdfOutline:
    """Stream through ``urdf_xml`` and collect its joints and links; :class:`ModelError` naming
    the problem if it is not a safe, well-formed ``<robot>`` document."""
    parent_of_link: dict[str, tuple[str, str, str]] = {}
    child_of_joint: dict[str, str] = {}
    n_joints = n_links = depth = 0
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
    return UrdfOutline(n_joints, n_links, parent_of_link, child_of_joint)


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
