"""Write a calibrated robot as a plain URDF that any URDF tool (Pinocchio, ROS) loads.

* joints 2..k get their origins replaced by ``origin_nominal · L_nominal^-1 · L_calibrated``
  (so fixed joints in between are left untouched); the robot keeps its own root, so the file
  drops into an existing robot description;
* the first link's correction cannot be told from the measurement frame, nor the tip's from
  the marker: they stay in those two transforms (``measurement_frame`` and ``tool`` of the
  result). With ``measurement_frame=True`` they are written as extra links: a new root link
  ``kincal_measurement_frame`` carries the measurement frame (camera, tracker) through a fixed
  joint to the old root, and a new link ``kincal_marker`` is fixed to the tip link.

Forward kinematics from the base frame to the tip frame then equal kincal's calibrated
prediction with zero gravity load, without the measurement frame and marker; with the extra
links, from ``kincal_measurement_frame`` to ``kincal_marker`` they equal it as measured.
Gravity-dependent joint compliance cannot be expressed in URDF; its calibrated values are
written in an XML comment and stay in the result JSON (``kincal predict`` applies them). Joint
corrections carried from a discovered model (``calibrate --model``: gear_periodic, joint_scale,
load-sign backlash) are functions of the joint angle that a URDF cannot express either, and
without them its forward kinematics would be wrong for raw readings: such results are refused
(:func:`refusal`).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

import numpy as np
import pinocchio as pin

from schemas.calibration import CalibrationResult, ModelCorrections
from service.render.result_json import result_chain
from solver import lie
from solver.arrays import FloatArray
from solver.errors import ModelError

MEASUREMENT_LINK = "kincal_measurement_frame"
MARKER_LINK = "kincal_marker"


CLI_FIX = (
    "use kincal predict/rank with the result JSON, or calibrate without --model for a plain URDF"
)


def refusal(corrections: ModelCorrections | None, fix: str = CLI_FIX) -> str | None:
    """Why a result carrying these corrections cannot be a plain URDF (one line ending in
    ``fix``, what to do instead), or None."""
    applied = [] if corrections is None else corrections.applied()
    if not applied:
        return None
    terms = ", ".join(c.description for c in applied)
    return (
        f"cannot export a URDF: the calibration corrects the joint readings by {terms} "
        f"(a function of the joint angle a URDF cannot express); {fix}"
    )


def export_urdf(result: CalibrationResult, *, measurement_frame: bool = False) -> str:
    """The calibrated URDF as text (see module docstring for what changes; ``measurement_frame``
    adds the measurement frame and marker links); raises :class:`ModelError` for a result
    carrying joint corrections (:func:`refusal`)."""
    reason = refusal(result.model_corrections)
    if reason is not None:
        raise ModelError(reason)
    chain, params = result_chain(result)
    root = ET.fromstring(result.robot.urdf)
    joints = {j.get("name"): j for j in root.findall("joint")}
    for i, name in enumerate(chain.joint_names[1:], start=1):
        delta = lie.inverse(chain.nominal_links[i]) @ params.links[i]
        _set_origin(joints[name], _origin(joints[name]) @ delta)

    if measurement_frame:
        old_root = _root_link(root)
        base_in_root = _frame_in_root(result.robot.urdf, chain.base_frame)
        measurement = (
            params.links[0] @ lie.inverse(chain.nominal_links[0]) @ lie.inverse(base_in_root)
        )
        marker = lie.inverse(chain.nominal_links[-1]) @ params.links[-1]
        tip_link = _link_of_frame(result.robot.urdf, chain.tip_frame)
        root.insert(0, ET.Element("link", name=MEASUREMENT_LINK))
        root.append(
            _fixed_joint("kincal_measurement_joint", MEASUREMENT_LINK, old_root, measurement)
        )
        root.append(ET.Element("link", name=MARKER_LINK))
        root.append(_fixed_joint("kincal_marker_joint", tip_link, MARKER_LINK, marker))
    root.insert(0, ET.Comment(_compliance_note(result, measurement_frame)))
    ET.indent(root)
    return '<?xml version="1.0"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _origin(joint: ET.Element) -> FloatArray:
    origin = joint.find("origin")
    out = np.eye(4)
    if origin is None:
        return out
    xyz = [float(v) for v in origin.get("xyz", "0 0 0").split()]
    rpy = [float(v) for v in origin.get("rpy", "0 0 0").split()]
    out[:3, :3] = pin.rpy.rpyToMatrix(*rpy)
    out[:3, 3] = xyz
    return out


def _set_origin(element: ET.Element, transform: FloatArray) -> None:
    origin = element.find("origin")
    if origin is None:
        origin = ET.SubElement(element, "origin")
    origin.set("xyz", " ".join(repr(float(v)) for v in transform[:3, 3]))
    origin.set("rpy", " ".join(repr(float(v)) for v in pin.rpy.matrixToRpy(transform[:3, :3])))


def _fixed_joint(name: str, parent: str, child: str, transform: FloatArray) -> ET.Element:
    joint = ET.Element("joint", name=name, type="fixed")
    ET.SubElement(joint, "parent", link=parent)
    ET.SubElement(joint, "child", link=child)
    _set_origin(joint, transform)
    return joint


def _root_link(root: ET.Element) -> str:
    children = {c.get("link") for c in root.iter("child")}
    roots = [link.get("name") for link in root.findall("link") if link.get("name") not in children]
    if len(roots) != 1:
        raise ModelError(f"URDF must have exactly one root link, found {roots}")
    return str(roots[0])


def _frame_in_root(urdf: str, frame: str) -> FloatArray:
    """Placement of a frame in the URDF's root link at the neutral configuration."""
    model = pin.buildModelFromXML(urdf)
    data = model.createData()
    pin.framesForwardKinematics(model, data, pin.neutral(model))
    return data.oMf[model.getFrameId(frame)].homogeneous


def _link_of_frame(urdf: str, frame: str) -> str:
    """The URDF link a Pinocchio frame belongs to (the frame itself if it is a link)."""
    model = pin.buildModelFromXML(urdf)
    current = model.frames[model.getFrameId(frame)]
    while current.type != pin.FrameType.BODY:
        current = model.frames[current.parentFrame]
    return str(current.name)


def _compliance_note(result: CalibrationResult, measurement_frame: bool) -> str:
    lines = [
        f" Calibrated by kincal {result.kincal_version} on {result.created_utc}.",
        f" Measurement frame: link {MEASUREMENT_LINK}; measured marker: link {MARKER_LINK}."
        if measurement_frame
        else " Measurement frame and marker: in the result JSON (measurement_frame, tool).",
        " Joint compliance (deflection = c * gravity torque; not expressible in URDF):",
    ]
    lines += [f"   {c.axis}: {c.value_rad_per_nm!r} rad/Nm" for c in result.compliance]
    return "\n".join(lines) + "\n"
