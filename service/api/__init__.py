"""The HTTP service (FastAPI): ``create_app(settings)`` builds it; ``kincal serve`` runs it.

``create_app`` is imported on first use (PEP 562): the ``kincal serve`` supervisor
(:mod:`service.jobs.supervisor`) lives in this package and must not import the web app and the
solver (≈ 350 MB and seconds) just to start its children."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from service.api.app import create_app


def __getattr__(name: str) -> Any:
    if name == "create_app":
        from service.api.app import create_app

        return create_app
    raise AttributeError(f"module 'service.api' has no attribute {name!r}")


__all__ = ["create_app"]
