"""The HTTP service (FastAPI): ``create_app(settings)`` builds it; ``kincal serve`` runs it.

``create_app`` is imported on first use (PEP 562): the ``kincal serve`` supervisor
(:mod:`service.jobs.supervisor`) lives in this package and must not import the web app and the
solver (≈ 350 MB and seconds) just to start its children."""

from __future__ import annotations

from typing import TYPE_CHECKING

from solver.lazy_exports import lazy_exports

if TYPE_CHECKING:
    from service.api.app import create_app

__getattr__ = lazy_exports(__name__, {"create_app": "app"})


__all__ = ["create_app"]
