"""A package's public names imported from its modules on first use (PEP 562), so that importing
the package, or a light module of it, does not pay for its heavy ones (pandas, the discovery
loop, the web app) at start-up."""

from __future__ import annotations

import importlib
from collections.abc import Callable, Mapping
from typing import Any


def lazy_exports(package: str, homes: Mapping[str, str]) -> Callable[[str], Any]:
    """The module ``__getattr__`` of ``package``: a name of ``homes`` (name → module of the
    package that defines it) is imported from ``package.<module>`` when first asked for; any
    other name raises AttributeError, as a missing attribute does.

    Usage, in the package's ``__init__``: ``__getattr__ = lazy_exports(__name__, _HOME)``, with
    the same names imported under ``typing.TYPE_CHECKING`` for the type checker."""

    def __getattr__(name: str) -> Any:
        if name not in homes:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(f"{package}.{homes[name]}"), name)

    return __getattr__
