"""Dependencies shared by the routers."""

from __future__ import annotations

from typing import Annotated

from fastapi import Depends, Request

from eyeserver.errors import StateConflictError
from eyeserver.service.core import Service

__all__ = ["ServiceDep", "get_service"]


def get_service(request: Request) -> Service:
    """The daemon's :class:`Service`, opened by the lifespan."""
    service = getattr(request.app.state, "service", None)
    if not isinstance(service, Service):
        raise StateConflictError("the daemon's service is not running")
    return service


ServiceDep = Annotated[Service, Depends(get_service)]
