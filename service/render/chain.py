"""The chain a calibration's or a discovery's options describe (:func:`chain_for`), apart
from :mod:`service.render.result_json` so that the pre-flight checks build it without loading
the result document's modules."""

from __future__ import annotations

from typing import TYPE_CHECKING

from solver.model import KinematicChain, build_chain

if TYPE_CHECKING:
    from schemas.calibration import CalibrationOptions
    from schemas.discovery import DiscoveryOptions
    from schemas.robots import RobotDescription


def chain_for(
    robot: RobotDescription, options: CalibrationOptions | DiscoveryOptions
) -> KinematicChain:
    """The chain of ``robot`` with the options' compliant joints, flex axes and payload centre
    (rigid unless joints or axes are declared compliant)."""
    return build_chain(
        robot.urdf_xml,
        robot.base_frame,
        robot.tip_frame,
        compliant_joints=options.compliant_joints,
        virtual_axes_at=options.virtual_axes_at,
        payload_com_m=options.payload_com_m,
    )
