"""Exports a robot controller can use, from a result JSON (``kincal export``, ``GET
/api/v1/calibrations/{id}/export``; docs/exports.md).

Formats, each reproducing kincal's calibrated prediction (zero gravity load) where it can
express it — tested by reloading the file and comparing forward kinematics to 1e-9:

* ``urdf`` — the robot's URDF with calibrated joint origins (:mod:`service.render.urdf_export`);
* ``offsets-yaml`` / ``offsets-csv`` — one offset per joint, added to the joint reading before
  the nominal URDF's forward kinematics (``q_urdf = q_reading + offset``); the YAML also holds
  the measurement frame and marker, and says whether the table is exact (only when the
  calibration moved nothing but joint offsets, ``--free joint_offsets``);
* ``dh`` / ``mdh`` — the DH / modified-DH table of the calibrated chain (:mod:`solver.dh`),
  in the YAML format ``kincal calibrate --dh`` reads;
* ``pal-master`` — PAL Robotics' ``master_calibration.yaml`` (``robot_state_publisher:
  geometric_calibration: {<joint>_<dx|dy|dz|droll|dpitch|dyaw>: value}``: additive deltas on
  each joint's URDF ``<origin>`` xyz and rpy as written, joint names without ``_joint``), the
  overlay PAL robots apply to their unmodified URDF (FIGAROH 1.0.2's
  ``geometric_calibration_export`` writes the same layout);
* ``ur-kinematics`` — the ``kinematics:`` YAML of Universal Robots' ROS description and driver
  (``ur_description``'s ``kinematics_parameters_file``): per joint of the arm (``shoulder``,
  ``upper_arm``, ``forearm``, ``wrist_1..3`` for ``shoulder_pan_joint`` ... ``wrist_3_joint``)
  the calibrated ``<origin>`` as x, y, z (m) and roll, pitch, yaw (rad), which the description's
  xacro writes into those joints' origins, and a ``hash``.

All of them describe the robot from its base frame to its tip frame: the measurement frame and
marker are not part of the robot (``measurement_frame=True`` adds them to ``urdf``, ``dh`` and
``mdh``; the offsets YAML always lists them). None can express gravity-dependent joint compliance:
each lists it as not expressed when the calibration has any.
"""

from __future__ import annotations

import csv
import hashlib
import io
import xml.etree.ElementTree as ET
from collections.abc import Callable
from typing import Any, Literal

import numpy as np
import pinocchio as pin
import yaml

from schemas.calibration import CalibrationResult
from schemas.dh import DhJoint, DhRobot, Placement
from service.render.result_json import result_chain
from service.render.urdf_export import export_urdf, refusal
from solver import lie
from solver.dh import DhConvention, dh_table_of_links
from solver.errors import KincalError
from solver.model import KinematicChain

ExportFormat = Literal[
    "urdf", "offsets-yaml", "offsets-csv", "dh", "mdh", "pal-master", "ur-kinematics"
]
FORMATS: tuple[ExportFormat, ...] = (
    "urdf",
    "offsets-yaml",
    "offsets-csv",
    "dh",
    "mdh",
    "pal-master",
    "ur-kinematics",
)
MEDIA_TYPES: dict[ExportFormat, str] = {
    "urdf": "application/xml",
    "offsets-yaml": "application/yaml",
    "offsets-csv": "text/csv",
    "dh": "application/yaml",
    "mdh": "application/yaml",
    "pal-master": "application/yaml",
    "ur-kinematics": "application/yaml",
}
SUFFIX: dict[ExportFormat, str] = {
    "urdf": ".urdf",
    "offsets-yaml": ".yaml",
    "offsets-csv": ".csv",
    "dh": ".yaml",
    "mdh": ".yaml",
    "pal-master": ".yaml",
    "ur-kinematics": ".yaml",
}
PAL_AXES = ("dx", "dy", "dz", "droll", "dpitch", "dyaw")
EXACT_TOLERANCE = 1e-12
"""A correction component below this (m, rad) counts as none when judging what a format holds."""


