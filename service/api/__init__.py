"""The HTTP service (FastAPI): ``create_app(settings)`` builds it; ``kincal serve`` runs it."""

from service.api.app import create_app

__all__ = ["create_app"]
