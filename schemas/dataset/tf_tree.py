"""A tf tree read from a bag: rigid transforms between named frames over time, composed along
the tree (``/tf`` and ``/tf_static``, ``tf2_msgs/TFMessage``).

An edge ``parentMchild`` is the pose of ``child`` in ``parent`` (translation m, unit quaternion
``x, y, z, w``, scalar last). A static edge is constant; a dynamic edge is known between its
first and last stamp and interpolated in between: linearly in translation, by slerp in
rotation (:func:`interpolate`); rotations are scipy's :class:`Rotation`. A frame has at most
one parent, as in tf2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from solver.errors import DatasetError


@dataclass(frozen=True)
class Edge:
    """``parentMchild`` at ``stamps_ns`` (n,), sorted: translation (n, 3) m, quaternion
    (n, 4) x,y,z,w. A static edge holds one sample and holds at every time."""

    parent: str
    child: str
    stamps_ns: NDArray[np.int64]
    translation_m: NDArray[np.float64]
    quaternion_xyzw: NDArray[np.float64]
    static: bool


@dataclass(frozen=True)
class Poses:
    """Poses at times (n,): translation (n, 3) m, quaternion (n, 4) x,y,z,w; ``valid`` (n,)
    is False where a dynamic edge on the way has no data around that time."""

    translation_m: NDArray[np.float64]
    quaternion_xyzw: NDArray[np.float64]
    valid: NDArray[np.bool_]


Placement = tuple[NDArray[np.float64], Rotation]
"""A rigid transform ``aMb`` per sample: translation (n, 3) m and the rotations (n of them)."""


def compose(aMb: Placement, bMc: Placement) -> Placement:
    """``aMc = aMb · bMc``, sample by sample."""
    (p_ab, r_ab), (p_bc, r_bc) = aMb, bMc
    return p_ab + r_ab.apply(p_bc), r_ab * r_bc


def invert(aMb: Placement) -> Placement:
    """``bMa`` from ``aMb``."""
    p, r = aMb
    r_inv = r.inv()
    return -r_inv.apply(p), r_inv


def slerp(r0: Rotation, r1: Rotation, u: NDArray[np.float64]) -> Rotation:
    """Per sample, the rotation a fraction ``u`` (n,) of the shorter arc from ``r0`` (u = 0)
    to ``r1`` (u = 1), to rounding (scipy normalises the products)."""
    return r0 * Rotation.from_rotvec(u[:, None] * (r0.inv() * r1).as_rotvec())


def interpolate(
    edge: Edge, stamps_ns: NDArray[np.int64]
) -> tuple[NDArray[np.float64], Rotation, NDArray[np.bool_]]:
    """The edge at ``stamps_ns`` (n,): translation (n, 3), rotations (n), and whether each
    time lies within the edge's stamps (always, for a static edge)."""
    n = len(stamps_ns)
    if edge.static or len(edge.stamps_ns) == 1:
        valid = np.ones(n, bool) if edge.static else stamps_ns == edge.stamps_ns[0]
        return (
            np.broadcast_to(edge.translation_m[-1], (n, 3)).copy(),
            Rotation.from_quat(np.broadcast_to(edge.quaternion_xyzw[-1], (n, 4))),
            valid,
        )
    stamps = edge.stamps_ns
    valid = (stamps_ns >= stamps[0]) & (stamps_ns <= stamps[-1])
    i = np.clip(np.searchsorted(stamps, stamps_ns, side="right") - 1, 0, len(stamps) - 2)
    span = (stamps[i + 1] - stamps[i]).astype(float)
    u = np.clip((stamps_ns - stamps[i]).astype(float) / np.where(span > 0, span, 1.0), 0.0, 1.0)
    p0, p1 = edge.translation_m[i], edge.translation_m[i + 1]
    translation = p0 + u[:, None] * (p1 - p0)
    translation = np.where((u == 0.0)[:, None], p0, translation)
    rotation = Rotation.from_quat(edge.quaternion_xyzw)
    return translation, slerp(rotation[i], rotation[i + 1], u), valid


class TfTree:
    """The tree of :class:`Edge` keyed by child frame; ``source`` names the bag in messages."""

    def __init__(self, edges: dict[str, Edge], source: str) -> None:
        self.edges = edges
        self.source = source

    @property
    def frames(self) -> list[str]:
        return sorted({e.child for e in self.edges.values()} | self.roots)

    @property
    def roots(self) -> set[str]:
        """Frames that are some edge's parent and no edge's child."""
        return {e.parent for e in self.edges.values()} - set(self.edges)

    def _to_root(self, frame: str) -> list[Edge]:
        """The edges from ``frame`` up to its tree's root (child first)."""
        path: list[Edge] = []
        while frame in self.edges and len(path) <= len(self.edges):
            path.append(self.edges[frame])
            frame = path[-1].parent
        return path

    def chain(self, parent: str, child: str) -> tuple[list[Edge], list[Edge]]:
        """The edges from the common ancestor down to ``parent`` and down to ``child``
        (``parentMchild = (ancestorMparent)⁻¹ · ancestorMchild``); :class:`DatasetError` naming
        the frames or the roots when the two are not in one tree."""
        known = self.frames
        for frame in (parent, child):
            if frame not in known:
                raise DatasetError(
                    f"{self.source}: frame {frame!r} is not in the tf tree (frames: "
                    f"{', '.join(known) or 'none'}); give two frames of /tf or /tf_static"
                )
        up_parent, up_child = self._to_root(parent), self._to_root(child)
        root_of = {
            f: (up[-1].parent if up else f) for f, up in ((parent, up_parent), (child, up_child))
        }
        if root_of[parent] != root_of[child]:
            raise DatasetError(
                f"{self.source}: frames {parent!r} and {child!r} are never connected in the tf "
                f"tree ({parent!r} is under root {root_of[parent]!r}, {child!r} under "
                f"{root_of[child]!r}; the tree's roots: {', '.join(sorted(self.roots))}); record "
                "the transform that joins the two trees, or name frames of one tree"
            )
        shared = {e.child for e in up_parent} & {e.child for e in up_child}
        return (
            [e for e in reversed(up_parent) if e.child not in shared],
            [e for e in reversed(up_child) if e.child not in shared],
        )

    def dynamic_stamps(self, parent: str, child: str) -> NDArray[np.int64]:
        """The stamps of every dynamic edge between the two frames (sorted, unique)."""
        down_parent, down_child = self.chain(parent, child)
        stamps = [e.stamps_ns for e in (*down_parent, *down_child) if not e.static]
        if not stamps:
            return np.zeros(0, np.int64)
        return np.unique(np.concatenate(stamps))

    def pose(self, parent: str, child: str, stamps_ns: NDArray[np.int64]) -> Poses:
        """``parentMchild`` at ``stamps_ns``, each dynamic edge interpolated at those times."""
        n = len(stamps_ns)
        identity: Placement = (np.zeros((n, 3)), Rotation.identity(n))
        valid = np.ones(n, bool)
        down: list[Placement] = []
        for path in self.chain(parent, child):
            pose = identity
            for edge in path:
                translation, rotation, covered = interpolate(edge, stamps_ns)
                pose = compose(pose, (translation, rotation))
                valid &= covered
            down.append(pose)
        translation, rotation = compose(invert(down[0]), down[1])
        return Poses(translation, rotation.as_quat(), valid)