def export(
    result: CalibrationResult, format: ExportFormat, *, measurement_frame: bool = False
) -> str:
    """The result in ``format`` (module docstring); :class:`KincalError` naming the cause for a
    result that corrects joint readings by a discovered model (no format here can hold it)."""
    reason = refusal(
        result.model_corrections,
        "use kincal predict/rank with the result JSON, or calibrate without --model",
    )
    if reason is not None:
        raise KincalError(
            reason.replace("cannot export a URDF", f"cannot export {format}").replace(
                "a URDF cannot express", "no export format can express"
            )
        )
    writers: dict[ExportFormat, Callable[[], str]] = {
        "urdf": lambda: export_urdf(result, measurement_frame=measurement_frame),
        "offsets-yaml": lambda: offsets_yaml(result),
        "offsets-csv": lambda: offsets_csv(result),
        "dh": lambda: dh_export(result, "dh", measurement_frame=measurement_frame),
        "mdh": lambda: dh_export(result, "mdh", measurement_frame=measurement_frame),
        "pal-master": lambda: pal_master(result),
        "ur-kinematics": lambda: ur_kinematics(result),
    }
    return writers[format]()


def robot_links(result: CalibrationResult) -> tuple[KinematicChain, np.ndarray]:
    """The calibrated chain's link placements without the measurement frame and marker
    (k+1, 4, 4): ``L_1`` and ``L_{k+1}`` nominal (their corrections are those two frames),
    the others calibrated."""
    chain, params = result_chain(result)
    links = params.links.copy()
    links[0], links[-1] = chain.nominal_links[0], chain.nominal_links[-1]
    return chain, links


def not_expressed(result: CalibrationResult) -> list[str]:
    """What the exports leave out: gravity-dependent compliance, when calibrated non-zero."""
    compliant = [c.axis for c in result.compliance if c.value_rad_per_nm != 0.0]
    if not compliant:
        return []
    return [
        "joint compliance (deflection = c * gravity torque) of "
        + ", ".join(compliant)
        + ": kept in the result JSON, applied by kincal predict/rank"
    ]


def offsets_not_exact(result: CalibrationResult, format: ExportFormat) -> list[str]:
    """For the offsets formats: the link geometry an offsets table leaves out (empty if none)."""
    if not format.startswith("offsets"):
        return []
    return [m for m in joint_offsets(result)[1] if m.startswith("link geometry")]


# --- joint offsets ------------------------------------------------------------------------------


def joint_offsets(result: CalibrationResult) -> tuple[list[dict[str, Any]], list[str]]:
    """One row per joint (name, offset, unit, standard error) and what the table cannot hold.

    Joint i's offset is the component of its link's correction ``Log(L_nominal⁻¹ L_calibrated)``
    along the joint screw s_i (``L_i Exp(δ s_i) Exp(s_i q) = L_i Exp(s_i (q + δ))``). The first
    joint's offset is part of the measurement frame (0 here); the last one's cannot be told
    from the marker, so a calibration leaves it at 0 (unidentifiable). Any other component of a
    correction (link geometry) is not an offset and is listed as not expressed, with its size.
    """
    chain, links = robot_links(result)
    rows, leftover = [], []
    for i, name in enumerate(chain.joint_names):
        twist = lie.se3_log(lie.inverse(chain.nominal_links[i]) @ links[i])
        screw = chain.joint_screws[i]
        offset = float(twist @ screw)
        rest = twist - offset * screw
        if np.abs(rest).max() > EXACT_TOLERANCE:
            leftover.append(
                f"{name}: link geometry {1e3 * np.linalg.norm(rest[:3]):.3g} mm, "
                f"{1e3 * np.linalg.norm(rest[3:]):.3g} mrad"
            )
        axis = int(np.argmax(np.abs(screw)))
        link = result.links[i]
        stderr = [*link.stderr_translation_m, *link.stderr_rotation_rad][axis]
        rows.append(
            {
                "joint": name,
                "offset": offset,
                "unit": "rad" if chain.is_revolute()[i] else "m",
                "stderr": None if i == 0 or stderr is None else float(stderr),
            }
        )
    missing = (
        [f"link geometry not along the joint axes ({'; '.join(leftover)})"] if leftover else []
    )
    return rows, missing + not_expressed(result)


