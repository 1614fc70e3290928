"""The fixed vocabulary of discovery's library effects: one list for the library
(:mod:`solver.discovery.library`) and the findings schema (:mod:`schemas.discovery`).

This module imports nothing but :mod:`typing` (and ``solver/discovery/__init__.py`` imports its
names lazily), so the schema reads it without making the discovery loop a start-up import of
the CLI.
"""

from __future__ import annotations

from typing import Literal, get_args

Effect = Literal[
    "joint_compliance",
    "base_flex",
    "link_bending",
    "gear_periodic",
    "backlash",
    "joint_scale",
    "thermal_drift",
    "payload_mass",
    "depth_scale",
    "gravity_direction",
]
EFFECTS: tuple[Effect, ...] = get_args(Effect)
