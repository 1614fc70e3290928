"""Ranges every number from outside must lie in: the same for dataset uploads (HTTP and files
read by the CLI) and ranking requests. Values beyond them are not measurements of a robot
arm; let through, they overflow the covariance arithmetic or stall an SVD much later."""

from __future__ import annotations

MAX_JOINT_POSITION = 1e4
"""|q| of a joint reading, rad (m for prismatic joints)."""
MAX_PAYLOAD_KG = 1e5
MAX_POSITION_M = 1e4
"""|x|, |y|, |z| of a measured marker position (measurement frame), m."""
MAX_TIME_S = 1e11
"""|t|: seconds since any epoch (Unix time now is ~1.8e9)."""
TEMPERATURE_RANGE_C = (-273.15, 1e4)