def offsets_yaml(result: CalibrationResult) -> str:
    rows, missing = joint_offsets(result)
    document = {
        "format": "kincal.joint_offsets/1",
        "robot": result.robot.name,
        "base_frame": result.robot.base_frame,
        "tip_frame": result.robot.tip_frame,
        "convention": "q_urdf = q_reading + offset, then the robot's nominal URDF",
        "exact": not any(m.startswith("link geometry") for m in missing),
        "offsets": rows,
        "measurement_frame": {
            "matrix": result.measurement_frame.matrix,
            "meaning": "base frame in the measurement frame",
        },
        "marker": {"matrix": result.tool.matrix, "meaning": "marker in the tip frame"},
        "not_expressed": missing,
    }
    return yaml.safe_dump(document, sort_keys=False, width=1000)


def offsets_csv(result: CalibrationResult) -> str:
    rows, _ = joint_offsets(result)
    out = io.StringIO()
    writer = csv.DictWriter(out, ["joint", "offset", "unit", "stderr"], lineterminator="\n")
    writer.writeheader()
    for row in rows:
        writer.writerow({**row, "offset": repr(row["offset"]), "stderr": row["stderr"] or ""})
    return out.getvalue()


# --- DH tables ------------------------------------------------------------------------------------


def dh_export(
    result: CalibrationResult, convention: DhConvention, *, measurement_frame: bool = False
) -> str:
    """The calibrated chain as a DH / modified-DH table (the YAML of ``calibrate --dh``); with
    ``measurement_frame`` its base transform starts at the measurement frame and its tool
    transform ends at the marker."""
    chain, links = robot_links(result)
    if measurement_frame:
        links = result_chain(result)[1].links
    table = dh_table_of_links(chain, links, convention)
    robot = DhRobot(
        name=result.robot.name,
        convention=convention,
        base_frame="kincal_measurement_frame" if measurement_frame else chain.base_frame,
        tip_frame="kincal_marker" if measurement_frame else chain.tip_frame,
        base=_placement(table.base),
        tool=_placement(table.tool),
        joints=[
            DhJoint(
                name=row.name,
                type=row.kind,
                a_m=row.a_m,
                alpha_rad=row.alpha_rad,
                d_m=row.d_m,
                theta_rad=row.theta_rad,
                lower=row.lower,
                upper=row.upper,
            )
            for row in table.rows
        ],
    )
    header = "".join(f"# not expressed: {line}\n" for line in not_expressed(result))
    return header + yaml.safe_dump(robot.model_dump(mode="json"), sort_keys=False, width=1000)


def _placement(transform: np.ndarray) -> Placement:
    xyz = transform[:3, 3]
    rpy = pin.rpy.matrixToRpy(transform[:3, :3])
    return Placement(
        xyz_m=(float(xyz[0]), float(xyz[1]), float(xyz[2])),
        rpy_rad=(float(rpy[0]), float(rpy[1]), float(rpy[2])),
    )


# --- PAL master_calibration.yaml ------------------------------------------------------------------


def pal_master(result: CalibrationResult) -> str:
    """PAL's ``master_calibration.yaml``: per joint whose origin the calibration changed, the
    additive deltas on its URDF origin xyz (m) and rpy (rad) as written, so that
    ``rpyToMatrix(rpy + drpy)`` is the calibrated rotation exactly (the rpy delta is the
    difference of the two rpy triplets, wrapped to (-π, π]: a change of 2π in any angle leaves
    the matrix as it is)."""
    calibrated = {j.get("name"): j for j in ET.fromstring(export_urdf(result)).findall("joint")}
    deltas: dict[str, float] = {}
    for joint in ET.fromstring(result.robot.urdf).findall("joint"):
        name = str(joint.get("name"))
        old_xyz, old_rpy = _xyz_rpy(joint)
        new_xyz, new_rpy = _xyz_rpy(calibrated[name])
        change = np.r_[new_xyz - old_xyz, (new_rpy - old_rpy + np.pi) % (2 * np.pi) - np.pi]
        if np.any(change != 0.0):
            key = name.removesuffix("_joint")
            deltas.update({f"{key}_{a}": float(v) for a, v in zip(PAL_AXES, change, strict=True)})
    header = "".join(f"# not expressed: {line}\n" for line in not_expressed(result))
    header += "# measurement frame and marker: in the kincal result JSON, not robot joints\n"
    document = {"robot_state_publisher": {"geometric_calibration": deltas}}
    return header + yaml.safe_dump(document, sort_keys=True, width=1000)


