"""Missing-physics discovery (issue 5): locate the mismatch, name the physics, model it.

Public API: :func:`discover` with :class:`DiscoveryOptions` on a chain and
:class:`DiscoveryData`, returning a :class:`DiscoveryResult`. The library of named effects is
:data:`EFFECTS` (:mod:`solver.discovery.library`).
"""

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
