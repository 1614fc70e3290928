"""Choosing what to calibrate: free and fixed parameters by name and by class, resolved to the
columns of the stacked Jacobian (:func:`solver.kinematics.parameter_names` order) that the fit
may move (``FitOptions.free_columns``). Fixed columns keep their starting value: the nominal
geometry, compliance 0, and for the base and tool links the closed-form alignment of the
measurement frame and marker (:func:`solver.measurement.pose.initial_parameters`).

Selectors (docs/calibration-options.md):

* classes — ``all``; ``geometry`` (every link's six local-twist components); ``joint_offsets``
  (each joint's correction about / along its own axis: the component of the twist of the link
  that places the joint along the joint screw, ``L_i · Exp(δ s_i) · Exp(s_i q) = L_i ·
  Exp(s_i (q + δ))``); ``base`` (the first link: measurement frame and robot base); ``tool``
  (the last link: tip to marker); ``compliance`` (every compliance axis);
* a link by name — a chain joint (the link that places it) or the tip frame: its six components;
* one column by name — ``<link>.<tx|ty|tz|rx|ry|rz>`` or ``compliance.<axis>``;
* shell-style patterns of those names (``arm_left_*``).

The measurement frame and the marker are unknown in every recording, so ``base`` and ``tool``
are free unless fixed explicitly: ``free = ["joint_offsets"]`` fits the joint offsets with the
measurement frame and marker, as FIGAROH's ``joint_offset`` model does.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Sequence

import numpy as np

from solver.errors import ModelError
from solver.kinematics import parameter_names
from solver.model import KinematicChain

CLASSES = ("all", "geometry", "joint_offsets", "base", "tool", "compliance")
TWIST_AXES = ("tx", "ty", "tz", "rx", "ry", "rz")


def joint_offset_column(chain: KinematicChain, joint: int) -> int:
    """The column of joint ``joint``'s offset: the component of its link's twist along the joint
    screw, which must lie along one axis of the joint frame (URDF axes along ±x, ±y or ±z;
    every DH joint); with a negative axis the offset is minus that component."""
    screw = chain.joint_screws[joint]
    axis = int(np.argmax(np.abs(screw)))
    if not np.isclose(abs(screw[axis]), 1.0, atol=1e-12):
        raise ModelError(
            f"joint_offsets: joint {chain.joint_names[joint]!r} moves about an axis that is not "
            f"one of its frame's axes ({np.round(screw, 6).tolist()}); select its link's "
            f"components by name instead (e.g. {chain.joint_names[joint]}.rz)"
        )
    return 6 * joint + axis


def _class_columns(chain: KinematicChain, name: str) -> set[int]:
    n_link_cols = 6 * chain.n_links
    total = n_link_cols + len(chain.compliance_axes)
    if name == "all":
        return set(range(total))
    if name == "geometry":
        return set(range(n_link_cols))
    if name == "joint_offsets":
        return {joint_offset_column(chain, j) for j in range(chain.n_joints)}
    if name == "base":
        return set(range(6))
    if name == "tool":
        return set(range(n_link_cols - 6, n_link_cols))
    return set(range(n_link_cols, total))  # compliance


def selector_columns(chain: KinematicChain, selector: str, option: str) -> set[int]:
    """Columns one selector names; :class:`ModelError` listing the valid names otherwise."""
    if selector in CLASSES:
        return _class_columns(chain, selector)
    names = parameter_names(chain)
    links = list(chain.link_names)
    by_link = {link: set(range(6 * i, 6 * i + 6)) for i, link in enumerate(links)}
    columns: set[int] = set()
    for link, link_columns in by_link.items():
        if fnmatch.fnmatchcase(link, selector):
            columns |= link_columns
    columns |= {i for i, name in enumerate(names) if fnmatch.fnmatchcase(name, selector)}
    if not columns:
        compliance = [n for n in names if n.startswith("compliance.")]
        raise ModelError(
            f"{option}: {selector!r} names no parameter of this chain; use a class "
            f"({', '.join(CLASSES)}), a link ({', '.join(links)}), a parameter "
            f"<link>.<{'|'.join(TWIST_AXES)}>"
            + (f" or {', '.join(compliance)}" if compliance else "")
            + " (shell patterns such as arm_* allowed)"
        )
    return columns


def free_columns(
    chain: KinematicChain, free: Sequence[str], fixed: Sequence[str]
) -> tuple[int, ...]:
    """Sorted columns the fit may move: those ``free`` selects, plus the base and tool links
    (measurement frame and marker), minus those ``fixed`` selects."""
    chosen: set[int] = set()
    for selector in free:
        chosen |= selector_columns(chain, selector, "free_parameters")
    chosen |= _class_columns(chain, "base") | _class_columns(chain, "tool")
    for selector in fixed:
        chosen -= selector_columns(chain, selector, "fixed_parameters")
    if not chosen:
        raise ModelError(
            "free_parameters / fixed_parameters leave nothing to calibrate; free at least "
            "the base or tool"
        )
    return tuple(sorted(chosen))


def fixed_names(chain: KinematicChain, columns: tuple[int, ...] | None) -> list[str]:
    """Names of the columns not in ``columns`` (None: nothing fixed)."""
    if columns is None:
        return []
    chosen = set(columns)
    return [name for i, name in enumerate(parameter_names(chain)) if i not in chosen]