def _xyz_rpy(joint: ET.Element) -> tuple[np.ndarray, np.ndarray]:
    origin = joint.find("origin")
    if origin is None:
        return np.zeros(3), np.zeros(3)
    xyz = np.array([float(v) for v in origin.get("xyz", "0 0 0").split()])
    rpy = np.array([float(v) for v in origin.get("rpy", "0 0 0").split()])
    return xyz, rpy


# --- Universal Robots' kinematics YAML ---------------------------------------------------------

UR_SECTIONS = (
    ("shoulder", "shoulder_pan_joint"),
    ("upper_arm", "shoulder_lift_joint"),
    ("forearm", "elbow_joint"),
    ("wrist_1", "wrist_1_joint"),
    ("wrist_2", "wrist_2_joint"),
    ("wrist_3", "wrist_3_joint"),
)
"""The sections of ``kinematics:`` and the joint whose ``<origin>`` each one sets in
``ur_description`` (``ur_common.xacro`` reads them, ``ur_macro.xacro`` writes them)."""


def ur_kinematics(result: CalibrationResult) -> str:
    """Universal Robots' ``kinematics:`` YAML: each UR joint's calibrated URDF origin, x, y, z
    (m) and roll, pitch, yaw (rad, URDF's fixed-axis convention), from the calibrated URDF
    (:func:`export_urdf`); ``hash`` names this calibration (``kincal_`` and 16 hex digits of
    the values' SHA-256), not the controller's own calibration checksum: the UR driver warns
    that the two differ, which they do. :class:`KincalError` for a robot whose chain is not
    the six UR joints (a ``tf_prefix`` before the names is allowed)."""
    chain, _ = result_chain(result)
    prefix = _ur_prefix(chain.joint_names)
    calibrated = {j.get("name"): j for j in ET.fromstring(export_urdf(result)).findall("joint")}
    sections: dict[str, Any] = {}
    for section, joint in UR_SECTIONS:
        xyz, rpy = _xyz_rpy(calibrated[prefix + joint])
        values = [*xyz.tolist(), *rpy.tolist()]
        sections[section] = dict(zip(("x", "y", "z", "roll", "pitch", "yaw"), values, strict=True))
    digest = hashlib.sha256(repr(sorted(sections.items())).encode()).hexdigest()[:16]
    sections["hash"] = f"kincal_{digest}"
    header = "".join(f"# not expressed: {line}\n" for line in not_expressed(result))
    header += "# measurement frame and marker: in the kincal result JSON, not robot joints\n"
    header += (
        "# hash: this calibration's, not the controller's checksum (the UR driver warns that "
        "they differ)\n"
    )
    return header + yaml.safe_dump({"kinematics": sections}, sort_keys=False, width=1000)


def _ur_prefix(joint_names: tuple[str, ...]) -> str:
    """The ``tf_prefix`` of a UR arm's six joint names; :class:`KincalError` otherwise."""
    wanted = [joint for _, joint in UR_SECTIONS]
    prefix = joint_names[0].removesuffix(wanted[0]) if joint_names else ""
    if list(joint_names) != [prefix + name for name in wanted]:
        raise KincalError(
            f"ur-kinematics needs a Universal Robots arm, the chain {', '.join(wanted)} (with "
            f"any tf_prefix); this calibration's chain is {', '.join(joint_names)}: use "
            "--format urdf or dh instead"
        )
    return prefix
