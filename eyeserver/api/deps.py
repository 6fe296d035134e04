"""Dependencies shared by the routers."""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, TypeVar

from fastapi import Depends, Request

from eyeserver.errors import StateConflictError
from eyeserver.service.core import Service

__all__ = ["ServiceDep", "app_state", "get_service"]

_T = TypeVar("_T")


def app_state(name: str, kind: type[_T]) -> Callable[[Request], _T]:
    """A dependency giving ``app.state.<name>``, an object of ``kind`` the lifespan made; 409
    while the daemon is not running (before start-up, after shut-down)."""

    def dependency(request: Request) -> _T:
        value = getattr(request.app.state, name, None)
        if not isinstance(value, kind):
            raise StateConflictError("the daemon's service is not running")
        return value

    dependency.__name__ = f"get_{name}"
    return dependency


get_service = app_state("service", Service)
"""The daemon's :class:`Service`, opened by the lifespan."""

ServiceDep = Annotated[Service, Depends(get_service)]
