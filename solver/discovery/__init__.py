"""Missing-physics discovery (issue 5): locate the mismatch, name the physics, model it.

Public API: :func:`discover` with :class:`DiscoveryOptions` on a chain and
:class:`DiscoveryData`, returning a :class:`DiscoveryResult`. The library of named effects is
:data:`EFFECTS` (:mod:`solver.discovery.library`).
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from solver.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from solver.discovery.features import DiscoveryData
    from solver.discovery.library import EFFECTS, Term
    from solver.discovery.loop import DiscoveryOptions, discover
    from solver.discovery.results import (
        Ambiguity,
        DiscoveryResult,
        Finding,
        HeldoutError,
        RandomEffect,
        Unexplained,
    )

_HOME = {
    "DiscoveryData": "features",
    "EFFECTS": "library",
    "Term": "library",
    "DiscoveryOptions": "loop",
    "discover": "loop",
    **dict.fromkeys(
        ["Ambiguity", "DiscoveryResult", "Finding", "HeldoutError", "RandomEffect", "Unexplained"],
        "results",
    ),
}
"""Where each public name lives. They are imported on first use (PEP 562), so a calibration
that only carries a discovery's model (:mod:`solver.discovery.carry`) does not pay for the
discovery loop's imports at start-up."""


__getattr__ = lazy_exports(__name__, _HOME)


__all__ = [
    "EFFECTS",
    "Ambiguity",
    "DiscoveryData",
    "DiscoveryOptions",
    "DiscoveryResult",
    "Finding",
    "HeldoutError",
    "RandomEffect",
    "Term",
    "Unexplained",
    "discover",
]
