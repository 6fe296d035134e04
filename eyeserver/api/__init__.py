"""The HTTP API: a FastAPI app built by :func:`create_app`, versioned under ``/api/v1``."""

from eyeserver.api.app import API_PREFIX, create_app

__all__ = ["API_PREFIX", "create_app"]
