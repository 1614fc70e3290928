"""Domain errors, one module for the whole project.

The CLI turns them into one line and exit code 2; the service turns them into RFC 9457
problem+json. Messages name the offending field (row, column, parameter) and the fix.
"""

from __future__ import annotations


class KincalError(Exception):
    """Base class of every error a user can cause and fix."""


class DatasetError(KincalError):
    """A recording is unreadable or inconsistent (names row and column)."""


class JointColumnsError(DatasetError):
    """A recording's joint columns are not the robot's joints (missing, or named another
    way): often a recording of another robot."""


class ModelError(KincalError):
    """A robot model cannot be built (unknown robot, frame, joint type)."""


class SolverError(KincalError):
    """A numerical solver failed or was misconfigured."""


class CalibrationError(KincalError):
    """A calibration cannot be carried out on the given data (e.g. too few samples)."""
